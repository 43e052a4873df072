"""Feature-set ablation: the same expert-labelled states and BC budget for every feature set.

    python scripts/ablations.py --dagger runs/policy/dagger --out runs/ablations [--sets all|Hand2obj,DexRep]
        [--stride 2] [--epochs 20] [--lr 1e-4] [--episodes 2] [--objects paper] [--workers 2] [--seed 0]

The states are those of a finished DAgger run (`dexdrake train dagger`: the expert's and the
DexRep policy's visited states, every `--stride`-th step, with the expert's labels); their
raw plant states (positions and velocities) are re-featurised with each set, so every set
sees exactly the same states and labels and gets the same BC budget (epochs, batch 64, lr,
seed). Each set is
scored twice on unseen objects:
- open loop: the mean squared error (summed over joints, normalised action units) of its
  predictions against the expert's labels along the expert's own episodes on the unseen
  objects (seeds 0..1) — how well the representation transfers to new shapes;
- closed loop: success over `--episodes` evaluation episodes per object (100 steps).
`--objects paper` evaluates the 10 unseen GRAB objects of the paper's ablation; `unseen`
all 13 unseen library objects. Writes ablations.md/.csv beside the paper's numbers, naming
the command; each finished set is kept in `--out`/ablations.json, so the same command run
again goes on with the sets still missing (a run with other settings into that folder is refused).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from dexdrake.eval.seeds import FIRST_TEST_SEED
from dexdrake.learn.curves import write_csv
from dexdrake.objects.meshfile import write_atomic

SETTINGS = ("dagger", "stride", "epochs", "lr", "episodes", "objects", "seed", "eval_seed")  # what a row depends on
COLUMNS = ("feature_set", "obs_dim", "train_mse", "unseen_open_loop_mse", "ours_paper_objects_pct", "ours_all_pct",
           "paper_pct", "mean_max_lift_m", "minutes")


def as_raw(data, hand: str):
    """DAgger data as the RawEpisodes that `featurise` re-featurises (labels as actions)."""
    from dexdrake.systems.scripted_data import RawEpisodes

    return RawEpisodes(hand, data.objects, data.seeds, data.success, data.episode_starts, data.states, data.labels)


def every_nth_step(data, stride: int):
    """Every `stride`-th step of each episode (episode starts kept)."""
    from dexdrake.learn.dagger import DaggerData

    step = np.arange(len(data.labels)) - np.maximum.accumulate(np.where(data.episode_starts, np.arange(len(data.labels)), 0))
    keep = step % stride == 0
    return DaggerData(data.objects, data.seeds, data.success, data.episode_starts[keep], data.states[keep],
                      data.observations[keep], data.labels[keep])


def expert_episodes(hand: str, objects: list[str], seeds: list[int]):
    """The expert's own episodes on `objects` (states and labels)."""
    from dexdrake.learn.dagger import DaggerData, labelled_episode
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import ReactiveGrasp

    env = GraspEnvFactory(hand, None, tuple(objects), 100)()
    return DaggerData.concat([labelled_episode(env, name, s, None, 0.0, ReactiveGrasp) for name in objects for s in seeds])


def run_set(feature_set: str, train, held_out, args, objects: list[str]) -> dict[str, object]:
    """Featurise, train BC, score open and closed loop for one feature set; returns its table row."""
    import torch

    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.paper import PAPER_ABLATIONS, PAPER_UNSEEN
    from dexdrake.learn.bc import BCConfig, train_bc
    from dexdrake.learn.demo_dataset import DemoDataset
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig
    from dexdrake.systems.env_factory import env_factory_for_policy
    from dexdrake.systems.scripted_data import featurise

    slug = feature_set.replace("+", "_").replace("-", "_").lower()
    folder = args.out / slug
    t0 = time.perf_counter()
    obs, blocks = featurise(train, feature_set, progress=True, workers=args.workers)
    held_obs, _ = featurise(held_out, feature_set, progress=True, workers=args.workers)
    config = PolicyConfig.from_blocks(blocks, train.actions.shape[1], feature_set=feature_set, hand=train.hand)
    policy = DexRepNetPolicy(config)
    bc = train_bc(policy, DemoDataset(obs, train.actions, train.episode_starts), folder,
                  BCConfig(epochs=args.epochs, lr=args.lr, seed=args.seed, checkpoint_every=0, val_fraction=0.0),
                  {"command": shlex.join(["python", *sys.argv])})
    with torch.no_grad():
        pred = policy(torch.as_tensor(held_obs)).numpy()
    open_loop = float(np.mean(np.sum((pred - held_out.actions) ** 2, axis=1)))
    report = evaluate_policy(bc.last_checkpoint, env_factory_for_policy, objects, args.episodes, args.eval_seed, args.workers,
                             label="unseen", command=shlex.join(["python", *sys.argv]))
    per = report.per_object()
    paper_objs = [n for n in per if n in PAPER_UNSEEN]
    return {
        "feature_set": feature_set,
        "obs_dim": sum(blocks.values()),
        "train_mse": f"{bc.train_loss[-1]:.3f}",
        "unseen_open_loop_mse": f"{open_loop:.3f}",
        "ours_paper_objects_pct": f"{sum(per[n]['success_pct'] for n in paper_objs) / max(1, len(paper_objs)):.1f}",
        "ours_all_pct": f"{report.average_pct():.1f}",
        "paper_pct": f"{PAPER_ABLATIONS[feature_set]:.1f}" if feature_set in PAPER_ABLATIONS else "",  # not in the paper
        "mean_max_lift_m": f"{sum(e.max_lift for e in report.episodes) / len(report.episodes):.3f}",
        "minutes": f"{(time.perf_counter() - t0) / 60:.1f}",
    }


