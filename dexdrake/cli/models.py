"""Sub-command `models check`: parse every robot model and print its DoF counts."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    models = subparsers.add_parser("models", help="robot model utilities")
    models_sub = models.add_subparsers(dest="models_command", required=True)
    check = models_sub.add_parser("check", help="parse every model and print its DoF counts")
    check.set_defaults(func=run_models_check)


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
