"""A scripted grasp controller: approach, descend, close, lift to the target, hold.

It proves the physics can grasp and serves as a baseline. The arm set-points come from a
small inverse-kinematics solve that places the palm's grasp centre (hand description
`palm.centre`) at a way-point while keeping the arm's rotation joints near their pre-grasp
values; the fingers move between the pre-grasp pose and a closed pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from dexdrake.hands.description import HandDescription


@dataclass(frozen=True)
class GraspScript:
    """Phase end times (s) and geometry of the scripted grasp."""

    approach_end: float = 0.5
    descend_end: float = 0.9
    close_end: float = 1.3
    lift_end: float = 2.1
    hover: float = 0.06  # approach way-point: this far above the object's top (m)
    grasp_depth: float = 0.0  # grasp centre height above the object centre (m), except ...
    top_clearance: float = 0.028  # ... tall objects: this far below the top, when that is ...
    tall_margin: float = 0.02  # ... more than this above the centre height
    reach: float = -0.03  # grasp centre shift along the fingers' direction (m)
    lift: float = 0.17  # lift height of the grasp centre (m)
    closure: float = 1.0  # fraction of each finger joint's closing range


def closed_pose(hand: HandDescription, closure: float = 1.0) -> np.ndarray:
    """Finger set-points of a power grasp: the pre-grasp pose moved toward each joint's
    limit in the flexion direction (`hand.closing` signs), arm joints untouched."""
    lo, hi = hand.joint_limits()
    q = hand.pregrasp_vector()
    for i, joint in enumerate(hand.policy_joints):
        sign = hand.closing.get(joint, 0.0)
        if sign > 0:
            q[i] += closure * (hi[i] - q[i])
        elif sign < 0:
            q[i] += closure * (lo[i] - q[i])
    return q


def _smooth(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10 - 15 * s + 6 * s * s)  # minimum-jerk profile


class ScriptedGrasp:
    """Callable controller for `GraspEnv.rollout`: returns joint set-points each step."""

    def __init__(self, env, script: GraspScript = GraspScript()):
        self.script = script
        scene = env.scene
        self.hand = scene.hand
        plant = scene.plant
        self.plant, self.ctx = plant, plant.CreateDefaultContext()
        self.palm_frame = plant.GetFrameByName(self.hand.palm.body, scene.hand_instance)
        self.centre = np.array(self.hand.palm.centre)
        self.q_index = scene.q_index
        self.n_arm = len(self.hand.arm_joints)
        self.lo, self.hi = self.hand.joint_limits()
        self.q_open = self.hand.pregrasp_vector()
        self.q_closed = closed_pose(self.hand, script.closure)
        self._plan(env)

    def _grasp_centre(self, q_arm: np.ndarray) -> np.ndarray:
        q = self.plant.GetPositions(self.ctx)
        q[self.q_index[: self.n_arm]] = q_arm
        self.plant.SetPositions(self.ctx, q)
        return self.plant.CalcPointsPositions(self.ctx, self.palm_frame, self.centre, self.plant.world_frame())[:, 0]

    def solve_arm(self, target: np.ndarray, q_seed: np.ndarray) -> np.ndarray:
        """Arm set-points that put the grasp centre at `target` (rotations kept near seed)."""
        lo, hi = self.lo[: self.n_arm], self.hi[: self.n_arm]
        nominal = self.q_open[: self.n_arm]
        weight = np.full(self.n_arm, 0.05)

        def residual(q_arm):
            return np.concatenate([self._grasp_centre(q_arm) - target, weight * (q_arm - nominal)])

        sol = least_squares(residual, np.clip(q_seed, lo, hi), bounds=(lo, hi), xtol=1e-8)
        return sol.x

    def _plan(self, env) -> None:
        q_now = env.scene.hand_positions(env.plant_context)
        self.q_start_arm = q_now[: self.n_arm]
        p_obj = env.object_position()
        fingers_dir = self._finger_direction()
        top = p_obj[2] + env.scene.object_info.extents[2] / 2
        height = p_obj[2] + self.script.grasp_depth
        if top - self.script.top_clearance > height + self.script.tall_margin:
            height = top - self.script.top_clearance
        grasp = np.array([p_obj[0], p_obj[1], height]) + self.script.reach * fingers_dir
        above = grasp + np.array([0.0, 0.0, top - height + self.script.hover])
        lift = grasp + np.array([0.0, 0.0, self.script.lift])
        self.q_above = self.solve_arm(above, self.q_start_arm)
        self.q_grasp = self.solve_arm(grasp, self.q_above)
        self.q_lift = self.solve_arm(lift, self.q_grasp)

    def _finger_direction(self) -> np.ndarray:
        """Horizontal unit vector along the fingers (palm frame +z) at the start pose."""
        self._grasp_centre(self.q_start_arm)
        z = self.palm_frame.CalcPoseInWorld(self.ctx).rotation().matrix()[:, 2].copy()
        z[2] = 0.0
        return z / np.linalg.norm(z)

    def __call__(self, env) -> np.ndarray:
        t, s = env.context.get_time(), self.script
        if t < s.approach_end:
            arm = self._blend(self.q_start_arm, self.q_above, t / s.approach_end)
            fingers = self.q_open
        elif t < s.descend_end:
            arm = self._blend(self.q_above, self.q_grasp, (t - s.approach_end) / (s.descend_end - s.approach_end))
            fingers = self.q_open
        elif t < s.close_end:
            arm = self.q_grasp
            fingers = self._blend(self.q_open, self.q_closed, (t - s.descend_end) / (s.close_end - s.descend_end))
        else:
            arm = self._blend(self.q_grasp, self.q_lift, (t - s.close_end) / (s.lift_end - s.close_end))
            fingers = self.q_closed
        q = np.array(fingers, dtype=float)
        q[: self.n_arm] = arm[: self.n_arm]
        return q

    @staticmethod
    def _blend(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
        return a + _smooth(s) * (b - a)
