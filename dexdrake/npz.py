"""Reading .npz archives: a missing, damaged or truncated file is one DexdrakeError naming it."""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from dexdrake.errors import DexdrakeError

# what numpy and zipfile raise for a damaged archive, at opening or when a member is read
_DAMAGED = (zipfile.BadZipFile, EOFError, zlib.error, OSError, ValueError)


class DamagedFileError(DexdrakeError):
    """A file that cannot be read as what it should be (truncated, corrupt)."""


@contextmanager
def open_npz(path: str | Path) -> Iterator[np.lib.npyio.NpzFile]:
    """`np.load(path)` (no pickles) as a context; its errors, and those of reading its members
    inside the block, become a DamagedFileError naming `path`."""
    path = Path(path)
    if path.is_dir():
        raise DexdrakeError(f"{path} is a folder; give a .npz file")
    if not path.is_file():
        raise DexdrakeError(f"{path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            yield data
    except _DAMAGED as exc:
        raise DamagedFileError(f"{path} is not a readable .npz file, damaged or truncated "
                               f"({type(exc).__name__}: {exc}); remove it or make it again") from exc
