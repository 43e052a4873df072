"""argparse value types that check a user's input before any work starts.

Each returns the parsed value or raises argparse.ArgumentTypeError, which argparse reports
as one line naming the flag ("dexdrake sim: error: argument --seed: ...", exit status 2).
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable
from pathlib import Path

_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")


def _number(kind: type, text: str) -> int | float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def int_at_least(low: int) -> Callable[[str], int]:
    """An integer >= low (seeds: 0, counts and steps: 1)."""
    def parse(text: str) -> int:
        value = _number(int, text)
        if value < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, got {value}")
        return value

    parse.__name__ = "integer"
    return parse


def float_in(low: float, high: float = math.inf, low_open: bool = True) -> Callable[[str], float]:
    """A finite number in (low, high] (or [low, high] with low_open=False)."""
    def parse(text: str) -> float:
        value = _number(float, text)
        if value < low or (low_open and value == low) or value > high:
            bracket = "(" if low_open else "["
            raise argparse.ArgumentTypeError(f"must be in {bracket}{low:g}, {high:g}], got {value:g}")
        return value

    parse.__name__ = "number"
    return parse


seed = int_at_least(0)
count = int_at_least(1)
non_negative_count = int_at_least(0)


def seed_list(text: str) -> list[int]:
    """Comma-separated seeds (integers >= 0), at least one: '100,101,102'."""
    return [seed(item) for item in text.split(",")]
positive = float_in(0.0)
non_negative = float_in(0.0, low_open=False)


def output_file(*suffixes: str) -> Callable[[str], Path]:
    """A file path that can be written: not a folder, its folder exists or can be made,
    and (if given) one of `suffixes`."""
    def parse(text: str) -> Path:
        path = Path(text)
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{text!r} must end in {' or '.join(suffixes)}")
        return writable(path, folder=False)

    parse.__name__ = "path"
    return parse


def output_folder(text: str) -> Path:
    """A folder that exists or can be made, and can be written into."""
    return writable(Path(text), folder=True)


def writable(path: Path, folder: bool) -> Path:
    """`path` if it can be written (as a folder or a file); else ArgumentTypeError."""
    if path.exists() and path.is_dir() != folder:
        raise argparse.ArgumentTypeError(f"{str(path)!r} is {'a file' if folder else 'a folder'}")
    parent = path if folder and path.exists() else path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"cannot create {str(path)!r}: {str(parent)!r} is a file")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write to {str(parent)!r} (permission denied)")
    return path


def label(text: str) -> str:
    """A label used as a file or folder name: letters, digits, '_', '-', '.'; no slashes."""
    if not _LABEL.match(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a plain name (use letters, digits, '_', '-' and '.', no slashes)")
    return text
