"""Helpful errors for names chosen from a fixed set (tasks, embodiments, cameras, ...)."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class UnknownNameError(ValueError, KeyError):
    """A name that is not one of the valid choices.

    Subclasses both ``ValueError`` (bad argument) and ``KeyError`` (failed lookup), so callers
    may catch either. The message lists every valid choice and the closest match.
    """

    def __init__(self, kind: str, name: object, valid: Iterable[str], context: str = ""):
        self.kind = kind
        self.name = name
        self.valid = sorted(valid)
        close = difflib.get_close_matches(str(name), self.valid, n=1, cutoff=0.5)
        hint = f" Did you mean {close[0]!r}?" if close else ""
        where = f" {context}" if context else ""
        message = (
            f"Unknown {kind} {name!r}{where}.{hint} Valid {kind}s{where}: {', '.join(self.valid)}."
        )
        super().__init__(message)

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return str(self.args[0])


def check_name(kind: str, name: object, valid: Iterable[str], context: str = "") -> str:
    """Return ``name`` if it is valid, else raise :class:`UnknownNameError` (``context``, e.g.
    ``"for task Pour"``, follows the name in the message)."""
    valid = list(valid)
    if not isinstance(name, str) or name not in valid:
        raise UnknownNameError(kind, name, valid, context)
    return name