def write_table(rows: list[dict[str, object]], args, objects: list[str], n_train: int, n_held: int) -> None:
    write_csv(args.out / "ablations.csv", COLUMNS, rows)
    lines = [
        "# Feature-set ablation (same states, labels and BC budget for every set)",
        "",
        f"- command: `{shlex.join(['python', *sys.argv])}`",
        f"- training data: {n_train} expert-labelled states of the DAgger run in `{args.dagger}` (one step in "
        f"{args.stride}), re-featurised per set; BC {args.epochs} epochs, batch 64, lr {args.lr}, seed {args.seed}",
        f"- open loop: MSE (summed over joints, normalised units) against the expert's labels on its own episodes on "
        f"{len(objects)} unseen objects, seeds 0..1 ({n_held} states)",
        f"- closed loop: {len(objects)} unseen objects x {args.episodes} episodes (seeds {args.eval_seed}.."
        f"{args.eval_seed + args.episodes - 1}), 100 steps, mean actions",
        "- paper: after BC + DAPG, 10 unseen GRAB objects, 3 seeds",
        "",
        "| feature set | obs dim | train MSE | unseen open-loop MSE | ours, paper objects (%) | ours, all evaluated (%) "
        "| paper (%) | mean max lift (m) | minutes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append("| " + " | ".join(str(r[k]) for k in COLUMNS) + " |")
    write_atomic(args.out / "ablations.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


def finished_rows(args) -> dict[str, dict[str, object]]:
    """The rows an earlier run of these settings finished in `args.out` ({} if none); exits with
    one line if that folder holds a run of other settings."""
    path = args.out / "ablations.json"
    if not path.is_file():
        return {}
    done = json.loads(path.read_text())
    now = settings(args)
    if done["settings"] != now:
        diff = "; ".join(f"{k} {done['settings'].get(k)!r} (now {now[k]!r})" for k in now if done["settings"].get(k) != now[k])
        raise SystemExit(f"{args.out} holds an ablation with other settings: {diff}; use another --out or delete it")
    return done["rows"]


def settings(args) -> dict[str, object]:
    """The arguments a table row depends on, as ablations.json records them."""
    return {k: str(getattr(args, k)) if k == "dagger" else getattr(args, k) for k in SETTINGS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dagger", type=Path, required=True, help="a `dexdrake train dagger` output folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sets", default="all")
    parser.add_argument("--stride", type=int, default=2, help="keep every n-th step of each episode")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--objects", default="paper", help="'paper' (10 GRAB objects), 'unseen' or names")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-seed", type=int, default=FIRST_TEST_SEED)
    args = parser.parse_args()

    import torch

    from dexdrake.dexrep.feature_sets import FEATURE_SETS
    from dexdrake.objects.library import resolve_objects
    from dexdrake.eval.paper import PAPER_UNSEEN
    from dexdrake.learn.dagger import DaggerData
    from dexdrake.learn.policy import load_policy

    torch.set_num_threads(2)
    sets = list(FEATURE_SETS) if args.sets == "all" else args.sets.split(",")
    unknown = [s for s in sets if s not in FEATURE_SETS]
    if unknown:
        raise SystemExit(f"unknown feature sets {unknown}; valid: {list(FEATURE_SETS)}")
    done = finished_rows(args)
    files = sorted(args.dagger.glob("data_*.npz"))
    if not files:
        raise SystemExit(f"no DAgger data (data_*.npz) in {args.dagger}")
    objects = list(PAPER_UNSEEN) if args.objects == "paper" else resolve_objects(args.objects)[1]
    hand = load_policy(args.dagger / "dagger_policy.pt")[0].config.hand
    train = as_raw(every_nth_step(DaggerData.concat([DaggerData.load(f) for f in files]), args.stride), hand)
    held_out = as_raw(expert_episodes(hand, objects, [0, 1]), hand)
    for fs in sets:
        if fs not in done:
            done[fs] = run_set(fs, train, held_out, args, objects)
            write_atomic(args.out / "ablations.json", json.dumps({"settings": settings(args), "rows": done}, indent=1).encode())
        write_table([done[f] for f in sets if f in done], args, objects, len(train.actions), len(held_out.actions))


if __name__ == "__main__":
    main()
