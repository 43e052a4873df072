"""CPU cost of one expert (ReactiveGrasp) label, against a full IK solve of the same lift, in one run.

    python scripts/bench_expert_label.py [--objects sphere_small,can_soda,box_cube,bottle_wine,cylinder_lying,egg_large]
        [--seeds 3] [--horizon 150]

Each episode is driven by `ReactiveGrasp` (the expert: lift set-points from a few
Jacobian steps); on every visited state a twin expert whose lift runs the full least-squares
IK (`ArmIK.solve`, the previous method) labels the same state. Prints ms per label
(time.process_time) of both, their ratio, the phases' shares and how often and where the two
labels differ (normalised action units).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", default="sphere_small,can_soda,box_cube,bottle_wine,cylinder_lying,egg_large")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--horizon", type=int, default=150)
    args = parser.parse_args()

    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp
    from dexdrake.systems.env_factory import training_scenario

    class FullIKExpert(ReactiveGrasp):
        """The expert with an IK solve for every lift label."""

        def _lift(self, q_arm: np.ndarray, p_obj: np.ndarray, lifted: bool) -> np.ndarray:
            target, R = self.lift_target(q_arm, p_obj, lifted)
            return self.ik.solve(target, q_arm, R)

    cpu = {"jacobian": 0.0, "full IK": 0.0}
    phases, labels, worst, apart = Counter(), 0, (0.0, ""), Counter()
    for name in args.objects.split(","):
        env = GraspEnv(training_scenario("adroit", name), horizon=args.horizon)
        for seed in range(args.seeds):
            env.reset(seed)
            env.fingertip_distances()  # as after every env step (the reward's query, shared with the label)
            expert, twin = ReactiveGrasp(env), FullIKExpert(env)
            for _ in range(args.horizon):
                start = time.process_time()
                q = expert(env)
                middle = time.process_time()
                q_twin = twin(env)
                cpu["jacobian"] += middle - start
                cpu["full IK"] += time.process_time() - middle
                phases[expert.phase] += 1
                labels += 1
                gap = float(np.max(np.abs(env.normalise(q) - env.normalise(q_twin))))
                worst = max(worst, (gap, f"{name} seed {seed} {expert.phase}/{twin.phase}"))
                apart[expert.phase] += gap > 0.05
                env.step_positions(q)
    new, old = (1e3 * cpu[k] / labels for k in ("jacobian", "full IK"))
    print(f"{labels} labels ({', '.join(f'{k} {100 * v / labels:.0f} %' for k, v in phases.most_common())})")
    print(f"expert label, Jacobian steps: {new:.2f} ms")
    print(f"expert label, full IK (peer): {old:.2f} ms")
    print(f"speed-up: {old / new:.1f}x")
    print(f"labels more than 0.05 apart (normalised action units): {dict(apart)}; largest {worst[0]:.3f} ({worst[1]})")


if __name__ == "__main__":
    main()
