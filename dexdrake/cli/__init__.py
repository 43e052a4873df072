"""The `dexdrake` command line: one sub-command per workflow.

The command line is the top layer: only this package (in `dexdrake/`) imports `systems/`
and `hardware/`. Each command's module is named for it and adds it through an
`add_parser(subparsers)` function (`flags` holds what several share); `systems/`,
`hardware/` and pydrake are imported inside the commands, so `--help` builds no Drake.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import time
import warnings
from pathlib import Path

from dexdrake.errors import DexdrakeError, DexdrakeWarning
from dexdrake.outputs import check_not_an_input, check_writable

# Modules that contribute sub-commands with `add_parser(subparsers)`.
COMMAND_MODULES = [
    "dexdrake.cli.sim", "dexdrake.cli.models",
    "dexdrake.cli.objects",
    "dexdrake.cli.demos", "dexdrake.cli.retarget",
    "dexdrake.cli.features", "dexdrake.cli.encoder",
    "dexdrake.cli.hil", "dexdrake.cli.parity", "dexdrake.cli.real",
    "dexdrake.cli.train", "dexdrake.cli.eval", "dexdrake.cli.demo",
    "dexdrake.cli.expert", "dexdrake.cli.ablations",
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


def _leaf(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[list[str], argparse.ArgumentParser]:
    """The words of the sub-command `args` runs and its parser."""
    words = []
    while True:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or getattr(args, subs[0].dest, None) is None:
            return words, parser
        words.append(getattr(args, subs[0].dest))
        parser = subs[0].choices[words[-1]]


def check_outputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Every output of the command (flags whose type is marked `output` by dexdrake.argtypes)
    can be written and is none of its input paths; else a one-line argparse error, exit 2."""
    outputs, inputs = [], []
    for action in parser._actions:
        value = getattr(args, action.dest, None)
        flag = action.option_strings[0] if action.option_strings else action.dest
        kind = getattr(action.type, "output", None)
        if kind and value is not None:
            try:
                check_writable(Path(value), folder=kind == "folder")
            except DexdrakeError as err:
                parser.error(f"argument {flag}: {err}")
            outputs.append((flag, Path(value)))
        elif action.dest != "help":
            for item in value if isinstance(value, list) else [value]:
                if isinstance(item, Path):
                    inputs.append((flag, item))
    try:
        check_not_an_input(outputs, inputs)
    except DexdrakeError as err:
        parser.error(str(err))


class _Warnings:
    """Shows a DexdrakeWarning at once as one line; holds library warnings (torch, numpy)
    back, to show them after a command that succeeds (none after an error line)."""

    def __init__(self):
        self.held: list[str] = []

    def show(self, message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, DexdrakeWarning):
            print(f"dexdrake: warning: {message}", file=sys.stderr)
        else:
            self.held.append(warnings.formatwarning(message, category, filename, lineno, line))

    def flush(self) -> None:
        sys.stderr.write("".join(self.held))
        self.held.clear()


# The resource tracker process (multiprocessing) frees the semaphores of workers ended on
# Ctrl-C, which is its job, and warns of each; it takes its warning filters from these options.
RESOURCE_TRACKER_QUIET = "ignore:resource_tracker:UserWarning"


def main(argv: list[str] | None = None) -> int:
    if RESOURCE_TRACKER_QUIET not in sys.warnoptions:
        sys.warnoptions.append(RESOURCE_TRACKER_QUIET)
    shown = _Warnings()
    with warnings.catch_warnings():
        warnings.showwarning = shown.show
        try:
            code = _run(argv, shown)
        except KeyboardInterrupt:  # before the command started
            print("dexdrake: interrupted", file=sys.stderr)
            code = 130
    if code == 130 and argv is None:
        # The process's own command, interrupted and said so: a Ctrl-C landing while the
        # interpreter shuts down (reaping worker processes) must not turn the exit status 130
        # into death by SIGINT.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


def _run(argv: list[str] | None, shown: _Warnings) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    words, leaf = _leaf(parser, args)
    name = " ".join(words)
    start = time.perf_counter()
    try:
        check_outputs(leaf, args)
        code = int(args.func(args) or 0)
    except DexdrakeError as err:
        shown.held.clear()
        _close_progress_bars()
        message = "; ".join(line.strip() for line in str(err).splitlines() if line.strip())
        print(f"dexdrake {name}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        shown.held.clear()
        _close_progress_bars()
        print(f"dexdrake {name}: interrupted after {time.perf_counter() - start:.1f} s", file=sys.stderr)
        return 130
    shown.flush()
    return code


def _close_progress_bars() -> None:
    """Close the progress bars a stopped command left open (each ends its line), so the
    command's last line stands on a line of its own."""
    from tqdm import tqdm

    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()
