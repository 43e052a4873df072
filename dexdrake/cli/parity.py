"""CLI: `dexdrake parity`, sim-to-HIL parity of the scenario's controller (the shipped
Allegro-on-Z1 policy in `hil`) on the same objects and seeds, HIL at each PWM -> N*m scale.

Episodes run in simulation first, then in HIL at the first scale, then at the other scales
(the sensitivity to the PWM assumption) interleaved episode by episode; the table
(systems/parity.parity_table) is printed at the end and rewritten to `--out` after every
episode, so a run stopped early leaves a consistent table whose "sim, same episodes" column
compares each row with simulation on exactly its episodes.
"""

from __future__ import annotations

import argparse

import numpy as np

from dexdrake import argtypes
from dexdrake.cli.flags import add_horizon, command_line, option_names
from dexdrake.eval.evaluate import EVAL_HORIZON


def add_parser(subparsers) -> None:
    parity = subparsers.add_parser(
        "parity", help="sim-to-HIL parity: the same episodes in simulation and hardware-in-the-loop",
        description="The scenario's controller on the same objects and seeds in simulation and hardware-in-the-loop "
                    "at each PWM -> N*m scale: success, lift, faults, the pose error the controller saw (sim: the "
                    "scenario's perception model) and, with rendered perception, its cost.")
    parity.add_argument("--config", default="hil", help="scenario (mode hil): a packaged name (hil) or a YAML path")
    parity.add_argument("--objects", nargs="+", default=["box_cube", "sphere_small", "can_soda"], help="object names")
    parity.add_argument("--seeds", nargs="+", type=argtypes.seed, default=[0], help="episode seeds, each on every object")
    add_horizon(parity, EVAL_HORIZON, "the evaluation's")
    parity.add_argument("--scales", nargs="+", type=argtypes.positive, default=[1.0, 0.5, 2.0],
                        help="HIL PWM -> N*m scales, multiples of allegro_units.NM_PER_PWM (the first runs first)")
    parity.add_argument("--camera", choices=["rendered", "sim"], default="rendered",
                        help="HIL perception: rendered frames or the world's pose")
    parity.add_argument("--out", type=argtypes.output_file(".md"),
                        help="write the table (markdown) here as well, after every episode")
    parity.set_defaults(func=cmd_parity, recorded_options=option_names(parity))


def cmd_parity(args: argparse.Namespace) -> int:
    from dexdrake.objects.library import get_object
    from dexdrake.objects.meshfile import write_atomic
    from dexdrake.systems.parity import parity_table, run_parity_episode
    from dexdrake.systems.scenario import ScenarioError, load_scenario

    scenario = load_scenario(args.config)
    if scenario.mode != "hil":
        raise ScenarioError(f"{args.config} is a {scenario.mode} scenario; `parity` needs emulated drivers")
    for name in args.objects:
        get_object(name)
    command = command_line(["parity"], args, args.recorded_options)
    modes = [("sim", 1.0)] + [("hil", s) for s in args.scales]
    episodes = [(obj, seed) for seed in args.seeds for obj in args.objects]
    order = [(mode, scale, obj, seed) for mode, scale in modes[:2] for obj, seed in episodes]
    order += [(mode, scale, obj, seed) for obj, seed in episodes for mode, scale in modes[2:]]
    rows: list[dict] = []
    for mode, scale, obj, seed in order:
        row = run_parity_episode(args.config, obj, seed, args.horizon, mode, scale, args.camera)
        rows.append(row)
        print(f"  {mode} x{scale:g} {obj:14s} seed {seed}: success {row['success']} lift "
              f"{row['lift']:.3f} m {row['fault'] or ''} ({row['wall_s']:.0f} s wall, "
              f"{row['cpu_s']:.0f} s CPU)"
              + f"; pose error max {1e3 * max(row['pose_error'], default=np.nan):.0f} mm"
              + (f", tracking lost {row['losses']}" if "losses" in row else ""), flush=True)
        if args.out:
            write_atomic(args.out, (parity_table(rows, modes, command, args.config) + "\n").encode())
    print(parity_table(rows, modes, command, args.config))
    return 0
