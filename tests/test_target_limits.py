"""The drivers' set-point limits modelled in simulation (systems/target_limits.py)."""

from pathlib import Path

import numpy as np
import pytest

from dexdrake.systems.scenario import load_scenario

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_limiter_clamps_then_follows_at_the_rate_from_the_measured_start():
    from pydrake.systems.analysis import Simulator

    from dexdrake.systems.target_limits import TargetLimiter

    limiter = TargetLimiter(lower=[-1.0, -1.0], upper=[1.0, 1.0], max_rate=[2.0, 0.5], period=0.01)
    simulator = Simulator(limiter)
    context = simulator.get_mutable_context()
    limiter.GetInputPort("hand_state").FixValue(context, [0.2, -0.1, 0.0, 0.0])
    limiter.GetInputPort("command").FixValue(context, [5.0, -0.1])  # beyond the upper limit
    simulator.Initialize()
    np.testing.assert_allclose(limiter.get_output_port().Eval(context), [0.2, -0.1])
    simulator.AdvanceTo(0.2)
    np.testing.assert_allclose(limiter.get_output_port().Eval(context), [0.6, -0.1], atol=1e-9)
    limiter.GetInputPort("command").FixValue(context, [5.0, -3.0])
    simulator.AdvanceTo(1.0)
    np.testing.assert_allclose(limiter.get_output_port().Eval(context), [1.0, -0.5], atol=1e-9)


def test_limits_and_rates_are_the_drivers():
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.z1_model import z1_model
    from dexdrake.systems.target_limits import target_limits

    scenario = load_scenario(CONFIGS / "hil.yaml")
    hand = load_hand(scenario.hand)
    lower, upper, rate = target_limits(scenario, hand)
    n_arm = len(hand.arm_joints)
    np.testing.assert_allclose(rate[n_arm:], scenario.drivers.hand.max_target_rate)
    assert np.all(rate[:n_arm] == rate[0]) and 0 < rate[0] <= z1_model().limits.velocity.min()
    lo, hi = hand.joint_limits()
    np.testing.assert_allclose(lower, lo)
    np.testing.assert_allclose(upper, hi)
    scenario.drivers.hand.max_target_rate = 1.5
    assert np.all(target_limits(scenario, hand)[2][n_arm:] == 1.5)
    adroit = load_hand("adroit")  # no drivers: the model's joint limits, no rate limit
    assert np.all(np.isinf(target_limits(scenario, adroit)[2]))


def test_sim_station_moves_fingers_no_faster_than_the_hil_drivers_allow():
    """A set-point jump reaches the simulated hand as the drivers' ramp, not as a step."""
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.station import make_station

    scenario = load_scenario(CONFIGS / "sim.yaml")
    scenario.policy = None
    station = make_station(scenario)
    hand = station.hand
    j = hand.policy_joints.index("joint_5.0")
    seen = []

    def controller(t, hand_state, object_pose):
        seen.append(hand_state[j])
        q = hand_state[: hand.num_actuators].copy() if not seen[1:] else controller.q
        controller.q = q
        out = q.copy()
        out[j] += 1.0
        return out

    run_station_episode(station, controller, 30)
    rate = 3.0  # configs/sim.yaml: the Allegro driver's default max_target_rate
    speeds = np.diff(seen) / scenario.control_period
    assert speeds.max() <= rate * 1.1, f"finger moved at {speeds.max():.2f} rad/s"
    assert seen[-1] - seen[0] == pytest.approx(1.0, abs=0.05)  # and it gets there
