"""CLI: `dexdrake features describe` and `dexdrake features show`."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import add_horizon
from dexdrake.outputs import check_writable


def _describe(args: argparse.Namespace) -> int:
    from dexdrake.dexrep.feature_sets import feature_set_names, observation_blocks
    from dexdrake.hands.description import load_hand

    hand = load_hand(args.hand)
    for name in [args.feature_set] if args.feature_set else feature_set_names():
        blocks = observation_blocks(hand, name)
        parts = ", ".join(f"{g} {n}" for g, n in blocks.items())
        print(f"{hand.name} {name}: {parts} (total {sum(blocks.values())})")
    return 0


def _show(args: argparse.Namespace) -> int:
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.rerun_logger import RerunLogger
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    rrd = None if args.spawn else (args.rrd or check_writable(Path(f"dexrep_{args.object}_{args.hand}_s{args.seed}.rrd"),
                                                              folder=False))
    env = GraspEnv(training_scenario(args.hand, args.object), horizon=args.horizon)
    logger = RerunLogger(rrd, "sim", spawn=args.spawn)
    try:
        summary = env.rollout(ScriptedGrasp, args.seed, logger=logger)
    finally:
        logger.close()
    where = "the rerun viewer" if args.spawn else rrd
    print(f"logged {summary.steps} steps of a scripted grasp of {args.object} ({args.hand}, seed {args.seed}, "
          f"success {summary.success}, max lift {summary.max_lift:.3f} m) to {where}")
    return 0


def add_parser(subparsers) -> None:
    """Adds the `features` command group."""
    feat = subparsers.add_parser("features", help="DexRep feature sets").add_subparsers(dest="action", required=True)
    d = feat.add_parser("describe", help="print each observation block's size")
    d.add_argument("--hand", default="adroit")
    d.add_argument("--feature-set", default=None, help="one feature set (default: all)")
    d.set_defaults(func=_describe)
    s = feat.add_parser("show", help="record a scripted-grasp episode to rerun (its DexRep in the DexRep tab)")
    s.add_argument("--object", required=True, help="object library name")
    s.add_argument("--hand", default="adroit")
    s.add_argument("--rrd", type=argtypes.output_file(".rrd"),
                   help="output .rrd file (default: dexrep_<object>_<hand>_s<seed>.rrd)")
    s.add_argument("--seed", type=argtypes.seed, default=0)
    add_horizon(s, 200)
    s.add_argument("--spawn", action="store_true", help="stream to a live rerun viewer instead of a file")
    s.set_defaults(func=_show)
