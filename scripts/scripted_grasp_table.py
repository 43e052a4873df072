"""Success rate of the scripted grasp or the grasp expert per object over seeds.

    python scripts/scripted_grasp_table.py [--hand adroit] [--split train] [--seeds 20]
        [--controller scripted|expert] [--workers 2] [--out models/weights/scripted_grasp_table.md]

Writes a markdown table (object, category, successes / seeds, mean max lift, CPU ms per
controller call) with per-category summary rows, names the command which made
it, and prints it; with --out also OUT.csv (one row per object, then one per category).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
import time
from collections import defaultdict
from pathlib import Path

from tqdm import tqdm


def _run_object(args: tuple[str, str, str, int, int]) -> tuple[str, list[bool], list[float], float]:
    hand, controller, name, seeds, horizon = args
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    cls = ReactiveGrasp if controller == "expert" else ScriptedGrasp
    env = GraspEnv(training_scenario(hand, name), horizon=horizon)
    cpu, calls = 0.0, 0

    def timed(env):
        env.fingertip_distances()  # as after every env step; the first query also loads the object's geometry
        grasp = cls(env)

        def act(env):
            nonlocal cpu, calls
            start = time.process_time()
            q = grasp(env)
            cpu, calls = cpu + time.process_time() - start, calls + 1
            return q

        return act

    results = [env.rollout(timed, seed) for seed in range(seeds)]
    return name, [r.success for r in results], [r.max_lift for r in results], 1e3 * cpu / calls


def main() -> None:
    from dexdrake.eval.evaluate import EVAL_HORIZON

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand", default="adroit")
    parser.add_argument("--split", default="train")
    parser.add_argument("--objects", help="comma-separated names (overrides --split)")
    parser.add_argument("--controller", choices=("scripted", "expert"), default="scripted",
                        help="the timed ScriptedGrasp or the grasp expert (ReactiveGrasp)")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--horizon", type=int, default=EVAL_HORIZON, help="control steps (default: the evaluation's)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()

    from dexdrake.objects.library import get_object, list_objects
    from dexdrake.systems.env_factory import training_scenario

    names = args.objects.split(",") if args.objects else [o.name for o in list_objects(args.split)]
    jobs = [(args.hand, args.controller, n, args.seeds, args.horizon) for n in names]
    start = time.perf_counter()
    rows = {}
    with mp.get_context("spawn").Pool(args.workers) as pool:
        for name, ok, lifts, ms in tqdm(pool.imap_unordered(_run_object, jobs), total=len(jobs), desc="objects"):
            rows[name] = (ok, lifts, ms)
    wall = time.perf_counter() - start

    scenario = training_scenario(args.hand)
    title = "Scripted grasp" if args.controller == "scripted" else "Grasp expert (ReactiveGrasp)"
    lines = [
        f"# {title} success ({args.hand}, {args.split if not args.objects else 'selected'} objects)",
        "",
        f"Command: `python {' '.join(sys.argv)}`  ",
        f"Seeds 0..{args.seeds - 1} per object (the paper's placement randomisation), horizon {args.horizon} "
        f"control steps at 50 Hz; success = object within 10 cm of the target 0.15 m above its start "
        f"for 50 consecutive steps. Wall time {wall / 60:.1f} min with {args.workers} workers; "
        "ms = CPU time per controller call.",
        "",
        f"Scenario: training's (`training_scenario`: {1e3 * scenario.time_step:g} ms plant step, "
        f"{1e3 * scenario.control_period:g} ms control period, the drivers' target limits); the expert's "
        f"grasp variants: models/weights/{args.hand}_expert_grasps.json (none: the hand's default).",
        "",
        "| object | category | success | rate | mean max lift (m) | ms |",
        "|---|---|---|---|---|---|",
    ]
    by_category: dict[str, list[bool]] = defaultdict(list)
    for name in names:
        ok, lifts, ms = rows[name]
        category = get_object(name).category
        by_category[category] += ok
        lines.append(f"| {name} | {category} | {sum(ok)}/{len(ok)} | {100 * sum(ok) / len(ok):.0f} % "
                     f"| {sum(lifts) / len(lifts):.3f} | {ms:.2f} |")
    lines += ["", "| category | success | rate |", "|---|---|---|"]
    for category, ok in sorted(by_category.items()):
        lines.append(f"| {category} | {sum(ok)}/{len(ok)} | {100 * sum(ok) / len(ok):.0f} % |")
    total_ok = sum(sum(ok) for ok in by_category.values())
    total = sum(len(ok) for ok in by_category.values())
    worst = min(sum(ok) / len(ok) for ok in by_category.values())
    mean_ms = sum(r[2] for r in rows.values()) / len(rows)
    lines += ["", f"**Overall: {total_ok}/{total} = {100 * total_ok / total:.1f} %; worst category {100 * worst:.0f} %; "
              f"{mean_ms:.2f} ms per controller call (mean over objects)**", ""]
    text = "\n".join(lines)
    print(text)
    if args.out:
        csv_rows = ["kind,name,category,successes,episodes,success_pct,mean_max_lift_m,ms_per_call"]
        for name in names:
            ok, lifts, ms = rows[name]
            csv_rows.append(f"object,{name},{get_object(name).category},{sum(ok)},{len(ok)},"
                            f"{100 * sum(ok) / len(ok):.1f},{sum(lifts) / len(lifts):.4f},{ms:.3f}")
        csv_rows += [f"category,,{c},{sum(ok)},{len(ok)},{100 * sum(ok) / len(ok):.1f},," for c, ok in sorted(by_category.items())]
        for path, body in ((args.out, text), (args.out.with_suffix(".csv"), "\n".join(csv_rows) + "\n")):
            tmp = path.with_suffix(path.suffix + ".tmp")
            tmp.write_text(body)
            tmp.replace(path)


if __name__ == "__main__":
    main()
