"""CLI: `dexdrake encoder train`, the PointNet auto-encoder whose encoder DexRep uses; its
flags are TrainConfig's fields (dexdrake/dexrep/train_encoder.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import add_settings, command_line, option_names, settings_from_args
from dexdrake.dexrep.train_encoder import TrainConfig


def _train(args: argparse.Namespace) -> int:
    from dexdrake.dexrep.train_encoder import train

    command = command_line(["encoder", "train"], args, args.recorded_options)
    m = train(settings_from_args(TrainConfig, args), Path(args.out), command=command)
    print(f"wrote {args.out}: Chamfer train {m['chamfer_train']:.4f}, unseen {m['chamfer_unseen']:.4f}")
    return 0


def add_parser(subparsers) -> None:
    """Adds the `encoder` command group."""
    enc = subparsers.add_parser("encoder", help="the PointNet encoder").add_subparsers(dest="action", required=True)
    t = enc.add_parser("train", help="train the PointNet auto-encoder, write the encoder")
    add_settings(t, TrainConfig)
    t.add_argument("--out", type=argtypes.output_file(".pt"), default="models/weights/pointnet_encoder.pt",
                   help="encoder file to write (default: %(default)s)")
    t.set_defaults(func=_train, recorded_options=option_names(t))
