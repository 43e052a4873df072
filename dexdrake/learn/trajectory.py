"""One rollout of a policy in an env, as flat arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    seed: int
    observations: np.ndarray  # float32 (T, D): observation before each action
    actions: np.ndarray  # float32 (T, A): actions as sampled (before the env clips them)
    rewards: np.ndarray  # float64 (T,)
    log_probs: np.ndarray  # float64 (T,): Gaussian log-likelihood of each action at sampling time
    success: bool  # info["success"] was True at some step
    terminated: bool  # the env returned done before its horizon

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    @property
    def total_reward(self) -> float:
        return float(self.rewards.sum())
