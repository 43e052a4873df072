"""The grasp expert (`ReactiveGrasp`): the scripted grasp's way-points, chosen from the current state.

`ScriptedGrasp` follows a clock: its set-point at a hand state depends on the time, which a
policy does not observe. The grasp expert decides its phase from the state alone (hand
joints, grasp-centre position, fingertip-to-surface distances, object height), so it labels
any state a learning policy visits (DAgger) and re-tries when a grasp fails:

- fingers closed on the object near the grasp point (thumb and another fingertip touching,
  or settled well closed), or the object already lifted (above its start and, where the
  hand's rules say so, near a fingertip: one dropped onto its side rests higher without
  being in the hand, and a lift that steers it back would chase it) with the fingers started
  closing (or, where the hand's rules say so, the thumb and a finger touching it: a wide object
  spreads them open): lift up from where the hand is, back over the placement range if the
  object has left it, fingers squeezing;
- grasp centre at the grasp point, or just above it with the arm stopped (blocked by the
  object or the table): close the fingers; fingers that have started closing keep closing
  within a wider radius (`keep_xy`: the fingers' closure is the rule's memory, so a policy
  whose hand wavers near the edge is not taught to open and close in turn);
- fingers closed but not on the object (missed or dropped, beyond that radius): open them;
- otherwise reach through a funnel: above the grasp point the target is the grasp point,
  and the farther off horizontally, the closer the target is to the approach way-point
  above it (continuous in the state, so a cloned policy can follow it), reached in joint space or,
  where the hand's rules say so (`approach_step`), along a straight line of the grasp centre
  (IK steps from the measured arm; a revolute arm's joint-space path bows); hands whose finger
  set-points are rate-limited start closing them in the last centimetres of the descent
  (`preclose`).

Arm set-points lead the measured arm joints by at most `max_lead` (normalised action units)
toward the phase's way-point, so the label always says which way to move. The label is a
function of the state, not of the episode's past, so a policy can clone it: the way-points
are solved from one fixed arm seed (the pre-grasp pose), never from the previous way-points,
and re-planned whenever the grasp for the object's pose has moved or turned (`replan_shift`,
`replan_turn`) before the fingers close; the lift keeps the palm's current rotation (not the
plan's) and rises to a height set by the object's resting height. The grasp geometry is
the hand's `GraspScript` with the variant chosen for the object by simulated trials
(`models/weights/<hand>_expert_grasps.json`, `dexdrake expert choose`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from dexdrake.hands.description import HandDescription
from dexdrake.paths import models_dir
from dexdrake.perceived_pose import rotation_from_vector
from dexdrake.systems.scene import ObjectPlacement
from dexdrake.systems.scripted_grasp import (GraspPlan, GraspScript, ScriptedGrasp, plan_grasp, script_for,
                                              with_overrides)


@dataclass(frozen=True)
class ReactiveRules:
    """Thresholds of the phase rules and the arm's set-point lead."""

    max_lead: float = 0.5  # largest arm set-point lead per joint (normalised action units; its trials:
    # models/weights/expert_grasp_table.md)
    at_grasp: float = 0.015  # grasp centre within this of the grasp point: close (m)
    blocked_height: float = 0.03  # ... or within this above it with the arm stopped (blocked) (m)
    stopped_speed: float = 0.15  # arm joints slower than this (m/s or rad/s) have stopped
    above_xy: float = 0.015  # horizontally within this of the grasp point: descend (m) ...
    descend_cone: float = 0.0  # ... plus this much per metre above it (arms whose joint-space descent bows)
    funnel: float = 0.02  # beyond that tolerance the target rises to the approach way-point over this (m)
    keep_xy: float = 0.03  # fingers that have started closing keep closing horizontally within this (m)
    touch: float = 0.008  # a fingertip this close to the surface touches it (m)
    fingers_touching: int = 1  # the thumb and this many other fingertips touching hold the object
    closed_hold: float = 0.5  # ... as do settled fingers closed this far
    hold_reach: float = 0.05  # ... with the grasp centre within this of the grasp point (m)
    lift_lead: float = 0.3  # arm set-point lead while lifting (normalised action units)
    started: float = 0.05  # closure fraction above which the fingers have started closing
    closed: float = 0.35  # closure fraction above which the fingers count as closed
    missed: float = 0.9  # fingers this closed without holding have missed
    settled_speed: float = 1.0  # fingers slower than this (rad/s, largest joint) have settled
    lifted: float = 0.01  # object this far above its start is lifted (m) ...
    in_hand: float = float("inf")  # ... with a fingertip within this of its surface (m; inf: its height alone)
    replan_shift: float = 0.003  # re-plan when the grasp point moved this far (m) ...
    replan_turn: float = 0.03  # ... or the palm's grasp rotation turned this far (rad), until the fingers close
    follow_closing: bool = True  # re-plan while the close rule holds (False: the grasp stays where it was
    # when the fingers began closing, so a palm that nudges the object does not chase it)
    preclose: float = 0.0  # descending fingers close this far already (closure fraction) ...
    preclose_height: float = 0.0  # ... once the grasp centre is within this above the grasp point and
    # `keep_xy` beside it (m): rate-limited fingers then reach the object sooner
    lift_steps: int = 3  # IK steps of the lift set-point
    lift_touching: bool = False  # a lifted object the thumb and a finger touch keeps the lift however open
    # the fingers are (a wide object spreads them below `started`; False: the lift needs that closure)
    approach_step: float = 0.0  # reach the funnel's target along a straight line of the grasp centre, this far
    # ahead of it (m; IK steps from the measured arm), the palm turning at most `approach_turn` (rad) ahead
    # (0: straight in joint space, which bows on a revolute arm)
    approach_turn: float = 0.1  # (rad)


