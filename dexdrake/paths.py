"""Where dexdrake finds its shipped models and keeps its on-disk cache."""

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
