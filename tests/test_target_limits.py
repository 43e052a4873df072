"""The drivers' set-point limits and overspeed trip modelled in simulation (systems/target_limits.py)."""

from pathlib import Path

import numpy as np
import pytest

from dexdrake.systems.scenario import load_scenario

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _limits(max_rate, feedforward=(False, False), paced=(False, False)):
    from dexdrake.systems.target_limits import TargetLimits

    return TargetLimits(np.array([-1.0, -1.0]), np.array([1.0, 1.0]), np.array(max_rate, float),
                        np.array(feedforward), np.array(paced))


def test_limiter_clamps_then_follows_at_the_rate_from_the_measured_start():
    from pydrake.systems.analysis import Simulator

    from dexdrake.systems.target_limits import TargetLimiter

    limiter = TargetLimiter(_limits([2.0, 0.5]), period=0.01, command_period=0.02)
    simulator = Simulator(limiter)
    context = simulator.get_mutable_context()
    limiter.GetInputPort("hand_state").FixValue(context, [0.2, -0.1, 0.0, 0.0])
    limiter.GetInputPort("command").FixValue(context, [5.0, -0.1])  # beyond the upper limit
    simulator.Initialize()
    target = limiter.GetOutputPort("target")
    np.testing.assert_allclose(target.Eval(context), [0.2, -0.1])
    simulator.AdvanceTo(0.2)
    np.testing.assert_allclose(target.Eval(context), [0.6, -0.1], atol=1e-9)
    limiter.GetInputPort("command").FixValue(context, [5.0, -3.0])
    simulator.AdvanceTo(1.0)
    np.testing.assert_allclose(target.Eval(context), [1.0, -0.5], atol=1e-9)
    # no velocity feed-forward asked for: the PD's desired velocity stays zero
    np.testing.assert_allclose(limiter.GetOutputPort("desired_state").Eval(context), [1.0, -0.5, 0.0, 0.0], atol=1e-9)


def test_limiter_feeds_the_ramps_velocity_forward_where_the_driver_does():
    """The Z1 client sends its reference's velocity with it (W) when velocity_feedforward
    is on; the simulated PD gets the same desired velocity on those joints only."""
    from pydrake.systems.analysis import Simulator

    from dexdrake.systems.target_limits import TargetLimiter

    limiter = TargetLimiter(_limits([2.0, 2.0], feedforward=[True, False]), period=0.01, command_period=0.02)
    simulator = Simulator(limiter)
    context = simulator.get_mutable_context()
    limiter.GetInputPort("hand_state").FixValue(context, [0.0, 0.0, 0.0, 0.0])
    limiter.GetInputPort("command").FixValue(context, [0.5, 0.5])
    simulator.Initialize()
    desired = limiter.GetOutputPort("desired_state")
    np.testing.assert_allclose(desired.Eval(context), [0.0, 0.0, 0.0, 0.0])
    simulator.AdvanceTo(0.1)  # ramping at 2 rad/s
    np.testing.assert_allclose(desired.Eval(context), [0.2, 0.2, 2.0, 0.0], atol=1e-9)
    simulator.AdvanceTo(0.5)  # arrived: at rest
    np.testing.assert_allclose(desired.Eval(context), [0.5, 0.5, 0.0, 0.0], atol=1e-9)


def test_paced_joints_follow_each_command_evenly_over_the_command_period():
    """A small step on a paced joint (the Z1 client with command_period_s) is spread over the
    command period at a constant fed-forward velocity, not taken at the rate limit in one
    tick; a step too large for the period still goes no faster than the limit."""
    from pydrake.systems.analysis import Simulator

    from dexdrake.systems.target_limits import TargetLimiter

    limiter = TargetLimiter(_limits([2.0, 2.0], feedforward=[True, True], paced=[True, False]),
                            period=0.005, command_period=0.02)
    simulator = Simulator(limiter)
    context = simulator.get_mutable_context()
    limiter.GetInputPort("hand_state").FixValue(context, [0.0, 0.0, 0.0, 0.0])
    limiter.GetInputPort("command").FixValue(context, [0.0, 0.0])
    simulator.Initialize()
    limiter.GetInputPort("command").FixValue(context, [0.01, 0.01])
    desired = limiter.GetOutputPort("desired_state")
    simulator.AdvanceTo(0.001)  # one tick (t = 0): paced 0.01 / 0.02 s = 0.5 rad/s; unpaced at the 2 rad/s limit, done
    np.testing.assert_allclose(desired.Eval(context), [0.0025, 0.01, 0.5, 2.0], atol=1e-9)
    simulator.AdvanceTo(0.011)  # three ticks: the paced joint still moving at the same rate
    np.testing.assert_allclose(desired.Eval(context), [0.0075, 0.01, 0.5, 0.0], atol=1e-9)
    simulator.AdvanceTo(0.021)  # arrived at the fourth tick, at rest from the fifth
    np.testing.assert_allclose(desired.Eval(context), [0.01, 0.01, 0.0, 0.0], atol=1e-9)
    limiter.GetInputPort("command").FixValue(context, [0.51, 0.51])  # 25 rad/s over the period: capped at 2
    simulator.AdvanceTo(0.026)
    np.testing.assert_allclose(desired.Eval(context), [0.02, 0.02, 2.0, 2.0], atol=1e-9)


