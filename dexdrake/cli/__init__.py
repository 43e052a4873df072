"""The `dexdrake` command line: one sub-command per workflow.

The command line is the top layer: only this package (in `dexdrake/`) imports `systems/`
and `hardware/`. Each module here contributes its sub-commands through an
`add_parser(subparsers)` function; heavy imports (pydrake, torch) happen inside the
commands, so `--help` is quick.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
import warnings

from dexdrake.errors import DexdrakeError, DexdrakeWarning

# Modules that contribute sub-commands with `add_parser(subparsers)`.
COMMAND_MODULES = [
    "dexdrake.cli.sim",
    "dexdrake.cli.objects",
    "dexdrake.cli.demos",
    "dexdrake.cli.dexrep",
    "dexdrake.cli.station",
    "dexdrake.cli.learn", "dexdrake.cli.demo",
]


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr, exit status 2 (as a
    DexdrakeError raised by a command); its sub-parsers are of the same class."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="dexdrake", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(subparsers)
    return parser


def _format_warning(message, category, filename, lineno, line=None) -> str:
    if issubclass(category, DexdrakeWarning):
        return f"dexdrake: warning: {message}\n"
    return _default_format(message, category, filename, lineno, line)


_default_format = warnings.formatwarning


def main(argv: list[str] | None = None) -> int:
    warnings.formatwarning = _format_warning
    args = build_parser().parse_args(argv)
    name = " ".join([args.command] + [str(v) for k, v in vars(args).items()
                                      if k.endswith("_command") and v])
    start = time.perf_counter()
    try:
        return int(args.func(args) or 0)
    except DexdrakeError as err:
        message = "; ".join(line.strip() for line in str(err).splitlines() if line.strip())
        print(f"dexdrake {name}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dexdrake {name}: interrupted after {time.perf_counter() - start:.1f} s", file=sys.stderr)
        return 130
