"""The Unitree Z1 as its model file describes it: limits, LOWCMD gains, payload and gravity.

One source of truth for every arm constant the drivers use: the `allegro_z1` hand
description's model (models/allegro/allegro_z1.urdf, generated from specs/z1.md by
scripts/build_allegro_models.py). Read from it:
  position, velocity and effort limits of joint1..joint6;
  the default LOWCMD gains: the model's Drake actuator gains are the controller's
    effective gains, kp * KP_SCALE and kd * KD_SCALE (specs/z1.md), divided back here;
  the payload: the mass carried beyond the flange (the Allegro hand), which the vendor
    controller must be told about (`load` in z1_controller/config/config.xml);
  gravity feed-forward: the inverse dynamics of the arm with the hand attached at zero
    velocity and acceleration (as the vendor's LOWCMD example sends it), hand joints at 0.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import cache

import numpy as np

from dexdrake.hardware.safety import HardwareError

KP_SCALE, KD_SCALE = 25.6, 0.0128  # LOWCMD gain scales on the controller side (specs/z1.md)
NUM_ARM_JOINTS = 6
MODEL_HAND = "allegro_z1"  # the hand description whose model holds the Z1


@dataclass(frozen=True)
class Z1Limits:
    """Per-joint limits and default LOWCMD gains of joint1..joint6 (from the model)."""

    lower: np.ndarray  # rad
    upper: np.ndarray  # rad
    velocity: np.ndarray  # rad/s
    effort: np.ndarray  # N*m
    kp: np.ndarray  # raw LOWCMD kp (the controller multiplies by KP_SCALE)
    kd: np.ndarray  # raw LOWCMD kd (x KD_SCALE)
    source: str  # the model file they were read from


class Z1Model:
    """The arm and its payload from the model file; `gravity(q)` is thread safe."""

    def __init__(self, hand_name: str = MODEL_HAND):
        from pydrake.multibody.parsing import Parser
        from pydrake.multibody.plant import MultibodyPlant

        from dexdrake.hands.description import load_hand

        hand = load_hand(hand_name)
        if len(hand.arm_joints) != NUM_ARM_JOINTS:
            raise HardwareError(f"hand {hand_name!r} has {len(hand.arm_joints)} arm joints, "
                                f"the Z1 has {NUM_ARM_JOINTS}")
        plant = MultibodyPlant(0.0)
        (robot,) = Parser(plant).AddModels(str(hand.model_path))
        plant.Finalize()
        joints = [plant.GetJointByName(name, robot) for name in hand.arm_joints]
        actuators = {plant.get_joint_actuator(i).joint().name(): plant.get_joint_actuator(i)
                     for i in plant.GetJointActuatorIndices(robot)}
        gains = [actuators[j.name()].get_controller_gains() for j in joints]
        self.limits = Z1Limits(
            lower=np.array([j.position_lower_limits()[0] for j in joints]),
            upper=np.array([j.position_upper_limits()[0] for j in joints]),
            velocity=np.array([j.velocity_upper_limits()[0] for j in joints]),
            effort=np.array([actuators[j.name()].effort_limit() for j in joints]),
            kp=np.array([g.p for g in gains]) / KP_SCALE,
            kd=np.array([g.d for g in gains]) / KD_SCALE,
            source=hand.model)
        flange = joints[-1].child_body()
        carried = plant.GetBodiesKinematicallyAffectedBy([joints[-1].index()])
        self.payload_kg = float(sum(plant.get_body(b).default_mass() for b in carried
                                    if b != flange.index()))
        self._plant = plant
        self._context = plant.CreateDefaultContext()
        self._q_index = np.array([j.position_start() for j in joints])
        self._v_index = np.array([j.velocity_start() for j in joints])
        self._q = np.zeros(plant.num_positions())
        self._lock = threading.Lock()

    def gravity(self, q_arm: np.ndarray) -> np.ndarray:
        """Joint torques (N*m) that hold the arm and its payload still at `q_arm`."""
        with self._lock:
            self._q[self._q_index] = q_arm
            self._plant.SetPositions(self._context, self._q)
            tau_g = self._plant.CalcGravityGeneralizedForces(self._context)
        return -tau_g[self._v_index]


@cache
def z1_model() -> Z1Model:
    """The shared Z1 model of the `allegro_z1` description (parsed once)."""
    return Z1Model()
