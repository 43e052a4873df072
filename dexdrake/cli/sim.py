"""Sub-commands `sim` (one episode) and `models check` (parse every robot model)."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from dexdrake import argtypes

CONTROLLERS = ("scripted",)
MIN_TIME_STEP = 1e-4  # s: 200 plant steps per control step; smaller ones take hours per episode


def add_parser(subparsers) -> None:
    sim = subparsers.add_parser("sim", help="run one simulated grasp episode")
    sim.add_argument("--hand", default="adroit")
    sim.add_argument("--object", default="sphere_medium")
    sim.add_argument("--controller", default="scripted", help=f"one of {', '.join(CONTROLLERS)}")
    sim.add_argument("--seed", type=argtypes.seed, default=0)
    sim.add_argument("--steps", type=argtypes.count, default=150, help="control steps (50 Hz)")
    sim.add_argument("--time-step", type=argtypes.float_in(MIN_TIME_STEP, 0.02, low_open=False),
                     help="plant step (s); default: the scene's (5 ms); must divide the 0.02 s control period, "
                          f"at least {MIN_TIME_STEP:g} s")
    sim.add_argument("--rrd", type=argtypes.output_file(".rrd"),
                     help="write a rerun recording to this .rrd file")
    sim.set_defaults(func=run_sim)

    models = subparsers.add_parser("models", help="robot model utilities")
    models_sub = models.add_subparsers(dest="models_command", required=True)
    check = models_sub.add_parser("check", help="parse every model and print its DoF counts")
    check.set_defaults(func=run_models_check)


def _validate_names(args: argparse.Namespace) -> None:
    from dexdrake.errors import DexdrakeError, UnknownNameError
    from dexdrake.hands.description import load_hand
    from dexdrake.objects.library import get_object
    from dexdrake.systems.scenario import is_multiple
    from dexdrake.systems.scene import SceneConfig

    period = SceneConfig.control_period
    if args.time_step is not None and not is_multiple(period, args.time_step):
        raise DexdrakeError(f"--time-step {args.time_step:g} must divide the control period "
                            f"({period:g} s) a whole number of times, e.g. 0.005 or 0.002")
    load_hand(args.hand)
    get_object(args.object)
    if args.controller not in CONTROLLERS:
        raise UnknownNameError("controller", args.controller, CONTROLLERS)


def run_sim(args: argparse.Namespace) -> int:
    _validate_names(args)
    from dexdrake.systems.grasp_env import GraspEnv
    from dexdrake.systems.scene import SceneConfig
    from dexdrake.systems.scripted_grasp import ScriptedGrasp

    config = SceneConfig(hand=args.hand, object=args.object)
    if args.time_step is not None:
        config = replace(config, time_step=args.time_step)
    env = GraspEnv(config, horizon=args.steps)
    logger = None
    if args.rrd:
        from dexdrake.systems.rerun_logger import RerunLogger

        logger = RerunLogger(args.rrd, "sim")
    start = time.perf_counter()
    summary = env.rollout(ScriptedGrasp, args.seed, logger=logger)
    wall = time.perf_counter() - start
    if logger is not None:
        logger.close()
    print(
        f"object={summary.object} seed={summary.seed} success={summary.success} "
        f"max_lift={summary.max_lift:.3f}m steps={summary.steps} reward={summary.total_reward:.1f} wall={wall:.2f}s"
        + (f" rrd={args.rrd}" if args.rrd else "")
    )
    return 0


def run_models_check(args: argparse.Namespace) -> int:
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    from dexdrake.hands.description import hand_names, load_hand

    print(f"{'hand':<14}{'model':<34}{'positions':>10}{'actuators':>10}{'bodies':>8}")
    for name in hand_names():
        hand = load_hand(name)
        plant = MultibodyPlant(0.0)
        Parser(plant).AddModels(hand.model_path)
        plant.Finalize()
        print(f"{name:<14}{hand.model:<34}{plant.num_positions():>10}{plant.num_actuators():>10}{plant.num_bodies():>8}")
    return 0
