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

    def __reduce__(self):  # rebuilt from its fields in the process that receives it
        return type(self), (self.kind, self.name, self.valid), self.__dict__


class NonFiniteError(DexdrakeError):
    """NaN or infinite numbers where finite ones are needed (a diverged training, a damaged
    checkpoint): nothing is written from them."""


class StationFault(DexdrakeError):
    """The station stopped itself: a driver fault (a modelled one in simulation), a
    perception failure, no object pose."""


class DexdrakeWarning(UserWarning):
    """Something a user should know that did not stop the work (the CLI prints one line)."""
