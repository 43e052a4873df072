"""Demonstration datasets: (observation, action) pairs stored as .npz.

File layout (written by the replay stage with `save_demo_dataset`):
    observations   float (N, D)
    actions        float (N, A), normalised to [-1, 1] like env actions
    episode_starts bool  (N,), optional: True at the first sample of each demo episode
    metadata       0-d str, optional: a JSON object (hand, feature set, source, ...)
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dexdrake.errors import DexdrakeError
from dexdrake.npz import open_npz
from dexdrake.objects.meshfile import write_atomic


@dataclass(frozen=True)
class DemoDataset:
    observations: np.ndarray  # float32 (N, D); float16 where memory matters (DAgger's aggregate)
    actions: np.ndarray  # float32 (N, A)
    episode_starts: np.ndarray | None = None  # bool (N,)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.observations.shape[0])

    def episode_ids(self) -> np.ndarray:
        """Episode index of every sample (all 0 when no episode_starts were stored)."""
        if self.episode_starts is None:
            return np.zeros(len(self), dtype=np.int64)
        return np.cumsum(self.episode_starts) - 1


def _validate(obs: np.ndarray, act: np.ndarray, starts: np.ndarray | None, where: str) -> None:
    if obs.ndim != 2 or act.ndim != 2:
        raise DexdrakeError(
            f"{where}: observations and actions must be 2-D (N x D, N x A); "
            f"got shapes {obs.shape} and {act.shape}"
        )
    if obs.shape[0] != act.shape[0]:
        raise DexdrakeError(f"{where}: {obs.shape[0]} observations but {act.shape[0]} actions")
    if obs.shape[0] == 0 or obs.shape[1] == 0 or act.shape[1] == 0:
        raise DexdrakeError(f"{where}: empty dataset (shapes {obs.shape}, {act.shape})")
    for name, arr in (("observations", obs), ("actions", act)):
        if not np.issubdtype(arr.dtype, np.number):
            raise DexdrakeError(f"{where}: {name} has non-numeric dtype {arr.dtype}")
        bad = ~np.isfinite(arr)
        if bad.any():
            rows = np.unique(np.nonzero(bad)[0])
            raise DexdrakeError(
                f"{where}: {name} has {int(bad.sum())} non-finite values in {len(rows)} rows "
                f"(first rows: {rows[:5].tolist()})"
            )
    if starts is not None:
        if starts.shape != (obs.shape[0],):
            raise DexdrakeError(f"{where}: episode_starts has shape {starts.shape}, expected ({obs.shape[0]},)")
        if not starts[0]:
            raise DexdrakeError(f"{where}: episode_starts[0] must be True (the first sample starts an episode)")


def load_demo_dataset(
    path: str | Path, obs_dim: int | None = None, action_dim: int | None = None
) -> DemoDataset:
    """Load and validate a demo .npz; optionally check it matches a policy's sizes."""
    path = Path(path)
    with open_npz(path) as data:
        arrays = {k: data[k] for k in data.files}
    missing = [k for k in ("observations", "actions") if k not in arrays]
    if missing:
        raise DexdrakeError(f"demo dataset {path} lacks {missing}; it has {sorted(arrays)}")
    obs, act = arrays["observations"], arrays["actions"]
    starts = arrays["episode_starts"].astype(bool) if "episode_starts" in arrays else None
    _validate(obs, act, starts, str(path))
    if obs_dim is not None and obs.shape[1] != obs_dim:
        raise DexdrakeError(f"demo dataset {path}: observations have {obs.shape[1]} columns, expected {obs_dim}")
    if action_dim is not None and act.shape[1] != action_dim:
        raise DexdrakeError(f"demo dataset {path}: actions have {act.shape[1]} columns, expected {action_dim}")
    metadata: dict[str, Any] = {}
    if "metadata" in arrays:
        try:
            metadata = json.loads(str(arrays["metadata"]))
        except json.JSONDecodeError as exc:
            raise DexdrakeError(f"demo dataset {path}: metadata is not valid JSON: {exc}") from exc
    return DemoDataset(obs.astype(np.float32), act.astype(np.float32), starts, metadata)


def save_demo_dataset(
    path: str | Path,
    observations: np.ndarray,
    actions: np.ndarray,
    episode_starts: np.ndarray | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> Path:
    """Validate and write a demo dataset in the layout `load_demo_dataset` reads (atomically)."""
    path = Path(path)
    obs = np.asarray(observations, dtype=np.float32)
    act = np.asarray(actions, dtype=np.float32)
    starts = None if episode_starts is None else np.asarray(episode_starts, dtype=bool)
    _validate(obs, act, starts, str(path))
    arrays: dict[str, np.ndarray] = {"observations": obs, "actions": act}
    if starts is not None:
        arrays["episode_starts"] = starts
    arrays["metadata"] = np.array(json.dumps(dict(metadata or {})))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_atomic(path, buf.getvalue())  # a reader never sees half a dataset
    return path
