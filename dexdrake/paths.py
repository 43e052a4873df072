"""Where dexdrake finds its shipped models, keeps the user's data and its on-disk cache."""

from __future__ import annotations

import os
from importlib.resources import files
from pathlib import Path


def models_dir() -> Path:
    """The installed `dexdrake.models` folder (robot models, objects, weights)."""
    return Path(str(files("dexdrake.models")))


def cache_dir() -> Path:
    """The per-user cache (`$DEXDRAKE_CACHE`, else ~/.cache/dexdrake); created on demand."""
    root = Path(os.environ.get("DEXDRAKE_CACHE", Path.home() / ".cache" / "dexdrake"))
    root.mkdir(parents=True, exist_ok=True)
    return root


def data_dir() -> Path:
    """The user's dexdrake data (imported objects): `$DEXDRAKE_DATA`, else
    `$XDG_DATA_HOME/dexdrake`, else ~/.local/share/dexdrake. Unlike the cache, clearing it
    loses the user's work. Created on demand."""
    env = os.environ.get("DEXDRAKE_DATA")
    xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    root = Path(env) if env else Path(xdg) / "dexdrake"
    root.mkdir(parents=True, exist_ok=True)
    return root


def resolve_model_path(path: str | Path) -> Path:
    """`path` as given when it exists; a relative `models/...` path otherwise resolves inside
    the installed `dexdrake.models` (so configs can name shipped weights from any folder)."""
    p = Path(path)
    if p.exists() or p.is_absolute() or not p.parts or p.parts[0] != "models":
        return p
    return models_dir().joinpath(*p.parts[1:])
