"""The one episode loop and its result, in every mode: training rollouts, DAgger labelling,
evaluation, the scripted grasp in simulation and its recorded data, the replay of
retargeted demonstrations, the demo, and the station (hil, real).

The loop runs an env of the learning protocol (learn/env_protocol.py): `reset(seed)`, then
`step(act(observation))` until the env says done, its info carries a "fault", or `horizon`
steps. `info` holds "success" (so far) and "lift" (m, NaN when the object's pose is not
known); recorders hook in through `act`, `on_reset` and `on_step`. `run_lockstep` runs K
envs this way side by side, one `act` call choosing the actions of all of them per step
(`run_episode` is its K = 1 case).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
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
    return run_lockstep([env], lambda observations, live: [act(observations[0])], [seed], horizon,
                        None if object_name is None else [object_name],
                        None if on_reset is None else lambda k: on_reset(),
                        None if on_step is None else lambda k, reward, info: on_step(reward, info))[0]


def run_lockstep(envs: Sequence[Any], act: Callable[[list[np.ndarray], list[int]], Sequence[np.ndarray]],
                 seeds: Sequence[int], horizon: int | None = None, object_names: Sequence[str] | None = None,
                 on_reset: Callable[[int], None] | None = None,
                 on_step: Callable[[int, float, dict[str, Any]], None] | None = None) -> list[EpisodeResult]:
    """Episodes of K envs in lockstep, env k from `reset(seeds[k])` (on object_names[k] when
    given): each step, `act(observations, live)` returns the actions of the envs still running
    (their indices `live`, ascending) in one call, e.g. one policy forward for all of them;
    an env stops when it says done, its info carries a "fault", or after `horizon` steps
    (default its own horizon). `on_reset(k)` runs after env k's reset, `on_step(k, reward,
    info)` after each of its steps. Env k's episode is the one `run_episode` gives alone."""
    tallies = []
    for k, (env, seed) in enumerate(zip(envs, seeds, strict=True)):
        name = None if object_names is None else object_names[k]
        obs = env.reset(int(seed)) if name is None else env.reset(int(seed), object_name=name)
        if on_reset is not None:
            on_reset(k)
        tallies.append(_Tally(env, int(seed), obs, env.horizon if horizon is None else horizon))
    live = [k for k, t in enumerate(tallies) if t.horizon > 0]
    while live:
        actions = act([tallies[k].obs for k in live], live)
        for k, action in zip(live, actions, strict=True):
            reward, info = tallies[k].step(action)
            if on_step is not None:
                on_step(k, reward, info)
        live = [k for k in live if not tallies[k].ended]
    return [t.result() for t in tallies]


class _Tally:
    """One env's running episode in `run_lockstep`: its observation and what it has scored."""

    def __init__(self, env: Any, seed: int, obs: np.ndarray, horizon: int):
        self.env, self.seed, self.obs, self.horizon = env, seed, obs, horizon
        self.steps, self.total, self.success, self.max_lift, self.lift_known = 0, 0.0, False, 0.0, False
        self.fault: str | None = None
        self.ended = False
        self.start = time.perf_counter()
        self.wall_s = 0.0

    def step(self, action: np.ndarray) -> tuple[float, dict[str, Any]]:
        self.obs, reward, done, info = self.env.step(action)
        self.steps += 1
        self.total += float(reward)
        self.success = self.success or bool(info["success"])
        lift = float(info.get("lift", math.nan))
        if math.isfinite(lift):
            self.max_lift, self.lift_known = max(self.max_lift, lift), True
        self.fault = info.get("fault")
        self.ended = done or self.fault is not None or self.steps >= self.horizon
        if self.ended:
            self.wall_s = time.perf_counter() - self.start
        return reward, info

    def result(self) -> EpisodeResult:
        return EpisodeResult(getattr(self.env, "object_name", ""), self.seed, self.success,
                             self.max_lift if self.lift_known else math.nan, self.steps, self.total, self.wall_s,
                             self.fault)
