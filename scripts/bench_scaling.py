"""Labelled-step throughput of DAgger collection with 1 and 2 workers, local processes and Ray.

    python scripts/bench_scaling.py [--objects sphere_medium,mug] [--episodes 8] [--horizon 50]
                                    [--backends process,ray] [--workers 1,2]

Each row: a fresh sampler of the backend, one episode per worker to build the envs (not
timed), then `--episodes` expert-driven DAgger episodes (the expert labels every step; the
work of `dexdrake train dagger`'s first iteration). Printed per row: labelled steps per
wall-clock second, the parallel efficiency (that rate over workers x the same backend's
1-worker rate: the baseline measured in this run), steps per worker CPU-second (CPU time
measured in the workers around each episode), its ratio to the 1-worker figure (the CPU
efficiency: what each worker loses to running beside the others) and the driver's CPU
seconds. The load average is printed with each row: wall-clock rates depend on it, and on a
shared Linux machine with autogrouped scheduling (/proc/sys/kernel/sched_autogroup_enabled)
one command's processes share one fair slice, so extra workers cannot raise its wall rate;
per-CPU-second rates hold. `measure_scaling` and `print_scaling` can be called from other
benchmarks.
"""

from __future__ import annotations

import argparse
import os
import time
from functools import partial


def measure_scaling(objects: list[str], episodes: int = 8, horizon: int = 50, backends=("process", "ray"),
                    worker_counts=(1, 2), hand: str = "adroit", feature_set: str = "DexRep") -> list[dict]:
    """One row per (backend, workers): expert-driven DAgger episodes timed after a warm-up."""
    from dexdrake.learn.dagger import DaggerData, dagger_job
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    factory = GraspEnvFactory(hand, feature_set, tuple(objects), horizon)
    jobs = [(objects[k % len(objects)], 1000 + k) for k in range(episodes)]
    rows = []
    for backend in backends:
        for workers in worker_counts:
            with make_sampler(factory, backend, workers) as sampler:
                sampler.map(partial(dagger_job, ReactiveGrasp, 0.0), None, [(objects[0], k) for k in range(workers)])  # env builds
                cpu0, driver0, wall0 = sampler.episode_cpu_s, time.process_time(), time.perf_counter()
                data = DaggerData.concat(sampler.map(partial(dagger_job, ReactiveGrasp, 0.0), None, jobs))
                wall = time.perf_counter() - wall0
                rows.append({"backend": backend, "workers": workers, "steps": len(data.labels), "wall_s": wall,
                             "worker_cpu_s": sampler.episode_cpu_s - cpu0, "driver_cpu_s": time.process_time() - driver0,
                             "load": os.getloadavg()[0]})
    for row in rows:
        one = next(r for r in rows if r["backend"] == row["backend"] and r["workers"] == min(worker_counts))
        row["steps_per_s"] = row["steps"] / row["wall_s"]
        row["efficiency"] = row["steps_per_s"] / (row["workers"] / one["workers"] * one["steps"] / one["wall_s"])
        row["steps_per_cpu_s"] = row["steps"] / row["worker_cpu_s"]
        row["cpu_efficiency"] = row["steps_per_cpu_s"] / (one["steps"] / one["worker_cpu_s"])
    return rows


def print_scaling(rows: list[dict], command: str) -> None:
    """The rows as a markdown table, headed by the command that made them."""
    print(f"`{command}` on {os.cpu_count()} cores\n")
    print("| backend | workers | labelled steps | wall s | steps/s (wall) | parallel efficiency (wall) | "
          "steps per worker-CPU-s | efficiency (CPU) | driver CPU s | load avg (1 min) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['backend']} | {r['workers']} | {r['steps']} | {r['wall_s']:.1f} | {r['steps_per_s']:.1f} | "
              f"{r['efficiency']:.0%} | {r['steps_per_cpu_s']:.1f} | {r['cpu_efficiency']:.0%} | "
              f"{r['driver_cpu_s']:.1f} | {r['load']:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", default="sphere_medium,mug")
    parser.add_argument("--episodes", type=int, default=8, help="episodes in all, the objects in turn")
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--backends", default="process,ray")
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts; the first is the baseline")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f}")
    rows = measure_scaling(args.objects.split(","), args.episodes, args.horizon, tuple(args.backends.split(",")),
                           tuple(int(w) for w in args.workers.split(",")))
    command = (f"python scripts/bench_scaling.py --objects {args.objects} --episodes {args.episodes} "
               f"--horizon {args.horizon} --backends {args.backends} --workers {args.workers}")
    print_scaling(rows, command)


if __name__ == "__main__":
    main()
