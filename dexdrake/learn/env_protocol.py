"""The environment interface the learning stack codes against.

The Drake grasp scene implements it; tests use a small toy env with the same shape.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol, runtime_checkable

import numpy as np

from dexdrake.errors import DexdrakeError


@runtime_checkable
class Env(Protocol):
    """An episodic task with a flat observation made of named encoder groups.

    `observation_blocks` maps group name -> size, in order; the observation vector is
    the concatenation of the groups in that order (e.g. {"hand": 105, "occ_surf": 1088,
    "local_geo": 1408}). Actions are normalised to [-1, 1]; the env clips them.
    `step` returns (observation, reward, done, info) with info["success"] (bool): task
    success so far in the episode.
    """

    observation_blocks: dict[str, int]
    action_dim: int
    horizon: int

    def reset(self, seed: int) -> np.ndarray: ...

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]: ...


EnvFactory = Callable[[], Env]
"""Builds an Env; must be picklable (a top-level function or functools.partial)."""

MakeEnvFactory = Callable[..., EnvFactory]
"""(hand, feature set, object names, horizon, arm_action=...) -> EnvFactory; picklable. The
layers above pass one in (systems.env_factory.GraspEnvFactory), so the core never imports them."""

PolicyEnvFactory = Callable[[Any, list[str], int], EnvFactory]
"""(policy config, object names, horizon) -> the EnvFactory for the policy's recorded hand,
feature set and arm action; picklable (systems.env_factory.env_factory_for_policy)."""


def observation_dim(blocks: Mapping[str, int]) -> int:
    """Total observation size of an ordered block mapping, after validating it."""
    if not blocks:
        raise DexdrakeError("observation_blocks is empty; need at least one encoder group")
    for name, size in blocks.items():
        if not isinstance(name, str) or not name:
            raise DexdrakeError(f"observation block names must be non-empty strings, got {name!r}")
        if int(size) != size or size <= 0:
            raise DexdrakeError(f"observation block {name!r} has size {size!r}; need a positive int")
    return int(sum(blocks.values()))
