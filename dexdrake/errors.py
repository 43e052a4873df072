"""Exceptions shared across dexdrake."""

from collections.abc import Iterable


class DexdrakeError(Exception):
    """Base class for errors a user can act on (bad input, unknown names)."""


class UnknownNameError(DexdrakeError, KeyError):
    """A name (hand, object, feature set, ...) that is not in its registry."""

    def __init__(self, kind: str, name: str, valid: Iterable[str]):
        self.kind, self.name, self.valid = kind, name, sorted(valid)
        super().__init__(f"unknown {kind} {name!r}; valid: {', '.join(self.valid)}")

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class DexdrakeWarning(UserWarning):
    """Something a user should know that did not stop the work (the CLI prints one line)."""
