"""CLI: `dexdrake eval`, the per-object success of a policy, seeing the object pose as it was
trained to (the perception model its checkpoint records; `--pose-noise` changes the sigmas)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from functools import partial
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import (add_envs_per_worker, add_episodes_per_object, add_horizon, command_line, envs_per_worker,
                                option_names)
from dexdrake.errors import DexdrakeError
from dexdrake.eval.evaluate import EVAL_HORIZON
from dexdrake.eval.seeds import FIRST_TEST_SEED, FIRST_VALIDATION_SEED, SEED_RANGES, check_evaluation_seeds, describe


def add_parser(subparsers) -> None:
    ev = subparsers.add_parser("eval", help="per-object and per-category success of a policy (the paper's Table I layout)")
    ev.add_argument("--policy", required=True, type=Path, help="policy checkpoint (.pt)")
    ev.add_argument("--objects", default="unseen",
                    help="'seen', 'unseen' (test), 'validation' (choices), 'near' (the earlier unseen set) or object names")
    add_episodes_per_object(ev, 10, "seeds S..S+N-1")
    ev.add_argument("--seed", type=argtypes.seed, default=FIRST_VALIDATION_SEED,
                    help="first episode seed S (default: the first validation seed); the seeds must lie in one of "
                         + ", ".join(f"{n} {describe(r)}" for n, r in SEED_RANGES.items())
                         + f": validation for every choice, test (from {FIRST_TEST_SEED}) once per shipped policy")
    ev.add_argument("--workers", type=argtypes.count, default=1, help="worker processes")
    add_envs_per_worker(ev, "objects (one environment each)", "; 1 with --rrd")
    add_horizon(ev, EVAL_HORIZON, "paper: 100")
    ev.add_argument("--pose-noise", type=argtypes.pose_noise, metavar="POS,ROT",
                    help="the object pose's noise sigmas (m, rad; the paper's: 0.02,0.1) instead of those the policy "
                         "was trained with; its frames' period and latency stay the trained ones")
    ev.add_argument("--out", type=argtypes.output_folder, help="folder for eval_<label>.md/.csv/.json")
    ev.add_argument("--label", type=argtypes.label, help="table label (default: seen, unseen or selected, from --objects)")
    ev.add_argument("--rrd", type=argtypes.output_file(".rrd"),
                    help="write a rerun recording of every episode to this .rrd file (one worker)")
    ev.set_defaults(func=cmd_eval, recorded_options=option_names(ev))


def cmd_eval(args: argparse.Namespace) -> int:
    from dexdrake.eval.evaluate import evaluate_policy
    from dexdrake.eval.tables import markdown_table, write_report
    from dexdrake.learn.policy import load_policy
    from dexdrake.objects.library import resolve_objects
    from dexdrake.perceived_pose import PerceptionModel
    from dexdrake.systems.env_factory import env_factory_for_policy

    label, objects = resolve_objects(args.objects)
    label = args.label or label
    part = check_evaluation_seeds(args.seed, args.episodes_per_object)
    print(f"seeds {args.seed}..{args.seed + args.episodes_per_object - 1}: {part} range {describe(SEED_RANGES[part])}", flush=True)
    if args.rrd and args.workers > 1:
        raise DexdrakeError("--rrd records in one process: use --workers 1")
    perception = PerceptionModel(**load_policy(args.policy)[1]["scenario"].get("perception", {}))
    if args.pose_noise is not None:
        perception = replace(perception, pose_noise_position_m=args.pose_noise[0],
                             pose_noise_rotation_rad=args.pose_noise[1])
    print("object pose: " + ("true" if perception.is_exact else ", ".join(f"{k} {v:g}" for k, v in vars(perception).items()))
          + (" (as trained)" if args.pose_noise is None else " (--pose-noise)"), flush=True)
    logger = None
    if args.rrd:
        from dexdrake.systems.rerun_logger import RerunLogger

        logger = RerunLogger(args.rrd, "eval")
    try:
        report = evaluate_policy(args.policy, partial(env_factory_for_policy, perception=perception), objects, args.episodes_per_object, args.seed, args.workers,
                                 args.horizon, label=label, record=None if logger is None else logger.hooks,
                                 envs_per_worker=envs_per_worker(args),
                                 command=command_line(["eval"], args, args.recorded_options))
    finally:
        if logger is not None:
            logger.close()
    print(markdown_table(report))
    if args.out:
        paths = write_report(report, args.out)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    low, high = report.average_ci95_pct()
    print(json.dumps({"average_pct": round(report.average_pct(), 2), "ci95_pct": [round(low, 2), round(high, 2)],
                      "episodes": len(report.episodes)}))
    return 0
