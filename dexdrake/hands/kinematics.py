"""A plant of a hand's model alone, for kinematics outside a scene: the arm's base welded
where the model puts it (the world frame of every mode), no object, no table."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import ModelInstanceIndex

from dexdrake.hands.description import HandDescription


@dataclass(frozen=True)
class HandKinematics:
    """The fields of a GraspScene that kinematics reads (dexdrake.hands.arm_ik.ArmIK)."""

    hand: HandDescription
    plant: MultibodyPlant
    hand_instance: ModelInstanceIndex
    q_index: np.ndarray  # plant position index of each policy joint


def hand_kinematics(hand: HandDescription) -> HandKinematics:
    """A finalised plant of `hand`'s model alone."""
    plant = MultibodyPlant(0.0)
    (instance,) = Parser(plant).AddModels(hand.model_path)
    plant.Finalize()
    q_index = np.array([plant.GetJointByName(j, instance).position_start() for j in hand.policy_joints])
    return HandKinematics(hand, plant, instance, q_index)
