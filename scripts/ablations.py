"""Feature-set ablation: BC on the same demos for every feature set, evaluated on unseen objects.

    python scripts/ablations.py --raw runs/m/scripted_raw.npz --out runs/m/ablations \
        [--sets all|Hand2obj,DexRep] [--epochs 30] [--lr 1e-4] [--episodes 2] [--objects paper] \
        [--workers 2] [--seed 0]

The demos are one raw recording (scripts/build_scripted_dataset.py record: per-step plant
positions and actions of successful scripted grasps) re-featurised with each set's
observation, so every set sees exactly the same states and actions and gets the same BC
budget (epochs, batch 64, lr, seed). `--objects paper` evaluates the 10 unseen GRAB objects
of the paper's ablation; `unseen` all 13 unseen library objects. Writes ablations.md/.csv
beside the paper's numbers, naming the command.
"""

from __future__ import annotations

import argparse
import csv
import shlex
import sys
import time
from pathlib import Path


def run_set(feature_set: str, raw, raw_meta, recorded, args, objects: list[str]) -> dict[str, object]:
    """Featurise, train BC and evaluate one feature set; returns its table row."""
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.scripted_data import dataset_metadata, featurise
    from dexdrake.eval.tables import PAPER_ABLATIONS, PAPER_UNSEEN
    from dexdrake.learn.bc import BCConfig, train_bc
    from dexdrake.learn.demo_dataset import load_demo_dataset, save_demo_dataset
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig

    slug = feature_set.replace("+", "_").replace("-", "_").lower()
    folder = args.out / slug
    t0 = time.perf_counter()
    obs, blocks = featurise(raw, feature_set, progress=True)
    data_path = save_demo_dataset(folder / "data.npz", obs, raw.actions, raw.episode_starts,
                                  dataset_metadata(recorded, raw, raw_meta, feature_set, blocks))
    data = load_demo_dataset(data_path)
    config = PolicyConfig.from_blocks(blocks, data.actions.shape[1], feature_set=feature_set, hand=raw.hand)
    bc = train_bc(DexRepNetPolicy(config), data, folder,
                  BCConfig(epochs=args.epochs, lr=args.lr, seed=args.seed, checkpoint_every=0),
                  {"command": shlex.join(["python", *sys.argv])})
    report = evaluate_policy(bc.best_checkpoint, objects, args.episodes, args.eval_seed, args.workers,
                             label="unseen", command=shlex.join(["python", *sys.argv]))
    per = report.per_object()
    paper_objs = [n for n in per if n in PAPER_UNSEEN]
    return {
        "feature_set": feature_set,
        "obs_dim": sum(blocks.values()),
        "bc_val_loss": f"{bc.best_val_loss:.4f}",
        "ours_paper_objects_pct": f"{sum(per[n]['success_pct'] for n in paper_objs) / max(1, len(paper_objs)):.1f}",
        "ours_all_pct": f"{report.average_pct():.1f}",
        "paper_pct": f"{PAPER_ABLATIONS[feature_set]:.1f}",
        "mean_max_lift_m": f"{sum(e.max_lift for e in report.episodes) / len(report.episodes):.3f}",
        "minutes": f"{(time.perf_counter() - t0) / 60:.1f}",
    }


def write_table(rows: list[dict[str, object]], args, objects: list[str], n_samples: int, n_episodes: int) -> None:
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "ablations.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        "# Feature-set ablation (BC only, reduced budget)",
        "",
        f"- command: `{shlex.join(['python', *sys.argv])}`",
        f"- demos: {n_samples} samples from {n_episodes} successful scripted-grasp episodes, the same for every set",
        f"- BC: {args.epochs} epochs, batch 64, lr {args.lr}, seed {args.seed} (paper: 150 epochs, lr 1e-5, then DAPG)",
        f"- evaluation: {len(objects)} unseen objects x {args.episodes} episodes (seeds {args.eval_seed}.."
        f"{args.eval_seed + args.episodes - 1}), 100 steps, mean actions",
        "- paper: DexRep ablations after BC + DAPG, 10 unseen GRAB objects, 3 seeds",
        "",
        "| feature set | obs dim | BC val loss | ours, paper objects (%) | ours, all evaluated (%) | paper (%) | mean max lift (m) | minutes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append("| " + " | ".join(str(r[k]) for k in ("feature_set", "obs_dim", "bc_val_loss",
                     "ours_paper_objects_pct", "ours_all_pct", "paper_pct", "mean_max_lift_m", "minutes")) + " |")
    (args.out / "ablations.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--raw", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sets", default="all")
    parser.add_argument("--epochs", type=int, default=30)
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
    from dexdrake.eval.scripted_data import load_raw
    from dexdrake.eval.tables import PAPER_UNSEEN

    torch.set_num_threads(1)
    sets = list(FEATURE_SETS) if args.sets == "all" else args.sets.split(",")
    unknown = [s for s in sets if s not in FEATURE_SETS]
    if unknown:
        raise SystemExit(f"unknown feature sets {unknown}; valid: {list(FEATURE_SETS)}")
    objects = list(PAPER_UNSEEN) if args.objects == "paper" else resolve_objects(args.objects)[1]
    recorded, raw_meta = load_raw(args.raw)
    raw = recorded.select_successful()
    rows = []
    for fs in sets:
        rows.append(run_set(fs, raw, raw_meta, recorded, args, objects))
        write_table(rows, args, objects, len(raw.actions), len(raw.objects))  # partial results survive


if __name__ == "__main__":
    main()
