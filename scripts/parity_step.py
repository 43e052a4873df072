"""Joint-level sim-to-HIL parity: the same open-loop set-point steps (every finger +1 rad
at 0.2 s, back at 1.2 s; arm joint1 +0.3 rad and joint4 -0.3 rad at 0.5 s, from the
pre-grasp pose, clear of the object) in the simulated station and in HIL (camera "sim").
Prints, per joint group, the fastest measured joint speed and the largest and final
difference between the two trajectories; both follow the set-point limits of `--config`.

    .venv/bin/python scripts/parity_step.py [--config hil] [--horizon 100]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from dexdrake import argtypes


def trajectory(config: str, mode: str, steps: int) -> np.ndarray:
    """Measured joint positions (steps x n, policy order) under the step commands."""
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import load_scenario, simulated
    from dexdrake.systems.station import make_station

    scenario = load_scenario(config)
    scenario.drivers.camera.kind = "sim"
    if mode == "sim":
        scenario = simulated(scenario)
    qs: list[np.ndarray] = []
    with make_station(scenario) as station:
        hand = station.hand
        n_arm, q0 = len(hand.arm_joints), hand.pregrasp_vector()
        lo, hi = hand.joint_limits()
        arm = np.zeros(hand.num_actuators)
        arm[[hand.policy_joints.index("joint1"), hand.policy_joints.index("joint4")]] = [0.3, -0.3]

        def controller(t, hand_state, object_pose):
            qs.append(hand_state[: hand.num_actuators].copy())
            q = q0 + (arm if t >= 0.5 else 0.0)
            if 0.2 <= t < 1.2:
                q[n_arm:] += 1.0
            return np.clip(q, lo, hi)

        run_station_episode(station, controller, steps)
    return np.array(qs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="hil")
    parser.add_argument("--horizon", type=argtypes.steps, default=100, help=argtypes.horizon_help())
    args = parser.parse_args()
    from dexdrake.hands.description import load_hand
    from dexdrake.systems.scenario import load_scenario

    scenario = load_scenario(args.config)
    n_arm = len(load_hand(scenario.hand).arm_joints)
    sim, hil = trajectory(args.config, "sim", args.horizon), trajectory(args.config, "hil", args.horizon)
    k = min(len(sim), len(hil))
    sim, hil = sim[:k], hil[:k]
    print(f"set-point steps, {k} control steps of {scenario.control_period * 1e3:.0f} ms ({args.config})")
    for name, cols in (("arm", slice(0, n_arm)), ("fingers", slice(n_arm, None))):
        speed = [np.abs(np.diff(q[:, cols], axis=0)).max() / scenario.control_period for q in (sim, hil)]
        diff = np.abs(hil[:, cols] - sim[:, cols])
        print(f"  {name:8s} max speed sim {speed[0]:.2f} rad/s, hil {speed[1]:.2f} rad/s; |hil - sim| "
              f"max {diff.max():.3f} rad (step {int(diff.max(axis=1).argmax())}), final {diff[-1].max():.3f} rad")
    print(f"command: .venv/bin/python scripts/parity_step.py --config {args.config} --horizon {args.horizon}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
