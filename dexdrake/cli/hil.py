"""Sub-command `hil`: one grasp episode against the emulated devices, hardware-in-the-loop."""

from __future__ import annotations

import argparse
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import MISMATCH_HELP, add_horizon
from dexdrake.outputs import check_writable


def add_parser(subparsers) -> None:
    hil = subparsers.add_parser("hil", help="run one grasp episode hardware-in-the-loop")
    hil.add_argument("--config", default="hil", help="scenario (mode hil): a packaged name (hil) or a YAML path")
    add_horizon(hil, 150)
    hil.add_argument("--rrd", type=argtypes.output_file(".rrd"), help="write a rerun recording of the loop to this .rrd file")
    hil.add_argument("--allow-scenario-mismatch", action="store_true", help=MISMATCH_HELP)
    hil.set_defaults(func=run_hil)


def format_rate(name: str, s: dict) -> str:
    """One loop's rate statistics `s` as a line."""
    return (f"{name}: {s.get('rate_hz', 0):.0f} Hz, period p50 {s.get('p50_ms', float('nan')):.2f} ms, "
            f"p99 {s.get('p99_ms', float('nan')):.2f} ms, max {s.get('max_ms', float('nan')):.2f} ms")


def format_world(w: dict) -> str:
    """A world's clock statistics `w` (HilWorld.stats) as a line."""
    return (f"world: {w['sim_time_s']:.2f} s simulated in {w['wall_s']:.2f} s wall "
            f"(real-time factor {w['real_time_factor']:.2f}), step p50 {w['step_p50_ms']:.2f} ms "
            f"p99 {w['step_p99_ms']:.2f} ms wall, late hand replies {w['late_replies']:.0f}")


def run_hil(args: argparse.Namespace) -> int:
    from dexdrake.systems.controllers import make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import ScenarioError, load_scenario
    from dexdrake.systems.station import make_station

    scenario = load_scenario(args.config)
    if scenario.mode != "hil":
        raise ScenarioError(f"{args.config} is a {scenario.mode} scenario; `hil` needs emulated drivers")
    rrd = args.rrd or (scenario.rrd and check_writable(Path(scenario.rrd), folder=False))
    # refused before any device starts
    controller, description = make_controller(scenario, args.allow_scenario_mismatch)
    logger = None
    if rrd:
        from dexdrake.systems.rerun_logger import RerunLogger

        logger = RerunLogger(rrd, scenario.mode, scenario=scenario)
    with make_station(scenario) as station:
        if logger is not None:
            logger.attach(station)
        result = run_station_episode(station, controller, args.horizon, logger)
    if logger is not None:
        logger.close()
    print(f"hil: {scenario.object} seed={scenario.seed} controller={description}")
    print(f"success={result.success} max_lift={result.max_lift:.3f} m steps={result.steps} "
          f"wall={result.wall_s:.1f} s" + (f" rrd={rrd}" if rrd else ""))
    clock = "simulated clock" if scenario.mode == "hil" else "wall clock"
    print(f"  loop rates on the devices' {clock}:")
    for key, name in (("can", "CAN (Allegro PD loop)"), ("z1", "Z1 UDP loop"), ("policy", "policy/control")):
        if key in result.stats:
            print("    " + format_rate(name, result.stats[key]))
    world = result.stats.get("world")
    if world:
        print("  " + format_world(world))
    print(f"  policy on the wall clock: {result.stats['policy']['wall_rate_hz']:.1f} Hz, "
          f"non-finite commands held {result.stats['policy']['non_finite']}, "
          f"clipped {result.stats['policy']['clipped']}")
    if result.fault:
        print(f"  stopped safely: {result.fault}")
        return 1
    return 0
