"""CLI: `dexdrake encoder train`, the PointNet auto-encoder whose encoder DexRep uses."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import command_line, option_names


def _train(args: argparse.Namespace) -> int:
    from dexdrake.dexrep.train_encoder import TrainConfig, train

    config = TrainConfig(meshes=args.meshes, epochs=args.epochs, steps_per_epoch=args.steps_per_epoch,
                         batch_size=args.batch_size, lr=args.lr, seed=args.seed, threads=args.threads)
    command = command_line(["encoder", "train"], args, args.recorded_options)
    m = train(config, Path(args.out), command=command)
    print(f"wrote {args.out}: Chamfer train {m['chamfer_train']:.4f}, unseen {m['chamfer_unseen']:.4f}")
    return 0


def add_parser(subparsers) -> None:
    """Adds the `encoder` command group."""
    enc = subparsers.add_parser("encoder", help="the PointNet encoder").add_subparsers(dest="action", required=True)
    t = enc.add_parser("train", help="train the PointNet auto-encoder, write the encoder")
    t.add_argument("--meshes", default="train", help="'train' (object library), 'primitives' or a folder")
    t.add_argument("--epochs", type=argtypes.count, default=10)
    t.add_argument("--steps-per-epoch", type=argtypes.count, default=8)
    t.add_argument("--batch-size", type=argtypes.count, default=8)
    t.add_argument("--lr", type=argtypes.positive, default=1e-3)
    t.add_argument("--seed", type=argtypes.seed, default=0)
    t.add_argument("--threads", type=argtypes.count, default=1)
    t.add_argument("--out", type=argtypes.output_file(".pt"), default="models/weights/pointnet_encoder.pt")
    t.set_defaults(func=_train, recorded_options=option_names(t))
