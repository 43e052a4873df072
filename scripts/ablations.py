"""Feature-set ablation: DAgger with the same budget for every feature set, evaluated on unseen objects.

    python scripts/ablations.py --out runs/ablations [--sets all|Hand2obj,DexRep] [--iterations 3]
        [--per-object 1] [--epochs 10] [--lr 1e-4] [--episodes 2] [--objects paper] [--workers 2] [--seed 0]

Every set is trained by `dexdrake.learn.dagger.train_dagger` on the training objects with
the same expert, iterations, episodes, BC epochs, lr and seeds; only the observation
differs. Iteration 0 runs the (deterministic) expert on the same seeds, so every set starts
from the same states and labels.
`--objects paper` evaluates the 10 unseen GRAB objects of the paper's ablation; `unseen`
all 13 unseen library objects. Writes ablations.md/.csv beside the paper's numbers,
naming the command; partial tables survive an interrupted run.
"""

from __future__ import annotations

import argparse
import csv
import shlex
import sys
import time
from pathlib import Path

COLUMNS = ("feature_set", "obs_dim", "train_success_last_pct", "ours_paper_objects_pct", "ours_all_pct", "paper_pct",
           "mean_max_lift_m", "minutes")


def run_set(feature_set: str, args, objects: list[str]) -> dict[str, object]:
    """Train one feature set by DAgger and evaluate it; returns its table row."""
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.tables import PAPER_ABLATIONS, PAPER_UNSEEN
    from dexdrake.learn.curves import read_csv
    from dexdrake.learn.dagger import DaggerConfig, train_dagger
    from dexdrake.learn.policy import load_policy
    from dexdrake.objects.library import list_objects

    slug = feature_set.replace("+", "_").replace("-", "_").lower()
    folder = args.out / slug
    t0 = time.perf_counter()
    config = DaggerConfig(feature_set=feature_set, iterations=args.iterations, episodes_per_object=args.per_object,
                          epochs=args.epochs, lr=args.lr, workers=args.workers, seed=args.seed)
    train = [o.name for o in list_objects("train")]
    final = train_dagger(train, folder, config, {"command": shlex.join(["python", *sys.argv])})
    log = read_csv(folder / "dagger_log.csv")
    report = evaluate_policy(final, objects, args.episodes, args.eval_seed, args.workers,
                             label="unseen", command=shlex.join(["python", *sys.argv]))
    per = report.per_object()
    paper_objs = [n for n in per if n in PAPER_UNSEEN]
    return {
        "feature_set": feature_set,
        "obs_dim": load_policy(final)[0].config.obs_dim,
        "train_success_last_pct": f"{100 * float(log[-1]['success_rate']):.1f}",
        "ours_paper_objects_pct": f"{sum(per[n]['success_pct'] for n in paper_objs) / max(1, len(paper_objs)):.1f}",
        "ours_all_pct": f"{report.average_pct():.1f}",
        "paper_pct": f"{PAPER_ABLATIONS[feature_set]:.1f}",
        "mean_max_lift_m": f"{sum(e.max_lift for e in report.episodes) / len(report.episodes):.3f}",
        "minutes": f"{(time.perf_counter() - t0) / 60:.1f}",
    }


def write_table(rows: list[dict[str, object]], args, objects: list[str]) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "ablations.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(COLUMNS))
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "# Feature-set ablation (DAgger, equal reduced budget)",
        "",
        f"- command: `{shlex.join(['python', *sys.argv])}`",
        f"- training: DAgger with the state-driven expert (systems/reactive_grasp.py) on the 53 training objects, "
        f"{args.iterations} iterations x {args.per_object} episode(s) per object, BC {args.epochs} epochs per "
        f"iteration, batch 64, lr {args.lr}, seed {args.seed}; iteration 0 is the same expert episodes for every set",
        "- train success: the executed success of the last DAgger iteration (the previous policy on training objects)",
        f"- evaluation: {len(objects)} unseen objects x {args.episodes} episodes (seeds {args.eval_seed}.."
        f"{args.eval_seed + args.episodes - 1}), 100 steps, mean actions",
        "- paper: DexRep ablations after BC + DAPG, 10 unseen GRAB objects, 3 seeds",
        "",
        "| feature set | obs dim | train success, last iteration (%) | ours, paper objects (%) | ours, all evaluated (%) "
        "| paper (%) | mean max lift (m) | minutes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append("| " + " | ".join(str(r[k]) for k in COLUMNS) + " |")
    (args.out / "ablations.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sets", default="all")
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--per-object", type=int, default=1)
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--objects", default="paper", help="'paper' (10 GRAB objects), 'unseen' or names")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-seed", type=int, default=0)
    args = parser.parse_args()

    import torch

    from dexdrake.dexrep.feature_sets import FEATURE_SETS
    from dexdrake.eval.envs import resolve_objects
    from dexdrake.eval.tables import PAPER_UNSEEN

    torch.set_num_threads(2)
    sets = list(FEATURE_SETS) if args.sets == "all" else args.sets.split(",")
    unknown = [s for s in sets if s not in FEATURE_SETS]
    if unknown:
        raise SystemExit(f"unknown feature sets {unknown}; valid: {list(FEATURE_SETS)}")
    objects = list(PAPER_UNSEEN) if args.objects == "paper" else resolve_objects(args.objects)[1]
    rows = []
    for fs in sets:
        rows.append(run_set(fs, args, objects))
        write_table(rows, args, objects)


if __name__ == "__main__":
    main()
