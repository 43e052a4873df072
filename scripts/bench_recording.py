"""What a rerun recording costs: CPU per control step of a scripted grasp in simulation,
recorded (`systems/rerun_logger.RerunLogger`, mode sim, to an .rrd in a temporary folder)
and not recorded, measured in the same run; prints both and their ratio. Times are this
process's CPU time per control step (time.process_time; the recorder's own threads count).

    python scripts/bench_recording.py [--hand adroit] [--object sphere_medium] [--horizon 150] [--episodes 2]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from dexdrake import argtypes

os.environ.setdefault("OMP_NUM_THREADS", "1")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--object", default="sphere_medium")
    parser.add_argument("--horizon", type=argtypes.steps, default=150, help=argtypes.horizon_help())
    parser.add_argument("--episodes", type=int, default=2, help="episodes of the one object (seeds 0..N-1)")
    args = parser.parse_args()

    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.rerun_logger import RerunLogger
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    env = GraspEnv(training_scenario(args.hand, args.object), horizon=args.horizon)
    env.rollout(ScriptedGrasp, 0)  # warm-up: scene built, caches filled
    plain = recorded = 0.0
    with tempfile.TemporaryDirectory() as folder:
        for seed in range(args.episodes):
            start = time.process_time()
            env.rollout(ScriptedGrasp, seed)
            plain += time.process_time() - start
            start = time.process_time()
            logger = RerunLogger(Path(folder) / f"s{seed}.rrd", "sim")
            env.rollout(ScriptedGrasp, seed, logger=logger)
            logger.close()
            recorded += time.process_time() - start
        size = sum(p.stat().st_size for p in Path(folder).glob("*.rrd")) / args.episodes
    steps = args.episodes * args.horizon
    print(f"hand={args.hand} object={args.object} episodes={args.episodes} x {args.horizon} control steps; "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"not recorded: {1e3 * plain / steps:.2f} ms CPU per control step")
    print(f"recorded:     {1e3 * recorded / steps:.2f} ms CPU per control step "
          f"({recorded / plain:.1f}x; {size / 1e6:.1f} MB per episode)")


if __name__ == "__main__":
    main()
