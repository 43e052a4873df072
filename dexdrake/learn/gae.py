"""Discounted returns and generalised advantage estimation (Schulman et al. 2016)."""

from __future__ import annotations

import numpy as np

from dexdrake.errors import DexdrakeError


def discounted_returns(rewards: np.ndarray, gamma: float, last_value: float = 0.0) -> np.ndarray:
    """R_t = r_t + gamma * R_{t+1}, with R_T = last_value (0 for an episode that ended)."""
    rewards = np.asarray(rewards, dtype=np.float64)
    out = np.empty_like(rewards)
    running = float(last_value)
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        out[t] = running
    return out


def gae_advantages(
    rewards: np.ndarray, values: np.ndarray, gamma: float, lam: float, last_value: float = 0.0
) -> np.ndarray:
    """A_t = sum_l (gamma*lam)^l delta_{t+l}, delta_t = r_t + gamma V(s_{t+1}) - V(s_t).

    `values[t]` is the baseline at s_t; V(s_T) = `last_value` (0 for an episode that ended).
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if rewards.shape != values.shape or rewards.ndim != 1:
        raise DexdrakeError(f"rewards {rewards.shape} and values {values.shape} must be equal 1-D shapes")
    if not (0.0 <= gamma <= 1.0 and 0.0 <= lam <= 1.0):
        raise DexdrakeError(f"gamma and lambda must be in [0, 1], got {gamma}, {lam}")
    next_values = np.append(values[1:], last_value)
    deltas = rewards + gamma * next_values - values
    return discounted_returns(deltas, gamma * lam)
