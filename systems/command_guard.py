"""The one rule for a bad command, in every mode (GraspEnv, the station's controller slot,
PolicySystem): a command with a non-finite entry (or of the wrong size) is not used, the
last command is held and `non_finite` counts it; a command with entries outside the bounds
is clipped to them and `clipped` counts it."""

from __future__ import annotations

import numpy as np


class CommandGuard:
    """Applies the rule above for bounds [lo, hi]; the counts belong to the guard's owner
    (an env or a system) and restart with `reset_counts`."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        tolerance = 1e-9 * np.maximum(self.hi - self.lo, 1.0)  # rounding of mid + a * half
        self._below, self._above = self.lo - tolerance, self.hi + tolerance  # beyond these a command is clipped
        self.reset_counts()

    def reset_counts(self) -> None:
        self.non_finite = 0
        self.clipped = 0

    @property
    def counts(self) -> dict[str, int]:
        return {"non_finite": self.non_finite, "clipped": self.clipped}

    def __call__(self, command: np.ndarray, last: np.ndarray) -> np.ndarray:
        """The command to use: `command` within the bounds, or `last` when it is not finite."""
        q = np.asarray(command, dtype=float)
        if q.shape != self.lo.shape or not np.isfinite(q).all():
            self.non_finite += 1
            return np.array(last, dtype=float)
        if (q < self._below).any() or (q > self._above).any():
            self.clipped += 1
        return np.minimum(np.maximum(q, self.lo), self.hi)
