"""The one map between a policy's normalised actions (each in [-1, 1], policy order) and
joint set-points, for each way of commanding the arm (ARM_ACTIONS):

- "joints": set-point = mid + action * half over each joint's range (the model's limits).
- "palm_pose" (hands whose description has a `palm_pose_action`): the arm's six actions are
  the palm's grasp-centre position, mid + action * half over the description's box, and its
  rotation R = R_ref exp(action * rotation) (a rotation vector, R_ref the palm's rotation at
  the pre-grasp pose). Their set-points are the arm's inverse kinematics of that pose
  (ArmIK.step, to convergence) from the measured arm positions, so the map is the same wherever the arm is
  measured (simulation, hardware). The fingers' actions map as in "joints".
- "palm_step" (a `palm_pose_action` with `step` and `step_rotation`): the arm's six actions move
  the palm from its measured pose (forward kinematics of the measured arm): the grasp centre by
  action * step, kept in the box, and its rotation to R = exp(action * step_rotation) R_measured
  (a world-frame rotation vector); set-points by the same inverse kinematics. An action of 0
  holds the palm where it is measured.

A joint's action outside [-1, 1] maps beyond its limits and a non-finite one to a non-finite
set-point: the command guard clips the one and holds the other, counting both
(dexdrake/command_guard.py). Palm actions are clipped to [-1, 1] before the IK; non-finite ones
leave the arm's set-points non-finite."""

from __future__ import annotations

import numpy as np
from pydrake.math import RotationMatrix

from dexdrake.errors import DexdrakeError, UnknownNameError
from dexdrake.hands.arm_ik import ArmIK
from dexdrake.hands.description import HandDescription
from dexdrake.hands.kinematics import hand_kinematics
from dexdrake.perceived_pose import rotation_from_vector

ARM_ACTIONS = ("joints", "palm_pose", "palm_step")
IK_STEPS, IK_TOLERANCE = 30, 1e-6  # the palm pose's IK: at most this many steps, to this weighted error (m)


class ActionMap:
    """Normalised actions <-> joint set-points of `hand` with its arm commanded as `arm_action`
    (module docstring)."""

    def __init__(self, hand: HandDescription, arm_action: str = "joints"):
        if arm_action not in ARM_ACTIONS:
            raise UnknownNameError("arm action", arm_action, ARM_ACTIONS)
        lo, hi = hand.joint_limits()
        self.hand, self.arm_action = hand, arm_action
        self.mid, self.half = (hi + lo) / 2, (hi - lo) / 2
        self.n_arm = len(hand.arm_joints) if arm_action != "joints" else 0
        self.steps = arm_action == "palm_step"
        if self.n_arm:
            box = hand.palm_pose_action
            if box is None or self.n_arm != 6 or (self.steps and not box.step):
                raise DexdrakeError(f"hand {hand.name!r} has no {arm_action} arm action (a six-joint arm and "
                                    f"`palm_pose_action`{' with step and step_rotation' if self.steps else ''} "
                                    "in its description)")
            self.ik = ArmIK(hand_kinematics(hand))
            self._lower, self._upper = np.array(box.lower), np.array(box.upper)
            self._centre_mid, self._centre_half = (self._upper + self._lower) / 2, (self._upper - self._lower) / 2
            self._rotation = box.rotation
            self._step, self._step_rotation = box.step, box.step_rotation
            self._R_ref = self.ik.palm_pose(hand.pregrasp_vector()[: self.n_arm])[1]

    def command(self, action: np.ndarray, q_measured: np.ndarray) -> np.ndarray:
        """The joint set-points of `action`, the arm's solved from the measured positions
        `q_measured` (policy order; not read by "joints")."""
        a = np.asarray(action, dtype=float)
        q = self.mid + a * self.half
        if self.n_arm:
            n = self.n_arm
            a = np.clip(a, -1.0, 1.0)
            if not np.isfinite(a[:n]).all():
                q[:n] = np.nan
                return q
            q_arm = np.asarray(q_measured, dtype=float)[:n]
            if self.steps:
                centre, R = self.ik.palm_pose(q_arm)
                centre = np.clip(centre + a[:3] * self._step, self._lower, self._upper)
                R = rotation_from_vector(a[3:n] * self._step_rotation) @ R
            else:
                centre = self._centre_mid + a[:3] * self._centre_half
                R = self._R_ref @ rotation_from_vector(a[3:n] * self._rotation)
            q[:n] = self.ik.step(centre, R, q_arm, IK_STEPS, IK_TOLERANCE)
        return q

    def normalise(self, q_command: np.ndarray, q_measured: np.ndarray | None = None) -> np.ndarray:
        """The action (unclipped) whose set-points are `q_command` from the measured positions
        `q_measured` (needed by "palm_step" only): the inverse of `command` (for the palm's
        actions, up to the inverse kinematics' branch, the one nearest the arm)."""
        q = np.asarray(q_command, dtype=float)
        a = (q - self.mid) / self.half
        if self.n_arm:
            centre, R = self.ik.palm_pose(q[: self.n_arm])
            if self.steps:
                if q_measured is None:
                    raise ValueError("palm_step actions are relative to the measured arm: pass q_measured")
                measured, R_measured = self.ik.palm_pose(np.asarray(q_measured, dtype=float)[: self.n_arm])
                a[:3] = (centre - measured) / self._step
                a[3: self.n_arm] = _log(R @ R_measured.T) / self._step_rotation
            else:
                a[:3] = (centre - self._centre_mid) / self._centre_half
                a[3: self.n_arm] = _log(self._R_ref.T @ R) / self._rotation
        return a


def _log(R: np.ndarray) -> np.ndarray:
    """The rotation vector of rotation matrix R (angle in [0, pi])."""
    aa = RotationMatrix(R).ToAngleAxis()
    return aa.angle() * aa.axis()
