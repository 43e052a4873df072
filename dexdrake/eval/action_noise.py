"""Temporally correlated action noise for DART-style demonstration recording.

An Ornstein-Uhlenbeck process sampled at the control period (an AR(1) sequence)
x_{t+1} = rho * x_t + sqrt(1 - rho^2) * std * eps_t, eps_t ~ N(0, I), started from its
stationary distribution, so every step has standard deviation `std` (in normalised action
units, where the action range [-1, 1] has width 2) and neighbouring steps are correlated
with `rho`: the hand drifts off the expert's path the way a slightly wrong policy does.
"""

from __future__ import annotations

import numpy as np

from dexdrake.errors import DexdrakeError

DEFAULT_RHO = 0.9  # step-to-step correlation: a correlation time of about 10 control steps


class OUActionNoise:
    """Seeded stationary OU noise of dimension `dim`; call `sample()` once per control step."""

    def __init__(self, dim: int, std: float, rho: float = DEFAULT_RHO, seed: int | list[int] = 0):
        if dim < 1:
            raise DexdrakeError(f"noise dimension must be >= 1, got {dim}")
        if std < 0 or not np.isfinite(std):
            raise DexdrakeError(f"noise std must be a finite number >= 0, got {std}")
        if not 0.0 <= rho < 1.0:
            raise DexdrakeError(f"noise correlation rho must be in [0, 1), got {rho}")
        self.std, self.rho = float(std), float(rho)
        self._rng = np.random.default_rng(seed)
        self._x = self.std * self._rng.standard_normal(dim)

    def sample(self) -> np.ndarray:
        """The noise for this step (then the process advances one step)."""
        x = self._x.copy()
        self._x = self.rho * self._x + np.sqrt(1.0 - self.rho**2) * self.std * self._rng.standard_normal(x.shape[0])
        return x
