"""The object pose as a perception pipeline delivers it: noisy, in frames, late.

`PerceptionModel` holds the settings (a Scenario's `perception` entry and a recipe's);
`PerceivedPose` applies them to the true pose of one episode:

  frames    one every `period_s` of simulated time (0: one every control step), at t = k * period;
  noise     each frame's pose is the true one moved by p += e_p, e_p ~ N(0, sigma_p^2 I3) (m),
            and turned by R = exp([w]x) R_true about the object's origin, w ~ N(0, sigma_r^2 I3)
            (rad, a world-frame rotation vector), drawn once per frame;
  latency   a frame is usable `latency_s` after it was taken; at time t the newest usable frame
            is seen (before the first is usable: the first, as a station waits for its first pose).

The draws come from the episode seed alone (numpy's generator seeded with [seed, SALT]), so an
episode sees the same poses whatever else runs beside it.
"""

import math
from dataclasses import dataclass

import numpy as np

SALT = 0x5E5  # separates the perception draws from the episode's other uses of its seed


@dataclass(unsafe_hash=True)  # plain (Drake's yaml_load_typed sets fields), hashable (frozen factories hold it)
class PerceptionModel:
    """How the features see the object pose: noise sigmas and the frames' period and latency (s).
    All zero (the default): the true pose at every control step."""

    pose_noise_position_m: float = 0.0  # sigma per axis (m)
    pose_noise_rotation_rad: float = 0.0  # sigma per axis of the rotation vector (rad)
    period_s: float = 0.0  # a frame every period_s (0: every control step)
    latency_s: float = 0.0  # a frame is used this long after it was taken

    @property
    def is_exact(self) -> bool:
        """True when the features see the true pose at every control step."""
        return self == PerceptionModel()

    def problems(self, control_period: float) -> list[str]:
        """What makes these settings unusable at `control_period` (s); empty when they are fine."""
        out = [f"{name} must be finite and >= 0, got {value}" for name, value in vars(self).items()
               if not (math.isfinite(value) and value >= 0)]
        for name in ("period_s", "latency_s"):
            value = getattr(self, name)
            n = round(value / control_period)
            if not out and value > 0 and abs(n * control_period - value) > 1e-9 * value:
                out.append(f"{name} ({value}) must be 0 or a whole multiple of the control period ({control_period}): "
                           "poses are taken and used at control steps")
        return out


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """exp([w]x): the 3x3 rotation by |w| rad about w (Rodrigues' formula)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * K @ K


class PerceivedPose:
    """The pose the features see in one episode under `model` at `control_period` (s).

    `reset(seed)` starts an episode; `__call__(t, p, R)` takes the true position (3,) and
    rotation (3x3) at time t (s, a control step, called in increasing t) and returns the seen
    (position, rotation)."""

    def __init__(self, model: PerceptionModel, control_period: float):
        self.model = model
        self._period = model.period_s or control_period
        self._eps = 1e-6 * control_period
        self.reset(0)

    def reset(self, seed: int) -> None:
        self._rng = np.random.default_rng([seed, SALT])
        self._frames: list[tuple[float, np.ndarray, np.ndarray]] = []  # (time taken, p, R), oldest first

    def _take(self, t: float, p: np.ndarray, R: np.ndarray) -> None:
        m = self.model
        e_p = self._rng.normal(0.0, 1.0, 3) * m.pose_noise_position_m
        w = self._rng.normal(0.0, 1.0, 3) * m.pose_noise_rotation_rad
        self._frames.append((t, np.asarray(p, float) + e_p, rotation_from_vector(w) @ np.asarray(R, float)))

    def __call__(self, t: float, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = round(t / self._period)
        due = abs(k * self._period - t) <= self._eps
        if due and (not self._frames or t > self._frames[-1][0] + self._eps):
            self._take(t, p, R)
        usable = [f for f in self._frames if f[0] + self.model.latency_s <= t + self._eps]
        while len(usable) > 1:  # older usable frames are never seen again
            self._frames.pop(0)
            usable.pop(0)
        _, p_seen, R_seen = usable[0] if usable else self._frames[0]
        return p_seen.copy(), R_seen.copy()
