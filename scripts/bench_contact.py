"""The plant's discrete contact approximations on the SAP solver side by side: what an
expert-driven env step costs and how often the grasp expert succeeds under each, in one run.

    python scripts/bench_contact.py [--hand adroit] [--split train] [--seeds 10] [--workers 2]
        [--approximations sap,similar,lagged] [--out models/weights/contact_approximations.md]

Each approximation (systems/scenario.py CONTACT_APPROXIMATIONS) runs the grasp expert
(ReactiveGrasp) on every object of the split at seeds 0..N-1 and the evaluation's horizon
(as `dexdrake expert table`) in the training scenario with only `contact_approximation`
changed. Per approximation: the
expert's success with its 95 % Wilson interval, episodes that diverged, and CPU ms per env step
(plant, features, reward and expert: the whole step) with its ratio to the first
approximation's, measured in the same run on the same episodes.
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
import sys
import time
from collections import defaultdict
from pathlib import Path

from tqdm import tqdm


def _run(job: tuple[str, str, str, int]) -> tuple[str, str, list[bool], int, int, float]:
    """(approximation, object, successes per seed, diverged episodes, env steps, CPU s)."""
    hand, approximation, name, seeds = job
    from dexdrake.eval.evaluate import EVAL_HORIZON
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    scenario = dataclasses.replace(training_scenario(hand, name), contact_approximation=approximation)
    env = GraspEnv(scenario, horizon=EVAL_HORIZON)
    ok, diverged, steps, cpu = [], 0, 0, 0.0
    for seed in range(seeds):
        start = time.process_time()
        result = env.rollout(ReactiveGrasp, seed)
        cpu += time.process_time() - start
        ok.append(result.success)
        diverged += result.fault is not None
        steps += result.steps
    return approximation, name, ok, diverged, steps, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--split", default="train")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--approximations", default="sap,similar,lagged")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()

    from dexdrake.eval.evaluate import wilson_interval
    from dexdrake.objects.library import list_objects
    from dexdrake.systems.scenario import CONTACT_APPROXIMATIONS

    approximations = args.approximations.split(",")
    unknown = [a for a in approximations if a not in CONTACT_APPROXIMATIONS]
    if unknown:
        sys.exit(f"bench_contact: unknown approximations {unknown}; valid: {', '.join(CONTACT_APPROXIMATIONS)}")
    names = [o.name for o in list_objects(args.split)]
    jobs = [(args.hand, a, n, args.seeds) for n in names for a in approximations]  # interleaved: same load
    ok, diverged, steps, cpu = defaultdict(list), defaultdict(int), defaultdict(int), defaultdict(float)
    start = time.perf_counter()
    with mp.get_context("spawn").Pool(args.workers) as pool:
        for a, _, o, d, n, c in tqdm(pool.imap_unordered(_run, jobs), total=len(jobs), desc="objects"):
            ok[a] += o
            diverged[a] += d
            steps[a] += n
            cpu[a] += c
    wall = time.perf_counter() - start
    ms = {a: 1e3 * cpu[a] / steps[a] for a in approximations}
    lines = [f"# Contact approximations: the grasp expert's success and an env step's cost ({args.hand})", "",
             f"Command: `python {' '.join(sys.argv)}`  ",
             f"{len(names)} {args.split} objects x seeds 0..{args.seeds - 1}, the training scenario with only "
             f"`contact_approximation` changed; ms = CPU per env step (plant, features, reward, expert), "
             f"ratio against {approximations[0]} in this run. Wall time {wall / 60:.1f} min with "
             f"{args.workers} workers.",
             "", "| approximation | success | rate | 95 % CI | diverged | ms per step | cost ratio |",
             "|---|---|---|---|---|---|---|"]
    for a in approximations:
        wins, total = sum(ok[a]), len(ok[a])
        low, high = wilson_interval(wins, total)
        lines.append(f"| {a} | {wins}/{total} | {100 * wins / total:.1f} % | {100 * low:.1f}-{100 * high:.1f} | "
                     f"{diverged[a]} | {ms[a]:.2f} | {ms[a] / ms[approximations[0]]:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        tmp = args.out.with_suffix(args.out.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(args.out)


if __name__ == "__main__":
    main()
