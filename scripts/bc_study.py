"""Fitting choices compared on one DAgger run's states: one fit per variant, in one run.

    python scripts/bc_study.py --run DAGGER_DIR --out DIR [--variants base,wd=1,noise=0.1,noise=0.3]
        [--iterations K] [--epochs 4] [--arm-weight 10] [--seed 3] [--episodes 2] [--validation-episodes 4]
        [--eval-seed 1500000000] [--workers 2] [--init CKPT]

A variant is `base` or `+`-joined settings: `wd=X` (BCConfig.weight_decay), `noise=X`
(BCConfig.obs_noise), `absolute` (an absolute arm head instead of the run's residual one),
`keep` (BCConfig.keep_function: refitted statistics leave the starting policy's actions as
they were). Every variant is a new network of the run's hand and feature set (with `--init`:
a copy of that trained policy, as DAgger fine-tunes it), fitted with the same seed,
episode split, epochs, lr and loss weights on the run's first K iterations (data_XX.npz),
and scored by
- its train loss and its loss on the held-out episodes of the training objects;
- its loss on the run's probe episodes (probe_XX.npz, never trained on: the validation objects);
- executed success on every training object (`--episodes` each) and every validation object
  (`--validation-episodes` each), seeds from `--eval-seed` in the validation range (this is
  model selection: the test seeds and the unseen objects stay untouched).
Writes DIR/bc_study.md/.csv (naming the command; rows kept as they finish) and one checkpoint
per variant.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from dexdrake.eval.seeds import FIRST_VALIDATION_SEED

COLUMNS = ("variant", "train_loss", "held_out_loss", "validation_probe_loss", "seen_success_pct", "validation_success_pct",
           "fit_minutes")
SETTINGS = {"wd": "weight_decay", "noise": "obs_noise"}
FLAGS = {"keep": "keep_function"}


def parse_variant(text: str) -> tuple[dict[str, float], bool]:
    """(BCConfig overrides, absolute arm head) of a variant's name."""
    overrides: dict[str, float | bool] = {}
    absolute = False
    for part in text.split("+"):
        key, _, value = part.partition("=")
        if part == "absolute":
            absolute = True
        elif part in FLAGS:
            overrides[FLAGS[part]] = True
        elif key in SETTINGS and value:
            overrides[SETTINGS[key]] = float(value)
        elif part != "base":
            raise SystemExit(f"bc_study: unknown variant setting {part!r} (base, wd=X, noise=X, absolute, keep)")
    return overrides, absolute


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a DAgger run's folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--variants", default="base,wd=1,noise=0.1,noise=0.3")
    parser.add_argument("--iterations", type=int, default=0, help="data of the first K iterations (0: all)")
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--arm-weight", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=2, help="executed episodes per training object")
    parser.add_argument("--validation-episodes", type=int, default=4, help="executed episodes per validation object")
    parser.add_argument("--eval-seed", type=int, default=FIRST_VALIDATION_SEED)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--init", type=Path, help="start every variant from this trained policy (not `absolute`)")
    args = parser.parse_args()
    variants = {name: parse_variant(name) for name in args.variants.split(",")}

    import torch

    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.seeds import VALIDATION_SEEDS, describe, seed_range
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.bc import BCConfig, bc_loss, train_bc
    from dexdrake.learn.curves import write_csv
    from dexdrake.learn.dagger import Aggregate, DaggerData, run_config
    from dexdrake.learn.demo_dataset import DemoDataset
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, load_policy, save_policy
    from dexdrake.objects.library import get_object, resolve_objects
    from dexdrake.objects.meshfile import write_atomic
    from dexdrake.systems.env_factory import env_factory_for_policy

    config = run_config(args.run)
    files = sorted(args.run.glob("data_[0-9][0-9].npz"))[: args.iterations or None]
    parts = [DaggerData.load(f) for f in files]
    aggregate = Aggregate(sum(len(p.labels) for p in parts))
    for part in parts:
        aggregate.add(part)
    seen = sorted(n for n in set(parts[0].objects) if get_object(n).split == "train")  # not scaled copies
    del parts
    dataset = aggregate.dataset()
    probes = [DaggerData.load(f) for f in sorted(args.run.glob("probe_[0-9][0-9].npz"))[: len(files)]]
    probe = DaggerData.concat(probes) if probes else None
    held_out = resolve_objects("validation")[1]
    if seed_range(args.eval_seed, max(args.episodes, args.validation_episodes)) != "validation":
        raise SystemExit(f"bc_study: error: --eval-seed must start a block of validation seeds {describe(VALIDATION_SEEDS)}")
    hand = load_hand(config.hand)
    n_arm, blocks = len(hand.arm_joints), observation_blocks(hand, config.feature_set)
    weights = (args.arm_weight,) * n_arm + (1.0,) * (dataset.actions.shape[1] - n_arm)
    command = shlex.join(["python", *sys.argv])
    print(f"{len(dataset)} states from {len(files)} data files of {args.run} ({config.hand}, {config.feature_set}); "
          f"{0 if probe is None else len(probe.labels)} probe states", flush=True)
    rows = []
    for name, (overrides, absolute) in variants.items():
        torch.manual_seed(args.seed)
        if args.init and not absolute:
            policy = load_policy(args.init)[0]
        else:
            policy = DexRepNetPolicy(PolicyConfig.from_blocks(blocks, dataset.actions.shape[1], feature_set=config.feature_set,
                                                              hand=config.hand, residual_arm=config.residual_arm and not absolute))
        start = time.perf_counter()
        bc = BCConfig(epochs=args.epochs, batch_size=config.batch_size, lr=config.lr, seed=args.seed, split_seed=args.seed,
                      checkpoint_every=0, action_weights=weights, **overrides)
        result = train_bc(policy, dataset, args.out / name, bc, {"command": command})
        fit_minutes = (time.perf_counter() - start) / 60
        checkpoint = save_policy(args.out / f"policy_{name}.pt", policy, {"command": command, "variant": name})
        rates = [evaluate_policy(checkpoint, env_factory_for_policy, objects, n, args.eval_seed, args.workers,
                                 label=f"{name} {label}", command=command).average_pct()
                 for objects, n, label in ((seen, args.episodes, "seen"), (held_out, args.validation_episodes, "validation"))]
        probe_loss = (float("nan") if probe is None else
                      bc_loss(policy, DemoDataset(probe.observations, probe.labels, probe.episode_starts)))
        rows.append({"variant": name, "train_loss": f"{result.train_loss[-1]:.3f}", "held_out_loss": f"{result.val_loss[-1]:.3f}",
                     "validation_probe_loss": f"{probe_loss:.3f}", "seen_success_pct": f"{rates[0]:.1f}",
                     "validation_success_pct": f"{rates[1]:.1f}", "fit_minutes": f"{fit_minutes:.1f}"})
        write_csv(args.out / "bc_study.csv", COLUMNS, rows)
        lines = [f"# Fitting choices on {len(dataset)} DAgger states ({config.hand}, {config.feature_set})", "",
                 f"- command: `{command}`",
                 f"- data: {args.run}, {len(files)} iterations; {f'from {args.init}' if args.init else 'fresh networks'}, {args.epochs} epochs, lr {config.lr}, "
                 f"batch {config.batch_size}, arm weight {args.arm_weight}, seed {args.seed}; losses summed over action "
                 "dimensions (normalised units), unweighted",
                 f"- executed: {len(seen)} training objects x {args.episodes} and {len(held_out)} validation x "
                 f"{args.validation_episodes} episodes from seed {args.eval_seed}", "",
                 "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
        lines += ["| " + " | ".join(str(r[k]) for k in COLUMNS) + " |" for r in rows]
        write_atomic(args.out / "bc_study.md", ("\n".join(lines) + "\n").encode())
        print(lines[-1], flush=True)


if __name__ == "__main__":
    main()
