"""`dexdrake ablations`: the feature-set ablation (dexdrake/eval/ablations.py) on a DAgger
run's states, with the simulator's featuriser, env factories and expert passed in."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import add_episodes_per_object, command_line, option_names
from dexdrake.eval.ablations import AblationSettings


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Adds the `ablations` command; returns its parser."""
    p = subparsers.add_parser("ablations", help="feature-set ablation: the same DAgger states and BC budget for "
                              "every feature set, scored open and closed loop on unseen objects")
    d = AblationSettings
    p.add_argument("--dagger", type=Path, required=True, help="a `dexdrake train dagger` output folder")
    p.add_argument("--out", type=argtypes.output_folder, required=True, help="output folder (an unfinished run there goes on)")
    p.add_argument("--feature-sets", default="all", help="'all' or comma-separated feature sets")
    p.add_argument("--stride", type=argtypes.count, default=d.stride, help="keep every n-th step of each episode")
    p.add_argument("--epochs", type=argtypes.count, default=d.epochs, help="BC epochs per set")
    p.add_argument("--lr", type=argtypes.float_in(0.0), default=d.lr, help="BC learning rate")
    add_episodes_per_object(p, d.episodes, "closed loop")
    p.add_argument("--objects", default=d.objects, help="'paper' (the paper's 10 unseen objects), 'unseen' or names")
    p.add_argument("--workers", type=argtypes.count, default=2, help="worker processes")
    p.add_argument("--seed", type=argtypes.seed, default=d.seed, help="BC seed")
    p.add_argument("--eval-seed", type=argtypes.seed, default=d.eval_seed, help="first closed-loop episode seed")
    p.set_defaults(func=cmd_ablations, recorded_options=option_names(p))
    return p


def cmd_ablations(args: argparse.Namespace) -> int:
    import torch

    from dexdrake.dexrep.feature_sets import FEATURE_SETS
    from dexdrake.eval.ablations import AblationRuntime, run_ablations
    from dexdrake.systems.env_factory import GraspEnvFactory, env_factory_for_policy
    from dexdrake.systems.reactive_grasp import ReactiveGrasp
    from dexdrake.systems.scripted_data import featurise_labelled

    torch.set_num_threads(2)
    settings = AblationSettings(str(args.dagger), args.stride, args.epochs, args.lr, args.episodes_per_object, args.objects,
                                args.seed, args.eval_seed)
    sets = list(FEATURE_SETS) if args.feature_sets == "all" else args.feature_sets.split(",")
    command = command_line(["ablations"], args, args.recorded_options)
    runtime = AblationRuntime(featurise_labelled, GraspEnvFactory, env_factory_for_policy, ReactiveGrasp,
                              args.workers, command)
    print(run_ablations(settings, sets, args.out, runtime), end="")
    return 0
