"""The grasp-and-lift task of DexRepNet: reward terms and the success criterion.

Every stage (scripted grasps, demo replay, RL, evaluation, hardware) scores episodes with
this module, so the task is defined once.

Reward (specs/dexrepnet.md): r = r_d + r_g + r_t with
  r_d = 0.1 * (1 / (10 * d_f2o + 0.25) - 1), d_f2o = sum of fingertip-to-surface distances;
  r_g = 1 if the object is lifted more than 0.02 m;
  r_t = 20 if ||p_obj - p_tar||^2 < 0.05, else 10 if < 0.1, else 0,
with p_tar 0.15 m above the object's start. Taken literally, r_t pays 20 to an object that
never moves (0.15^2 = 0.0225 < 0.05), so here r_t is paid only while the object is lifted
(the r_g condition); this is the one deliberate departure from the paper's formula.
Its squared thresholds are radii of 0.224 and 0.316 m, wider than the 0.10 m success radius,
so r_t pays in full while a policy carries a lifted object away from the target. The
"aligned" reward (`TaskSpec.reward`) uses Adroit relocate's bonus radii instead, 0.05 and
0.10 m, so r_t pays only inside the success radius; "paper" (the default) is the formula above.

Success: the object stays within 0.10 m of the target for at least 50 consecutive control
steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dexdrake.errors import DexdrakeError

# r_t pays 20 while ||p_obj - p_tar||^2 is below the first threshold, 10 below the second (m^2)
TARGET_THRESHOLDS = {"paper": (0.05, 0.1), "aligned": (0.05**2, 0.10**2)}


@dataclass(frozen=True)
class TaskSpec:
    target_height: float = 0.15  # p_tar = p_obj(start) + (0, 0, target_height)
    lift_threshold: float = 0.02  # r_g: lifted above this (m)
    success_radius: float = 0.10  # success: within this of p_tar (m)
    success_steps: int = 50  # ... for this many consecutive control steps
    reward: str = "paper"  # r_t's thresholds, a key of TARGET_THRESHOLDS

    def __post_init__(self) -> None:
        if self.reward not in TARGET_THRESHOLDS:
            raise DexdrakeError(f"unknown reward {self.reward!r}; choose one of {sorted(TARGET_THRESHOLDS)}")


@dataclass(frozen=True)
class RewardTerms:
    r_d: float
    r_g: float
    r_t: float

    @property
    def total(self) -> float:
        return self.r_d + self.r_g + self.r_t


def reward_terms(
    fingertip_distances: np.ndarray, p_obj: np.ndarray, p_start: np.ndarray, spec: TaskSpec = TaskSpec()
) -> RewardTerms:
    """The paper's reward terms for one control step.

    fingertip_distances: closest distance of each fingertip to the object surface (m, >= 0).
    p_obj, p_start: the object's current and starting positions in the world (m).
    """
    d_f2o = float(np.sum(np.maximum(fingertip_distances, 0.0)))
    r_d = 0.1 * (1.0 / (10.0 * d_f2o + 0.25) - 1.0)
    lifted = float(p_obj[2] - p_start[2]) > spec.lift_threshold
    r_g = 1.0 if lifted else 0.0
    d2 = float(np.sum((p_obj - target_position(p_start, spec)) ** 2))
    near, far = TARGET_THRESHOLDS[spec.reward]
    r_t = 0.0
    if lifted:
        r_t = 20.0 if d2 < near else 10.0 if d2 < far else 0.0
    return RewardTerms(r_d, r_g, r_t)


def target_position(p_start: np.ndarray, spec: TaskSpec = TaskSpec()) -> np.ndarray:
    """The lift target p_tar: `target_height` above the object's starting position."""
    return np.asarray(p_start, dtype=float) + np.array([0.0, 0.0, spec.target_height])


@dataclass
class SuccessTracker:
    """Counts consecutive control steps with the object near the target."""

    p_start: np.ndarray
    spec: TaskSpec = field(default_factory=TaskSpec)
    streak: int = 0
    best_streak: int = 0
    max_lift: float = 0.0

    def update(self, p_obj: np.ndarray) -> bool:
        """Record one control step; returns whether the episode has succeeded so far."""
        near = np.linalg.norm(p_obj - target_position(self.p_start, self.spec)) < self.spec.success_radius
        self.streak = self.streak + 1 if near else 0
        self.best_streak = max(self.best_streak, self.streak)
        self.max_lift = max(self.max_lift, float(p_obj[2] - self.p_start[2]))
        return self.success

    @property
    def success(self) -> bool:
        return self.best_streak >= self.spec.success_steps
