"""A scripted grasp controller: approach, descend, close, lift to the target, hold.

It proves the physics can grasp and serves as a baseline. The arm set-points come from the
arm's inverse kinematics (dexdrake/hands/arm_ik.py), placing the palm's grasp centre (hand description
`palm.centre`) at a way-point with the palm facing down and the fingers turned across the
object's shorter horizontal axis; the fingers move between the pre-grasp pose and a closed
pose.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from pydrake.math import RigidTransform

from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import HandDescription
from dexdrake.objects.library import ObjectInfo
from dexdrake.hands.arm_ik import ArmIK


@dataclass(frozen=True)
class GraspScript:
    """Phase end times (s) and geometry of the scripted grasp."""

    approach_end: float = 0.5
    descend_end: float = 0.9
    close_end: float = 1.3
    lift_end: float = 2.1
    hover: float = 0.06  # approach way-point: this far above the object's top (m)
    palm_depth: float = 0.045  # grasp centre this far below the object's top (m), except ...
    tall_palm_depth: float = 0.028  # ... on tall objects (top more than palm_depth + tall_margin
    tall_margin: float = 0.01  # above the centre), which are grasped around their upper part
    min_height: float | None = None  # grasp centre at least this above the table (m; None: no floor)
    reach: float = -0.03  # grasp centre shift along the fingers' direction (m) ...
    reach_edge: float = 0.0  # ... plus this fraction of the footprint's half-width there (1: the shift
    # counts from the footprint's far edge, e.g. a pinch on a rim; 0: from the object's origin)
    side: float = 0.0  # grasp centre shift across the fingers, to their left seen from above (m;
    # centres a pinch whose fingertips lie to one side of the palm's grasp centre)
    lift: float = 0.17  # lift height of the grasp centre (m)
    lift_lead: float | None = None  # the expert's arm set-point lead while lifting (normalised action
    # units; None: the hand's `ReactiveRules.lift_lead`): a slower lift shakes a pinched object less
    closure: float = 1.0  # fraction of each finger joint's closing range
    closed_pose: str = ""  # a named hand-description grasp pose for some joints ("": closing rule only)
    open_pose: str = ""  # a named grasp pose the open hand already takes (e.g. the thumb pre-shaped to oppose)
    orientation_weight: float = 0.01  # IK weight of palm rotation error (m per unit)
    ik_damping: float = 1e-3  # damping of `ArmIK.step`'s least-squares steps (m)
    round_footprint: float = 0.15  # footprint widths within this fraction of each other: round, yaw kept
    max_yaw: float | None = None  # the palm turns at most this far about the vertical from its pre-grasp
    # rotation (rad; None: up to the footprint's symmetry, a quarter or half turn)
    closed_hold: float | None = None  # settled fingers closed this far hold the object (closure fraction;
    # None: the hand's `ReactiveRules.closed_hold`; a pinch whose fingers sweep far before they reach a
    # thin object holds it only when the thumb and a finger touch it: above 1)


def with_overrides(cls, overrides: dict, hand: HandDescription, key: str):
    """`cls()` with the fields a hand description overrides under `key` (unknown names refused)."""
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise DexdrakeError(f"hand {hand.name!r}: {key} has unknown fields {unknown}; known: {sorted(names)}")
    return cls(**overrides)


def script_for(hand: HandDescription) -> GraspScript:
    """The grasp geometry and timing for `hand`: GraspScript with its description's `grasp_script`."""
    return with_overrides(GraspScript, hand.grasp_script, hand, "grasp_script")


def open_pose(hand: HandDescription, pose: str = "") -> np.ndarray:
    """The pre-grasp pose, with the joints of the hand's grasp pose named `pose` (if any) at
    that pose's set-points (clamped into the joint limits)."""
    if pose and pose not in hand.grasp_poses:
        raise DexdrakeError(f"hand {hand.name!r} has no grasp pose {pose!r}; known: {sorted(hand.grasp_poses)}")
    named = hand.grasp_poses.get(pose, {})
    lo, hi = hand.joint_limits()
    q = hand.pregrasp_vector()
    for i, joint in enumerate(hand.policy_joints):
        if joint in named:
            q[i] = np.clip(named[joint], lo[i], hi[i])
    return q


def closed_pose(hand: HandDescription, closure: float = 1.0, pose: str = "") -> np.ndarray:
    """Finger set-points of a power grasp: the pre-grasp pose moved toward each joint's
    limit in the flexion direction (`hand.closing` signs), arm joints untouched; the joints
    of the hand's grasp pose named `pose` (if any) take that pose's set-points instead."""
    q = open_pose(hand, pose)
    named = hand.grasp_poses.get(pose, {})
    lo, hi = hand.joint_limits()
    for i, joint in enumerate(hand.policy_joints):
        sign = 0.0 if joint in named else hand.closing.get(joint, 0.0)
        if sign > 0:
            q[i] += closure * (hi[i] - q[i])
        elif sign < 0:
            q[i] += closure * (lo[i] - q[i])
    return q


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _smooth(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10 - 15 * s + 6 * s * s)  # minimum-jerk profile


