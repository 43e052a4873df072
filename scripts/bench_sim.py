"""Simulation speed of the Adroit grasp scene during a scripted grasp, on one core.

Prints, per plant time step, control steps per second (50 Hz control), plant steps per
second and simulated seconds per second, with the ratio to MuJoCo stepping the paper's
Adroit relocate scene measured in the same run (optional `bench` extra; see
`mujoco_peer.py`). Rates are per second of this process's CPU time (wall time is printed
too: on a shared machine it is inflated by other processes; the load average is printed).

    python scripts/bench_sim.py [--object sphere_medium] [--episodes 2] [--horizon 150]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

from dexdrake import argtypes

os.environ.setdefault("OMP_NUM_THREADS", "1")

TIME_STEPS = (0.002, 0.005, 0.01)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--object", default="sphere_medium")
    parser.add_argument("--episodes", type=int, default=2, help="episodes of the one object (seeds 0..N-1)")
    parser.add_argument("--horizon", type=argtypes.steps, default=150, help=argtypes.horizon_help())
    args = parser.parse_args()

    import mujoco_peer
    import torch

    torch.set_num_threads(1)
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    print(f"hand={args.hand} object={args.object} episodes={args.episodes} x {args.horizon} control steps (50 Hz)")
    print(f"load average {os.getloadavg()[0]:.1f}")
    peer = mujoco_peer.measure_relocate()
    if peer is None:
        print("MuJoCo peer: not measured (install the optional extra: pip install -e '.[bench]')")
    else:
        print(f"MuJoCo peer ({peer.version}, Adroit relocate, dt 2 ms): {peer.sim_s_per_cpu_s:.1f} simulated s per CPU-s")
    print(f"{'plant dt (ms)':>14}{'control steps/s':>17}{'plant steps/s':>15}{'sim s/s':>9}{'vs MuJoCo':>11}"
          f"{'wall s':>8}{'success':>9}")
    for dt in TIME_STEPS:
        env = GraspEnv(replace(training_scenario(args.hand, args.object), time_step=dt), horizon=args.horizon)
        env.rollout(ScriptedGrasp, seed=0)  # warm-up (first-use allocations)
        start, cpu_start, successes = time.perf_counter(), time.process_time(), 0
        for seed in range(args.episodes):
            successes += env.rollout(ScriptedGrasp, seed=seed).success
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        control = args.episodes * args.horizon / cpu
        plant = control * env.scenario.control_period / dt
        sim_rate = control * env.scenario.control_period
        ratio = f"{sim_rate / peer.sim_s_per_cpu_s:>10.3f}x" if peer else f"{'-':>11}"
        print(f"{dt * 1e3:>14.1f}{control:>17.1f}{plant:>15.0f}{sim_rate:>9.2f}{ratio}{wall:>8.1f}"
              f"{successes:>6}/{args.episodes}")


if __name__ == "__main__":
    main()
