"""Absolute against residual arm head: two fresh fits on one DAgger run's states, in one run.

    python scripts/ab_residual_arm.py --run DAGGER_DIR --out DIR [--epochs 4] [--arm-weight 10] [--seed 3]

Both networks are fitted with the same seed, split, epochs and loss weights on the run's
aggregate (its prior_XX.npz, then data_XX.npz files). Prints each head's train and held-out
loss and its held-out squared error per arm dimension, and the residual head's arm error as
a fraction of the absolute head's; writes both checkpoints to DIR, to compare their executed
success with `dexdrake eval`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a DAgger run's folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--arm-weight", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()

    import torch

    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.bc import BCConfig, train_bc
    from dexdrake.learn.dagger import Aggregate, DaggerConfig, DaggerData, prior_files
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, save_policy

    files = prior_files(args.run, DaggerConfig())
    parts = [DaggerData.load(f) for f in files]
    aggregate = Aggregate(sum(len(p.labels) for p in parts))
    for part in parts:
        aggregate.add(part)
    del parts
    dataset = aggregate.dataset()
    hand = load_hand("adroit")
    n_arm, blocks = len(hand.arm_joints), observation_blocks(hand, "DexRep")
    weights = (args.arm_weight,) * n_arm + (1.0,) * (dataset.actions.shape[1] - n_arm)
    print(f"{len(dataset)} states from {len(files)} files of {args.run}")
    arm_error = {}
    for residual in (False, True):
        torch.manual_seed(args.seed)
        policy = DexRepNetPolicy(PolicyConfig.from_blocks(blocks, dataset.actions.shape[1], feature_set="DexRep",
                                                          hand="adroit", residual_arm=residual))
        start = time.perf_counter()
        bc = BCConfig(epochs=args.epochs, batch_size=64, lr=1e-4, seed=args.seed, split_seed=args.seed,
                      checkpoint_every=0, action_weights=weights)
        result = train_bc(policy, dataset, args.out / f"bc_residual_{residual}", bc, {})
        idx = result.val_indices
        with torch.no_grad():
            pred = np.concatenate([policy(torch.as_tensor(dataset.observations[idx[i:i + 8192]])).numpy()
                                   for i in range(0, len(idx), 8192)])
        err = ((pred - dataset.actions[idx]) ** 2).mean(axis=0)
        arm_error[residual] = float(err[:n_arm].sum())
        print(f"residual arm {residual}: train loss {result.train_loss[-1]:.4f}, held-out {result.val_loss[-1]:.4f}; "
              f"held-out arm error per joint {np.round(err[:n_arm], 4).tolist()} (sum {arm_error[residual]:.4f}); "
              f"{time.perf_counter() - start:.0f} s")
        save_policy(args.out / f"policy_residual_{residual}.pt", policy,
                    {"command": "python scripts/ab_residual_arm.py", "run": str(args.run), "epochs": args.epochs})
    print(f"residual / absolute held-out arm error: {arm_error[True] / arm_error[False]:.2f}")


if __name__ == "__main__":
    main()