def test_limits_and_rates_are_the_drivers():
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.z1_model import z1_model
    from dexdrake.systems.target_limits import target_limits

    scenario = load_scenario(CONFIGS / "hil.yaml")
    hand = load_hand(scenario.hand)
    lower, upper, rate, feedforward, paced = target_limits(scenario, hand)
    n_arm = len(hand.arm_joints)
    np.testing.assert_allclose(rate[n_arm:], scenario.drivers.hand.max_target_rate)
    assert np.all(rate[:n_arm] == rate[0]) and 0 < rate[0] <= z1_model().limits.velocity.min()
    lo, hi = hand.joint_limits()
    np.testing.assert_allclose(lower, lo)
    np.testing.assert_allclose(upper, hi)
    # the Z1 config's velocity feed-forward (configs/hil.yaml: on, as in training's scenario)
    on = [True] * n_arm + [False] * (hand.num_actuators - n_arm)
    assert feedforward.tolist() == on and scenario.drivers.arm.velocity_feedforward is True
    assert paced.tolist() == on  # the Z1 client follows each target over the control period
    scenario.drivers.arm.velocity_feedforward = False
    assert not target_limits(scenario, hand).velocity_feedforward.any()
    scenario.drivers.arm.velocity_feedforward = None  # the driver's default: on
    assert target_limits(scenario, hand).velocity_feedforward.tolist() == on
    scenario.drivers.hand.max_target_rate = 1.5
    assert np.all(target_limits(scenario, hand).max_rate[n_arm:] == 1.5)
    adroit = load_hand("adroit")  # no drivers: the model's joint limits, no rate limit, no pacing
    assert np.all(np.isinf(target_limits(scenario, adroit).max_rate))
    assert not target_limits(scenario, adroit).paced.any()


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


def test_overspeed_trips_on_a_fast_joint_or_a_fast_window_mean():
    """A window-0 joint trips on its velocity at once; a windowed joint on its mean speed
    over a full window only (a short burst inside a slow window does not trip)."""
    from pydrake.systems.analysis import Simulator

    from dexdrake.errors import StationFault
    from dexdrake.systems.target_limits import OverspeedMonitor

    monitor = OverspeedMonitor(speed=[2.0, 2.0], window=[0.0, 0.1], period=0.01, names=["arm", "finger"])
    simulator = Simulator(monitor)
    context = simulator.get_mutable_context()
    port = monitor.GetInputPort("hand_state")
    port.FixValue(context, [0.0, 0.0, 1.9, 0.0])
    simulator.Initialize()
    simulator.AdvanceTo(0.05)
    port.FixValue(context, [0.0, 0.1, 1.9, 50.0])  # 0.1 rad within the window: 1 rad/s mean
    simulator.AdvanceTo(0.25)
    port.FixValue(context, [0.0, 0.4, 1.9, 0.0])  # 0.3 rad more in the next window: 3 rad/s
    with pytest.raises(StationFault, match="finger at 3.00 rad/s"):
        simulator.AdvanceTo(0.5)
    monitor2 = OverspeedMonitor(speed=[2.0, 2.0], window=[0.0, 0.1], period=0.01, names=["arm", "finger"])
    simulator = Simulator(monitor2)
    context = simulator.get_mutable_context()
    monitor2.GetInputPort("hand_state").FixValue(context, [0.0, 0.0, -2.1, 0.0])
    with pytest.raises(StationFault, match="arm at 2.10 rad/s"):
        simulator.AdvanceTo(0.02)


def test_overspeed_limits_are_the_drivers():
    from dexdrake.hands.description import load_hand
    from dexdrake.hardware.allegro_can import AllegroConfig, check_allegro_config
    from dexdrake.hardware.safety import OVERSPEED_TOLERANCE
    from dexdrake.hardware.z1_model import z1_model
    from dexdrake.systems.target_limits import overspeed_limits

    scenario = load_scenario(CONFIGS / "hil.yaml")
    hand = load_hand(scenario.hand)
    speed, window = overspeed_limits(scenario, hand)
    n_arm, perm = len(hand.arm_joints), hand.hardware_permutation()
    np.testing.assert_allclose(speed[:n_arm], z1_model().limits.velocity * (1 + OVERSPEED_TOLERANCE))
    assert np.all(window[:n_arm] == 0)
    np.testing.assert_allclose(speed[perm], check_allegro_config(AllegroConfig()).max_measured_velocity
                               * (1 + OVERSPEED_TOLERANCE))
    assert np.all(window[perm] == AllegroConfig().velocity_window_s)
    assert overspeed_limits(scenario, load_hand("adroit")) is None  # no drivers, no trip


def test_an_overspeed_ends_the_training_env_episode_as_a_driver_fault():
    from dexdrake.systems.env_factory import GraspEnvFactory

    env = GraspEnvFactory("allegro_z1", None, ("can_soda",), 10)()
    env.reset(0)
    n, n_arm = env.action_dim, len(env.scene.hand.arm_joints)
    state = env.hand_state()
    state[n + n_arm - 1] = 10.0  # the last arm joint swinging at 10 rad/s
    env.mirror(state, env.object_pose())
    _, _, done, info = env.step_positions(state[:n])
    assert done and not info["success"] and "overspeed: joint6" in info["fault"]
    assert np.isfinite(info["lift"])
    env.reset(1)  # the next episode runs
    assert "fault" not in env.step_positions(env.hand_state()[:n])[3]
