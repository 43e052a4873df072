"""Sub-command `sim`: one episode, of a scenario's sim station or of GraspEnv."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from dexdrake import argtypes
from dexdrake.cli.flags import MISMATCH_HELP, add_horizon
from dexdrake.errors import DexdrakeError

CONTROLLERS = ("scripted", "expert")
MIN_TIME_STEP = 1e-4  # s: 200 plant steps per control step; smaller ones take hours per episode


def add_parser(subparsers) -> None:
    sim = subparsers.add_parser(
        "sim", help="run one simulated grasp episode",
        description="One simulated grasp episode. With --config, the sim station of a scenario (a packaged "
                    "name: sim; or a YAML path) in the diagram of hil and real, its policy or --policy or "
                    "--controller in the slot; without, GraspEnv with --hand and --object.")
    sim.add_argument("--config", help="sim scenario: a packaged name (sim) or a YAML path")
    sim.add_argument("--hand", help="hand (default: the scenario's; without --config: adroit)")
    sim.add_argument("--object", help="object (default: the scenario's; without --config: sphere_medium)")
    slot = sim.add_mutually_exclusive_group()
    slot.add_argument("--policy", type=Path, help="policy checkpoint in the slot (--config only; default: "
                      "the scenario's policy, else the scripted grasp)")
    slot.add_argument("--controller", help=f"one of {', '.join(CONTROLLERS)} (default: scripted, or the "
                      "scenario's policy with --config)")
    sim.add_argument("--allow-scenario-mismatch", action="store_true", help=MISMATCH_HELP)
    sim.add_argument("--seed", type=argtypes.seed, help="episode seed (default: the scenario's; without --config: 0)")
    add_horizon(sim, 150)
    sim.add_argument("--time-step", type=argtypes.float_in(MIN_TIME_STEP, 0.02, low_open=False),
                     help="plant step (s); default: the scenario's (5 ms); must divide the 0.02 s control period, "
                          f"at least {MIN_TIME_STEP:g} s")
    sim.add_argument("--rrd", type=argtypes.output_file(".rrd"),
                     help="write a rerun recording to this .rrd file")
    sim.set_defaults(func=run_sim)


def _scenario(args: argparse.Namespace):
    """The validated sim Scenario of the flags: --config's (or the training scenario of
    --hand and --object), with --hand, --object, --seed and --time-step applied."""
    from dexdrake.errors import UnknownNameError
    from dexdrake.systems.env_factory import training_scenario
    from dexdrake.systems.scenario import ScenarioError, load_scenario, validate_scenario

    if args.controller is not None and args.controller not in CONTROLLERS:
        raise UnknownNameError("controller", args.controller, CONTROLLERS)
    if args.config is None:
        if args.policy is not None:
            raise DexdrakeError("--policy runs in a scenario's station: give --config (e.g. --config sim)")
        scenario = training_scenario(args.hand or "adroit", args.object or "sphere_medium")
        source = "--hand/--object"
    else:
        scenario = load_scenario(args.config)
        source = args.config
        if scenario.mode != "sim":
            raise ScenarioError(f"{args.config} is a {scenario.mode} scenario; `sim` needs simulated drivers "
                                f"(`dexdrake {scenario.mode} --config {args.config}`)")
    changes = {k: v for k, v in (("hand", args.hand), ("object", args.object), ("seed", args.seed),
                                 ("time_step", args.time_step)) if v is not None}
    scenario = replace(scenario, **changes)
    try:
        validate_scenario(scenario, source)
    except ScenarioError as err:
        flags = ", ".join(f"--{k.replace('_', '-')}" for k in changes)
        raise ScenarioError(f"{err}" + (f" (after {flags})" if flags else "")) from None
    return scenario


def run_sim(args: argparse.Namespace) -> int:
    scenario = _scenario(args)
    logger = None
    if args.rrd:
        from dexdrake.systems.rerun_logger import RerunLogger

        logger = RerunLogger(args.rrd, "sim", **({} if args.config is None else {"scenario": scenario}))
    try:
        line = _run_env(scenario, args, logger) if args.config is None else _run_station(scenario, args, logger)
    finally:
        if logger is not None:
            logger.close()
    print(line + (f" rrd={args.rrd}" if args.rrd else ""))
    return 0


def _run_env(scenario, args: argparse.Namespace, logger) -> str:
    """One GraspEnv episode of the scripted grasp or the expert."""
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.reactive_grasp import ReactiveGrasp
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    env = GraspEnv(scenario, horizon=args.horizon)
    make = ReactiveGrasp if args.controller == "expert" else ScriptedGrasp
    start = time.perf_counter()
    summary = env.rollout(make, scenario.seed, logger=logger)
    wall = time.perf_counter() - start
    return (f"object={summary.object} seed={summary.seed} success={summary.success} "
            f"max_lift={summary.max_lift:.3f}m steps={summary.steps} reward={summary.total_reward:.1f} wall={wall:.2f}s")


def _run_station(scenario, args: argparse.Namespace, logger) -> str:
    """One episode of the scenario's sim station in the diagram of every mode."""
    from dexdrake.learn.policy import load_policy
    from dexdrake.systems.controllers import expert_controller, make_controller
    from dexdrake.systems.diagram import run_station_episode
    from dexdrake.systems.scenario import PolicyEntry
    from dexdrake.systems.station import make_station

    if args.policy is not None:
        feature_set = load_policy(args.policy)[0].config.feature_set
        scenario = replace(scenario, policy=PolicyEntry(checkpoint=str(args.policy), feature_set=feature_set))
    elif args.controller is not None:
        scenario = replace(scenario, policy=None)
    if args.controller == "expert":
        controller, description = expert_controller(scenario), "expert (ReactiveGrasp)"
    else:
        controller, description = make_controller(scenario, args.allow_scenario_mismatch)
    station = make_station(scenario)
    if logger is not None:
        logger.attach(station)
    result = run_station_episode(station, controller, args.horizon, logger)
    print(f"sim: {scenario.object} seed={scenario.seed} controller={description}")
    return (f"success={result.success} max_lift={result.max_lift:.3f} m steps={result.steps} "
            f"wall={result.wall_s:.1f} s" + (f" fault={result.fault}" if result.fault else ""))
