"""argparse value types that check a user's input before any work starts.

Each returns the parsed value or raises argparse.ArgumentTypeError, which argparse reports
as one line naming the flag ("dexdrake sim: error: argument --seed: ...", exit status 2).
"""

from __future__ import annotations

import argparse
import math
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


def int_at_least(low: int, high: int | None = None) -> Callable[[str], int]:
    """An integer >= low (seeds: 0, counts and steps: 1) and, if given, <= high."""
    def parse(text: str) -> int:
        value = _number(int, text)
        if value < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, got {value}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high}, got {value}")
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
MAX_STEPS = 10_000  # control steps of one episode or run: 200 s of simulated time at 50 Hz
MAX_EPISODES = 10_000  # episodes per object of one command
steps = int_at_least(1, MAX_STEPS)
episodes = int_at_least(1, MAX_EPISODES)


def horizon_help(note: str = "") -> str:
    """The help of every `--horizon` flag (type `steps`), with a command's `note` on its value."""
    return f"control steps per episode ({note + '; ' if note else ''}at most {MAX_STEPS})"


def episodes_per_object_help(note: str = "") -> str:
    """The help of every `--episodes-per-object` flag (type `episodes`), with a command's `note`."""
    return f"episodes per object ({note + '; ' if note else ''}at most {MAX_EPISODES})"


positive = float_in(0.0)
non_negative = float_in(0.0, low_open=False)


def output_file(*suffixes: str) -> Callable[[str], Path]:
    """A file to write, ending in one of `suffixes` (if given). Marked `output = "file"`:
    `dexdrake.cli.main` checks every output with `dexdrake.outputs` before the command runs."""
    def parse(text: str) -> Path:
        path = Path(text)
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{text!r} must end in {' or '.join(suffixes)}")
        return path

    parse.__name__ = "path"
    parse.output = "file"
    return parse


def output_folder(text: str) -> Path:
    """A folder to write into (checked as `output_file`'s are)."""
    return Path(text)


output_folder.output = "folder"


def pose_noise(text: str) -> tuple[float, float]:
    """"POS,ROT": the object pose's noise sigmas, position (m) and rotation (rad), each finite and >= 0."""
    parts = text.split(",")
    try:
        values = tuple(float(x) for x in parts)
    except ValueError:
        values = ()
    if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected POS,ROT (two finite numbers >= 0: m, rad), got {text!r}")
    return values


def label(text: str) -> str:
    """A label used as a file or folder name: letters, digits, '_', '-', '.'; no slashes."""
    if not _LABEL.match(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a plain name (use letters, digits, '_', '-' and '.', no slashes)")
    return text
