"""The one rule for a bad command, in every mode and layer (GraspEnv, the station's controller
slot, PolicySystem, the Allegro and Z1 drivers' `hardware.safety.JointLimits`): a command
with a non-finite entry (or of the wrong size) is not used, the last command is held and
`non_finite` counts it; a command with entries outside the bounds is clipped to them and
`clipped` counts it (an excess within 1e-9 of a joint's range, the rounding of a normalised
action's mapping to set-points, is clipped without being counted)."""

from __future__ import annotations

import numpy as np


class CommandGuard:
    """Applies the rule above for bounds [lower, upper]; the counts belong to the guard's owner
    (an env, a system or a driver) and restart with `reset_counts`."""

    def __init__(self, lower: np.ndarray, upper: np.ndarray):
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        tolerance = 1e-9 * np.maximum(self.upper - self.lower, 1.0)
        self._below, self._above = self.lower - tolerance, self.upper + tolerance  # beyond these: counted
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
        if q.shape != self.lower.shape or not np.isfinite(q).all():
            self.non_finite += 1
            return np.array(last, dtype=float)
        if (q < self._below).any() or (q > self._above).any():
            self.clipped += 1
        return np.minimum(np.maximum(q, self.lower), self.upper)