def expert_grasps_path(hand: str) -> Path:
    """The hand's table of per-object grasp variants (written by `dexdrake expert choose`)."""
    return models_dir() / "weights" / f"{hand}_expert_grasps.json"


@cache
def _expert_grasps(hand: str) -> dict:
    path = expert_grasps_path(hand)
    return json.loads(path.read_text()) if path.is_file() else {"variants": {}, "objects": {}}


def expert_script(hand: HandDescription, object_name: str) -> GraspScript:
    """The hand's grasp script with the variant chosen for `object_name` by simulated trials
    (the object's shape decides it; objects without an entry get the hand's default)."""
    table = _expert_grasps(hand.name)
    entry = table["objects"].get(object_name)
    script = script_for(hand)
    return replace(script, **table["variants"][entry["variant"]]) if entry else script


def variant_expert(overrides: dict, env) -> ReactiveGrasp:
    """The expert for `env`'s episode with the hand's grasp script changed by `overrides` (a
    grasp variant, dexdrake.eval.expert.VARIANTS): what `dexdrake expert choose` tries."""
    return ReactiveGrasp(env, replace(script_for(env.scene.hand), **overrides))


class ReactiveGrasp(ScriptedGrasp):
    """The grasp expert: a callable controller for `GraspEnv` (like ScriptedGrasp) whose output
    depends on the state only."""

    def __init__(self, env, script: GraspScript | None = None, rules: ReactiveRules | None = None):
        hand = env.scene.hand
        self.rules = rules or with_overrides(ReactiveRules, hand.grasp_expert, hand, "grasp_expert")
        info = env.scene.object_info  # an augmented object is grasped as the one it derives from
        super().__init__(env, script or expert_script(hand, info.derived_from or info.name))
        self.p_start = env.object_position()
        # the lift height: the grasp height on the object at rest, plus the lift
        at_rest = plan_grasp(self.script, info, RigidTransform([0.0, 0.0, info.rest_height]), self.R_pregrasp)
        self.lift_height = at_rest.grasp[2] + self.script.lift
        self.closed_hold = self.rules.closed_hold if self.script.closed_hold is None else self.script.closed_hold
        self._arm_half = (self.hi - self.lo)[: self.n_arm] / 2
        self._span = self.q_closed - self.q_open
        self._fingers = np.abs(self._span) > 1e-9
        self.phase = "approach"
        tips = [p.name for p in self.hand.fingertips]
        self.thumb_tip = next((i for i, name in enumerate(tips) if name.startswith("th")), len(tips) - 1)

    def _plan(self, env) -> None:
        self._solve(self._grasp_plan(env))

    def _solve(self, plan: GraspPlan) -> None:
        """Adopt `plan`: its way-points solved from the fixed arm seed (so they depend on the
        object's pose only, not on when or from where they were planned)."""
        self.plan, self.R_grasp = plan, plan.R
        self.q_above = self.ik.solve(plan.above, self.q_open[: self.n_arm], plan.R)
        self.q_grasp = self.ik.solve(plan.grasp, self.q_above, plan.R)
        self.grasp_point = self.ik.palm_pose(self.q_grasp)[0]
        self.above_point = self.ik.palm_pose(self.q_above)[0]

    def _follow(self, env) -> None:
        """Re-plan when the grasp for the object's pose now has moved or turned beyond the
        thresholds from the adopted one (a cheap check; the IK runs only then)."""
        plan = self._grasp_plan(env)
        turn = RotationMatrix(self.plan.R.T @ plan.R).ToAngleAxis().angle()
        if float(np.linalg.norm(plan.grasp - self.plan.grasp)) > self.rules.replan_shift or turn > self.rules.replan_turn:
            self._solve(plan)

    def closure(self, q: np.ndarray) -> float:
        """How far the fingers are from open (0) toward the closed pose (1), averaged over joints."""
        f = self._fingers
        return float(((q[f] - self.q_open[f]) / self._span[f]).mean())

    def __call__(self, env) -> np.ndarray:
        r = self.rules
        state = env.hand_state()
        n = len(self.q_open)
        q, v = state[:n], state[n:]
        p_obj = env.object_position()
        tips = env.fingertip_distances()
        lifted = p_obj[2] - self.p_start[2] > r.lifted and float(tips.min()) < r.in_hand
        closure = self.closure(q)
        offset = self.ik.palm_pose(q[: self.n_arm])[0] - self.grasp_point
        above, aside, reach = offset[2], float(np.linalg.norm(offset[:2])), float(np.linalg.norm(offset))
        touch = tips < r.touch
        thumb_and_fingers = bool(touch[self.thumb_tip]) and int(touch.sum()) - 1 >= r.fingers_touching
        settled = float(np.abs(v[self._fingers]).max()) < r.settled_speed
        arm_stopped = float(np.abs(v[: self.n_arm]).max()) < r.stopped_speed
        holding = (closure > r.started and settled and (thumb_and_fingers or closure > self.closed_hold)
                   and reach < r.hold_reach)
        closing = reach < r.at_grasp or above < r.blocked_height and (
            aside < r.above_xy and arm_stopped or aside < r.keep_xy and closure > r.started)
        if not holding and not lifted and closure < r.closed and (r.follow_closing or not closing):
            self._follow(env)
        fingers = self.q_open
        if holding or (lifted and (closure > r.started or r.lift_touching and thumb_and_fingers)):
            self.phase, arm, fingers = "lift", self._lift(q[: self.n_arm], p_obj, lifted), self.q_closed
        elif closing:
            self.phase, arm, fingers = "close", self.q_grasp, self.q_closed
        elif closure > r.missed or (closure > r.closed and not aside < r.keep_xy):
            self.phase, arm = "open", q[: self.n_arm]
        else:  # a funnel: the farther off horizontally, the closer the target to the approach way-point
            tolerance = r.above_xy + r.descend_cone * max(above, 0.0)
            s = min(max((aside - tolerance) / r.funnel, 0.0), 1.0)
            self.phase = "approach" if s >= 1.0 else "descend"
            if r.approach_step > 0:
                arm = self._toward(q[: self.n_arm], self.grasp_point + s * (self.above_point - self.grasp_point))
            else:
                arm = self.q_grasp + s * (self.q_above - self.q_grasp)
            if s < 1.0 and above < r.preclose_height and aside < r.keep_xy:
                fingers = self.q_open + r.preclose * self._span
        out = np.array(fingers, dtype=float)
        lift_lead = r.lift_lead if self.script.lift_lead is None else self.script.lift_lead
        lead = lift_lead if self.phase == "lift" else r.max_lead
        out[: self.n_arm] = self._lead(q[: self.n_arm], arm[: self.n_arm], lead)
        return out

    def _lift(self, q_arm: np.ndarray, p_obj: np.ndarray, lifted: bool) -> np.ndarray:
        """Arm set-points toward `lift_target`: a few IK steps from q_arm, a function of the state."""
        target, R = self.lift_target(q_arm, p_obj, lifted)
        return self.ik.step(target, R, q_arm, self.rules.lift_steps)

    def _toward(self, q_arm: np.ndarray, point: np.ndarray) -> np.ndarray:
        """Arm set-points that move the grasp centre straight toward `point`, at most `approach_step`
        ahead, and turn the palm toward the plan's rotation, at most `approach_turn` ahead."""
        p, R = self.ik.palm_pose(q_arm)
        d = point - p
        p_next = p + d * min(1.0, self.rules.approach_step / max(float(np.linalg.norm(d)), 1e-12))
        turn = RotationMatrix(self.R_grasp @ R.T).ToAngleAxis()
        R_next = rotation_from_vector(min(turn.angle(), self.rules.approach_turn) * turn.axis()) @ R
        return self.ik.step(p_next, R_next, q_arm, self.rules.lift_steps)

    def lift_target(self, q_arm: np.ndarray, p_obj: np.ndarray, lifted: bool) -> tuple[np.ndarray, np.ndarray]:
        """Where the lift takes the grasp centre, and the palm's rotation: up to the lift height,
        the palm keeping its rotation, and, once the object is off the table, back over the
        nearest possible start position if the object has left the placement range (the start
        itself cannot be seen once the object is in the hand; the nearest one is never farther
        from it, so drift is undone, not only stopped)."""
        p, R = self.ik.palm_pose(q_arm)
        back = ObjectPlacement.nearest_start(p_obj[:2]) - p_obj[:2] if lifted else np.zeros(2)
        return np.array([p[0] + back[0], p[1] + back[1], self.lift_height]), R

    def _lead(self, q_arm: np.ndarray, target: np.ndarray, lead: float) -> np.ndarray:
        """A set-point from q_arm toward target, at most `lead` (normalised) ahead on any joint."""
        step = (target - q_arm) / self._arm_half
        scale = min(1.0, lead / max(float(np.abs(step).max()), 1e-12))
        return q_arm + scale * step * self._arm_half
