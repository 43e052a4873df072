"""Flags several commands share, flags made from a settings dataclass, and the command
line a run records.

A settings dataclass marks each field a command line sets with
`field(metadata={"help": ...})`; optional metadata: "flag" (its name without the leading
dashes, default the field's name with '-' for '_'), "type" (an argparse value type, e.g.
from dexdrake.argtypes; default str), "choices" and "metavar". A bool field (off by default)
is a switch, a tuple field takes one or more values. The field's default is the flag's default.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
from pathlib import Path
from typing import Any

from dexdrake import argtypes

MISMATCH_HELP = "run a policy trained under another plant step or control period (with a warning)"


def _settings(cls: type, names: tuple[str, ...] = ()) -> list[dataclasses.Field]:
    """The fields of `cls` a command line sets (`names` of them, in that order, if given)."""
    fields = {f.name: f for f in dataclasses.fields(cls) if "help" in f.metadata}
    return [fields[n] for n in names] if names else list(fields.values())


def setting_names(cls: type) -> list[str]:
    """The names of the fields of `cls` a command line sets, in field order."""
    return [f.name for f in _settings(cls)]


def _dest(f: dataclasses.Field) -> str:
    return f.metadata.get("flag", f.name).replace("-", "_")


def add_settings(parser: argparse.ArgumentParser, cls: type, *names: str) -> None:
    """One flag per field of `cls` that a command line sets (`names` of them, in that order,
    if given): its name, type, default and help from the field."""
    for f in _settings(cls, names):
        meta, default = f.metadata, f.default
        flag = "--" + _dest(f).replace("_", "-")
        if isinstance(default, bool):
            parser.add_argument(flag, action="store_true", help=meta["help"])
            continue
        shown = f" (default: {default})" if default not in (None, "", ()) and "default" not in meta["help"] else ""
        kwargs: dict[str, Any] = {"type": meta.get("type", str), "help": meta["help"] + shown}
        kwargs.update({k: meta[k] for k in ("choices", "metavar") if k in meta})
        if isinstance(default, tuple):
            kwargs.update(nargs="+", default=list(default))
        else:  # an empty string is no value: argparse would parse it with the flag's type
            kwargs["default"] = None if default == "" else default
        parser.add_argument(flag, **kwargs)


def _field_value(f: dataclasses.Field, value: Any) -> Any:
    """A flag's value as its field holds it: paths as strings, lists as tuples, no value as the default."""
    if value is None:
        return f.default
    if isinstance(value, list):
        return tuple(str(v) if isinstance(v, Path) else v for v in value)
    return str(value) if isinstance(value, Path) else value


def settings_from_args(cls: type, args: argparse.Namespace, **given: Any) -> Any:
    """A `cls` from the flags `add_settings` made (every field a command line sets) and `given`."""
    return cls(**{f.name: _field_value(f, getattr(args, _dest(f))) for f in _settings(cls)}, **given)


def option_names(parser: argparse.ArgumentParser) -> list[str]:
    """The names (without dashes) of every option of `parser` but --help, in its order."""
    return [a.option_strings[-1][2:] for a in parser._actions if a.option_strings and a.dest != "help"]


def command_line(words: list[str], args: argparse.Namespace, options: list[str]) -> str:
    """The command with every option's effective value (for result tables and manifests)."""
    parts = ["dexdrake", *words]
    for opt in options:
        value = getattr(args, opt.replace("-", "_"))
        if isinstance(value, bool):
            parts += [f"--{opt}"] if value else []
        elif isinstance(value, list):
            parts += [f"--{opt}", *map(str, value)] if value else []
        elif value is not None:
            parts += [f"--{opt}", str(value)]
    return shlex.join(parts)


def add_horizon(parser: argparse.ArgumentParser, default: int | None, note: str = "") -> None:
    """--horizon: the control steps of each episode the command runs (help: argtypes.horizon_help)."""
    shown = f" (default: {default})" if default is not None else ""
    parser.add_argument("--horizon", type=argtypes.steps, default=default, metavar="N",
                        help=argtypes.horizon_help(note) + shown)


def add_episodes_per_object(parser: argparse.ArgumentParser, default: int, note: str = "") -> None:
    """--episodes-per-object: the episodes the command runs on each object (help:
    argtypes.episodes_per_object_help)."""
    parser.add_argument("--episodes-per-object", type=argtypes.episodes, default=default, metavar="N",
                        help=argtypes.episodes_per_object_help(note) + f" (default: {default})")


def add_backend_options(parser: argparse.ArgumentParser) -> None:
    from dexdrake.learn.samplers import BACKENDS

    parser.add_argument("--backend", choices=BACKENDS, default="process",
                        help="where rollout workers run: in this process, local processes or Ray actors")
    parser.add_argument("--address", help="Ray cluster to join (e.g. auto or HEAD_IP:6379; needs --backend ray; "
                        "default: a local Ray instance); see configs/ray_cluster.md")


def add_envs_per_worker(parser: argparse.ArgumentParser, what: str, note: str = "") -> None:
    parser.add_argument("--envs-per-worker", type=argtypes.count, default=None,
                        help=f"{what} whose episodes a worker steps in lockstep, one policy call for all of them "
                             f"(default: dexdrake.learn.samplers.ENVS_PER_WORKER{note})")


def envs_per_worker(args: argparse.Namespace) -> int:
    """--envs-per-worker, or its default."""
    from dexdrake.learn.samplers import ENVS_PER_WORKER

    return args.envs_per_worker or ENVS_PER_WORKER