@dataclass(frozen=True)
class GraspPlan:
    """Where the hand grasps: the palm rotation and the grasp centre's way-points (world
    frame), reached in the order above -> grasp -> lift."""

    R: np.ndarray
    above: np.ndarray
    grasp: np.ndarray
    lift: np.ndarray


def plan_grasp(script: GraspScript, info: ObjectInfo, X_obj: RigidTransform, R_start: np.ndarray) -> GraspPlan:
    """The grasp for an object at pose X_obj, from its shape (extents, footprint) and pose
    only: the palm turned from rotation R_start across the footprint's shorter axis, the
    grasp centre below the object's top (deeper on tall objects); the turn is clipped to the
    script's `max_yaw`, so a palm that cannot turn across the short axis grasps it obliquely."""
    widths = info.footprint_widths()
    is_round = widths.max() - widths.min() < script.round_footprint * widths.max()
    yaw = 0.0 if is_round else _grasp_yaw(R_start, X_obj.rotation().matrix(), info.extents)
    if script.max_yaw is not None:
        yaw = float(np.clip(yaw, -script.max_yaw, script.max_yaw))
    R = _rot_z(yaw) @ R_start
    fingers_dir = R[:, 2].copy()
    fingers_dir[2] = 0.0
    fingers_dir /= np.linalg.norm(fingers_dir)
    p_obj = X_obj.translation()
    top = p_obj[2] + info.extents[2] / 2
    tall = top - script.palm_depth > p_obj[2] + script.tall_margin
    height = top - (script.tall_palm_depth if tall else script.palm_depth)
    if script.min_height is not None:
        height = max(height, script.min_height)
    reach = script.reach + script.reach_edge * _half_width(info, X_obj.rotation().matrix(), fingers_dir)
    up = np.array([0.0, 0.0, 1.0])
    across = np.cross(up, fingers_dir)  # horizontal, to the left of the fingers seen from above
    grasp = np.array([p_obj[0], p_obj[1], height]) + reach * fingers_dir + script.side * across
    return GraspPlan(R, grasp + (top - height + script.hover) * up, grasp, grasp + script.lift * up)


def _half_width(info: ObjectInfo, R_obj: np.ndarray, direction: np.ndarray) -> float:
    """Half the object's footprint width along a horizontal world `direction` (its resting
    footprint's width across the nearest of `footprint_widths`' directions)."""
    d = R_obj.T @ direction
    widths = info.footprint_widths()
    angle = np.arctan2(d[1], d[0]) % np.pi
    return float(widths[int(round(angle / np.pi * len(widths))) % len(widths)] / 2)


def _grasp_yaw(R_start: np.ndarray, R_obj: np.ndarray, extents) -> float:
    """Yaw (about world z) that turns the fingers across the object's shorter horizontal
    axis; square footprints have a quarter-turn symmetry, others a half turn. (Round
    footprints, whose yaw a policy cannot see, are not turned; see `plan_grasp`.)"""
    ex, ey = extents[0], extents[1]
    short_axis = R_obj[:, 1] if ex >= ey else R_obj[:, 0]
    period = np.pi / 2 if abs(ex - ey) < 0.15 * max(ex, ey) else np.pi
    f = R_start[:, 2]
    yaw = np.arctan2(short_axis[1], short_axis[0]) - np.arctan2(f[1], f[0])
    return float((yaw + period / 2) % period - period / 2)


class ScriptedGrasp:
    """Callable controller for `GraspEnv.rollout`: returns joint set-points each step.

    It reads the world through the env only: `scene` (hand, plant, object info),
    `plant_context` (the measured hand positions), `object_pose()` (where the object is
    seen: the plant in simulation, perception on the station) and `context.get_time()`."""

    def __init__(self, env, script: GraspScript | None = None):
        self.script = script or script_for(env.scene.hand)
        self.hand = env.scene.hand
        self.ik = ArmIK(env.scene, self.script.orientation_weight, self.script.ik_damping)
        self.n_arm = len(self.hand.arm_joints)
        self.lo, self.hi = self.hand.joint_limits()
        self.q_open = open_pose(self.hand, self.script.open_pose)
        self.q_closed = closed_pose(self.hand, self.script.closure, self.script.closed_pose)
        self.R_pregrasp = self.ik.palm_pose(self.q_open[: self.n_arm])[1]  # the palm's rotation every grasp turns from
        self._plan(env)

    def _plan(self, env) -> None:
        self.q_start_arm = env.scene.hand_positions(env.plant_context)[: self.n_arm]
        self.plan = self._grasp_plan(env)
        self.R_grasp = self.plan.R
        self.q_above = self.ik.solve(self.plan.above, self.q_start_arm, self.R_grasp)
        self.q_grasp = self.ik.solve(self.plan.grasp, self.q_above, self.R_grasp)
        self.q_lift = self.ik.solve(self.plan.lift, self.q_grasp, self.R_grasp)

    def _grasp_plan(self, env) -> GraspPlan:
        """The grasp plan for the object where it is now (the palm's pre-grasp rotation as reference)."""
        return plan_grasp(self.script, env.scene.object_info, env.object_pose(), self.R_pregrasp)

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
