"""CPU per arm IK solve (`ArmIK.solve`, the expert's way-points: bounded Levenberg-Marquardt
with the analytic Jacobian) against scipy's least_squares on the same residual with
finite-difference Jacobians, in one run.

Both solve the same random grasp-centre targets around the pre-grasp pose (palm rotation
kept), interleaved target by target, from the pre-grasp arm; prints ms per solve
(time.process_time), the ratio, and the largest difference between the two solutions.
Run: python scripts/bench_arm_ik.py [--hand adroit] [--targets 200] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--targets", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from scipy.optimize import least_squares

    from dexdrake.hands.arm_ik import ArmIK
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scene import build_grasp_scene

    scene = build_grasp_scene(training_scenario(args.hand, "sphere_small"))
    ik = ArmIK(scene)
    q0 = np.clip(scene.hand.pregrasp_vector()[: ik.n_arm], ik.lo, ik.hi)
    p0, R0 = ik.palm_pose(q0)
    rng = np.random.default_rng(args.seed)
    targets = p0 + rng.uniform([-0.15, -0.15, -0.15], [0.15, 0.15, 0.05], size=(args.targets, 3))
    margin = 1e-3 * (ik.hi - ik.lo)
    start = np.clip(q0, ik.lo + margin, ik.hi - margin)

    def scipy_solve(target):  # the peer: solve's problem, scipy's trust-region solver and Jacobian
        return least_squares(ik.residual, start, bounds=(ik.lo, ik.hi), xtol=1e-8, args=(target, R0, 0.0, q0)).x

    cpu, gap = {"ArmIK.solve": 0.0, "scipy least_squares": 0.0}, 0.0
    for target in targets:
        t = time.process_time()
        q_a = ik.solve(target, q0, R0)
        cpu["ArmIK.solve"] += time.process_time() - t
        t = time.process_time()
        q_f = scipy_solve(target)
        cpu["scipy least_squares"] += time.process_time() - t
        gap = max(gap, float(np.max(np.abs(q_a - q_f))))
    for name, total in cpu.items():
        print(f"{name:20s} {1e3 * total / len(targets):6.2f} ms per solve")
    print(f"ArmIK.solve: {cpu['scipy least_squares'] / cpu['ArmIK.solve']:.2f}x cheaper; "
          f"largest joint difference between the solutions {gap:.1e}")


if __name__ == "__main__":
    main()
