"""CLI: `dexdrake expert table|choose`, the grasp expert (or the scripted grasp) alone.

`table`: its success per object over seeds S..S+N-1, as a markdown table and a CSV.
`choose`: the expert's grasp variant per training object by simulated trials, written to the
hand's grasp table (models/weights/<hand>_expert_grasps.json), which the expert reads.
The work is dexdrake.eval.expert's; the envs and controllers come from systems/.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import add_backend_options, add_episodes_per_object, add_horizon, command_line, option_names
from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.eval.evaluate import EVAL_HORIZON

CONTROLLERS = ("scripted", "expert")  # as `dexdrake sim --controller`
TABLE_SEEDS = (0, 10)  # the table's seed block: first seed, episodes per object
CHOICE_SEEDS = (100, 12)  # the choice's, apart from the table's (fewer trials cannot tell most variants apart)


def add_parser(subparsers) -> None:
    expert = subparsers.add_parser("expert", help="the grasp expert alone: success per object, choice of its grasps")
    sub = expert.add_subparsers(dest="expert_command", required=True)

    table = sub.add_parser("table", help="per-object success of the grasp expert or the scripted grasp (md + csv)",
                           description="Run the grasp expert (or the scripted grasp) alone for seeds S..S+N-1 on "
                                       "each object in the training scenario; print a markdown table (object, "
                                       "category, success, mean max lift, CPU ms per controller call; then per "
                                       "category and overall) naming the command.")
    _common(table, "train")
    table.add_argument("--controller", choices=CONTROLLERS, default="expert",
                       help="the grasp expert (ReactiveGrasp, with the hand's chosen grasps) or the timed "
                            "scripted grasp (default: expert)")
    add_episodes_per_object(table, TABLE_SEEDS[1], "seeds S..S+N-1")
    table.add_argument("--seed", type=argtypes.seed, default=TABLE_SEEDS[0],
                       help=f"first episode seed S (default: {TABLE_SEEDS[0]})")
    add_horizon(table, EVAL_HORIZON, "the evaluation's")
    table.add_argument("--out", type=argtypes.output_file(".md"),
                       help="also write the table to this .md file and OUT.csv beside it (one row per object, "
                            "then per category)")
    table.set_defaults(func=cmd_table, recorded_options=option_names(table))

    choose = sub.add_parser("choose", help="choose the expert's grasp variant per training object by simulated trials",
                            description="Try every grasp variant the hand can take (dexdrake.eval.expert.VARIANTS) "
                                        "with the grasp expert on each training object for seeds S..S+N-1 and keep "
                                        "the one with the most successes less its handicap (dexdrake.eval.expert.HANDICAPS: "
                                        "fingertip pinches give up 2; ties: the earlier, the hand's default "
                                        "first); write the hand's grasp table, which the expert reads. Seeds that "
                                        "`expert table` reports on are refused. With --objects, each re-chosen "
                                        "entry records its command and seeds.")
    _common(choose, "")
    add_episodes_per_object(choose, CHOICE_SEEDS[1], "trials of each variant, seeds S..S+N-1")
    choose.add_argument("--seed", type=argtypes.seed, default=CHOICE_SEEDS[0],
                        help=f"first trial seed S (default: {CHOICE_SEEDS[0]}, apart from the table's "
                             f"{TABLE_SEEDS[0]}..{TABLE_SEEDS[0] + TABLE_SEEDS[1] - 1})")
    add_horizon(choose, EVAL_HORIZON, "the evaluation's")
    choose.add_argument("--out", type=argtypes.output_file(".json"),
                        help="the grasp table to write (default: models/weights/<hand>_expert_grasps.json, the one "
                             "the expert reads); with --objects, the table whose other entries are kept")
    choose.set_defaults(func=cmd_choose, recorded_options=option_names(choose))


def _common(parser: argparse.ArgumentParser, objects: str) -> None:
    parser.add_argument("--hand", default="adroit", help="the hand (default: adroit)")
    if objects:
        parser.add_argument("--objects", default=objects,
                            help="'train' (the training objects), 'unseen', 'validation', 'near' or comma-separated "
                                 f"object names (default: {objects})")
    else:
        parser.add_argument("--objects", help="comma-separated training objects to re-choose, keeping the other "
                                              "entries of the existing table (default: every training object)")
    parser.add_argument("--workers", type=argtypes.count, default=2, help="rollout worker processes (default: 2)")
    add_backend_options(parser)


def cmd_table(args: argparse.Namespace) -> int:
    from dexdrake.eval.expert import controller_table
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.objects.library import get_object, resolve_objects
    from dexdrake.systems.env_factory import GraspEnvFactory, training_scenario
    from dexdrake.systems.reactive_grasp import ReactiveGrasp, expert_grasps_path
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    load_hand(args.hand)  # an unknown hand: one line, before any work
    label, objects = resolve_objects(args.objects)
    make = ReactiveGrasp if args.controller == "expert" else ScriptedGrasp
    factory = GraspEnvFactory(args.hand, None, tuple(objects), args.horizon)
    command = command_line(["expert", "table"], args, args.recorded_options)
    with make_sampler(factory, args.backend, args.workers, args.address) as sampler:
        table = controller_table(sampler, make, objects, {n: get_object(n).category for n in objects}, args.seed,
                                 args.episodes_per_object, args.horizon, "episodes")
        workers = sampler.num_workers
    scenario = training_scenario(args.hand)
    what = "Grasp expert (ReactiveGrasp)" if args.controller == "expert" else "Scripted grasp"
    heading = f"{what} success ({args.hand}, {label} objects)"
    notes = [f"Command: `{command}`  ",
             f"Seeds {table.seeds_text()} per object (the paper's placement randomisation), horizon {args.horizon} "
             "control steps at 50 Hz; success = object within 10 cm of the target 0.15 m above its start for 50 "
             f"consecutive steps. Wall time {table.wall_s / 60:.1f} min with {workers} workers; ms = CPU time "
             "per controller call.",
             f"Scenario: training's (`training_scenario`: {1e3 * scenario.time_step:g} ms plant step, "
             f"{1e3 * scenario.control_period:g} ms control period, the drivers' target limits, object masses "
             f"{load_hand(args.hand).object_mass.describe()}); the expert's grasp "
             f"variants: models/weights/{expert_grasps_path(args.hand).name} (none: the hand's default)."]
    print(table.markdown(heading, notes))
    if args.out:
        paths = table.write(args.out, heading, notes)
        print("wrote " + ", ".join(map(str, paths)))
    return 0


def cmd_choose(args: argparse.Namespace) -> int:
    from dexdrake.eval.expert import choice_lines, choose_variants
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.samplers import make_sampler
    from dexdrake.objects.library import list_objects
    from dexdrake.objects.meshfile import write_atomic
    from dexdrake.outputs import check_writable
    from dexdrake.systems.env_factory import GraspEnvFactory
    from dexdrake.systems.reactive_grasp import expert_grasps_path, variant_expert

    hand = load_hand(args.hand)
    out = args.out or check_writable(expert_grasps_path(args.hand), folder=False)
    training = [o.name for o in list_objects("train")]
    names, old = training, None
    if args.objects is not None:
        names = [n.strip() for n in args.objects.split(",") if n.strip()]
        unknown = [n for n in names if n not in training]
        if unknown or not names:
            raise UnknownNameError("training object", ",".join(unknown) or args.objects, training)
        if out.is_file():
            old = _read_table(out)
    seeds = list(range(args.seed, args.seed + args.episodes_per_object))
    reported = range(TABLE_SEEDS[0], TABLE_SEEDS[0] + TABLE_SEEDS[1])
    if set(seeds) & set(reported):
        raise DexdrakeError(f"seeds {seeds[0]}..{seeds[-1]} overlap {reported[0]}..{reported[-1]}, the seeds "
                            "`expert table` reports on; choose on others (--seed)")
    command = command_line(["expert", "choose"], args, args.recorded_options)
    factory = GraspEnvFactory(args.hand, None, tuple(names), args.horizon)
    with make_sampler(factory, args.backend, args.workers, args.address) as sampler:
        table = choose_variants(sampler, variant_expert, hand, names, seeds, args.horizon, command, old)
    print("\n".join(choice_lines(table)))
    write_atomic(out, (json.dumps(table, indent=1) + "\n").encode())
    print(f"wrote {out}")
    return 0


def _read_table(path: Path) -> dict:
    """The existing grasp table at `path` (its seeds and objects are what a re-choice reads)."""
    try:
        table = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        table, reason = None, str(err)
    else:
        reason = "it lacks 'seeds' or 'objects'"
    if not isinstance(table, dict) or not {"seeds", "objects"} <= set(table):
        raise DexdrakeError(f"{path} is not a readable expert grasp table ({reason}); re-choose every object "
                            "or give another --out")
    return table
