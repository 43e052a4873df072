"""Checks on what a command will write, made before any work starts, and the lock that keeps
two writers out of one named thing (a run folder, a user object).

- `check_writable(path, folder)`: the path is not a folder where a file is meant (or the
  reverse), its nearest existing ancestor is a folder, and a file can really be created
  there (a probe file is made and removed: permission bits say nothing for root, and
  read-only mounts or /proc refuse only an actual write). Missing parent folders are fine:
  every writer makes them.
- `check_not_an_input(outputs, inputs)`: no output is one of the command's input files.
- `WriterLock(folder)`: a lock file holding the owner's pid; a second writer is refused in
  one line, a lock left by a dead process is taken over.
- `check_run_kind(folder, kind)`: a run folder is never given to a run of another kind
  (each kind is known by the log it writes first, `RUN_LOGS`).
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

from dexdrake.errors import DexdrakeError

LOCK_FILE = ".dexdrake.lock"
RUN_LOGS = {"BC": "bc_log.csv", "DAgger": "dagger_log.csv", "DAPG": "dapg_log.csv"}  # kind -> its log


class OutputError(DexdrakeError):
    """An output path that cannot be written, or that would replace an input."""


def _nearest_existing(path: Path) -> Path:
    parent = path
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    return parent


def check_writable(path: Path, folder: bool) -> Path:
    """`path` if a folder (`folder`) or a file can be written there; else OutputError."""
    path = Path(path)
    if path.exists() and path.is_dir() != folder:
        raise OutputError(f"{str(path)!r} is {'a file' if folder else 'a folder'}; "
                          f"give {'a folder' if folder else 'a file name'}")
    parent = _nearest_existing(path if folder else path.parent)
    if not parent.is_dir():
        raise OutputError(f"cannot create {str(path)!r}: {str(parent)!r} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".dexdrake-probe-")
    except OSError as err:
        reason = os.strerror(err.errno) if err.errno else str(err)
        raise OutputError(f"cannot write to {str(parent)!r} ({reason.lower()}); choose another place") from None
    os.close(fd)
    os.unlink(probe)
    return path


def _same(a: Path, b: Path) -> bool:
    if a.exists() and b.exists():
        return os.path.samefile(a, b)
    return a.resolve() == b.resolve()


def check_not_an_input(outputs: Iterable[tuple[str, Path]], inputs: Iterable[tuple[str, Path]]) -> None:
    """OutputError if an output (flag, path) is one of the inputs (flag, path)."""
    inputs = list(inputs)
    for out_flag, out in outputs:
        for in_flag, given in inputs:
            if _same(Path(out), Path(given)):
                raise OutputError(f"{out_flag} {out} is the input {in_flag}: it would be overwritten; "
                                  f"write to another file")


def check_run_kind(folder: Path, kind: str) -> None:
    """OutputError if `folder` holds the log of a run of a kind (`RUN_LOGS`) other than `kind`."""
    for other, log in RUN_LOGS.items():
        if other != kind and (Path(folder) / log).exists():
            raise OutputError(f"--out {folder} holds a {other} run ({log}); give this {kind} run another folder")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class WriterLock:
    """Exclusive writer of `folder` while held (a context manager): `folder/.dexdrake.lock`
    holds the owner's pid, created with O_EXCL; held by a live process -> OutputError naming
    it; left by a dead one -> taken over. `what` names the thing in the message. Folders the
    lock made are removed again if nothing was written into them."""

    def __init__(self, folder: Path, what: str | None = None):
        self.folder, self.what = Path(folder), what or f"folder {folder}"
        self.path = self.folder / LOCK_FILE

    def _owner(self) -> int | None:
        try:
            return int(self.path.read_text().strip() or 0) or None
        except (OSError, ValueError):
            return None

    def __enter__(self) -> "WriterLock":
        self.existing = _nearest_existing(self.folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                owner = self._owner()
                if owner is not None and owner != os.getpid() and _pid_alive(owner):
                    raise OutputError(f"{self.what} is being written by another dexdrake process (pid {owner}); "
                                      f"wait for it to end or use another name/folder") from None
                self.path.unlink(missing_ok=True)  # stale: its owner is gone
                continue
            except OSError as err:
                if err.errno in (errno.EACCES, errno.EROFS, errno.EPERM):
                    raise OutputError(f"cannot write to {self.folder} ({os.strerror(err.errno).lower()})") from None
                raise
            with os.fdopen(fd, "w") as f:
                f.write(f"{os.getpid()}\n")
            return self
        raise OutputError(f"cannot take the lock {self.path}; remove it if no dexdrake process is running")

    def __exit__(self, *exc) -> None:
        if self._owner() == os.getpid():
            self.path.unlink(missing_ok=True)
        made = self.folder
        while made != self.existing and made.is_dir() and not any(made.iterdir()):
            made.rmdir()
            made = made.parent
