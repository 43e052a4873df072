"""The one episode loop and its result, in every mode: training rollouts, DAgger labelling,
evaluation, the scripted grasp in simulation, the demo, and the station (hil, real).

The loop runs an env of the learning protocol (learn/env_protocol.py): `reset(seed)`, then
`step(act(observation))` until the env says done, its info carries a "fault", or `horizon`
steps. `info` holds "success" (so far) and "lift" (m, NaN when the object's pose is not
known); recorders hook in through `act`, `on_reset` and `on_step`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class EpisodeResult:
    """What one episode did: success, the highest lift, steps run, rewards; `fault` when a
    station stopped itself, `stats` for what the env measured (loop rates, bad commands)."""

    object: str
    seed: int
    success: bool
    max_lift: float  # m (NaN: the object's pose was never known)
    steps: int
    total_reward: float
    wall_s: float = 0.0
    fault: str | None = None
    stats: dict[str, Any] = field(default_factory=dict)


def run_episode(env, act: Callable[[np.ndarray], np.ndarray], seed: int, horizon: int | None = None,
                object_name: str | None = None, on_reset: Callable[[], None] | None = None,
                on_step: Callable[[float, dict[str, Any]], None] | None = None) -> EpisodeResult:
    """One episode of `env` from `reset(seed)` (on `object_name` when given), `act` choosing
    each action from the observation, for at most `horizon` steps (default env.horizon).
    `on_reset()` runs after the reset, `on_step(reward, info)` after every step."""
    obs = env.reset(int(seed)) if object_name is None else env.reset(int(seed), object_name=object_name)
    if on_reset is not None:
        on_reset()
    steps, total, success, max_lift, lift_known, fault = 0, 0.0, False, 0.0, False, None
    start = time.perf_counter()
    for steps in range(1, (env.horizon if horizon is None else horizon) + 1):
        obs, reward, done, info = env.step(act(obs))
        if on_step is not None:
            on_step(reward, info)
        total += float(reward)
        success = success or bool(info["success"])
        lift = float(info.get("lift", math.nan))
        if math.isfinite(lift):
            max_lift, lift_known = max(max_lift, lift), True
        fault = info.get("fault")
        if done or fault is not None:
            break
    return EpisodeResult(getattr(env, "object_name", ""), int(seed), success, max_lift if lift_known else math.nan,
                         steps, total, time.perf_counter() - start, fault)
