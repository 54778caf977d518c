"""The session's stderr: a progress line rewritten in place (``\\r``) and log lines that never
glue onto it.

:data:`CONSOLE` knows whether the last thing written to stderr was a progress line without its
newline; :class:`LineSafeHandler` (the CLI's log handler) ends that line before a log record,
so a warning starts on a line of its own and the next refresh of the progress line follows it.
"""

from __future__ import annotations

import logging
import sys
import threading


class Console:
    """The progress line's state on stderr (shared by every thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open = False

    def progress(self, text: str) -> None:
        """Rewrite the progress line (no newline: the next refresh overwrites it)."""
        with self._lock:
            print(f"\r{text}", end="", file=sys.stderr, flush=True)
            self._open = True

    def end_line(self) -> None:
        """End an open progress line (a newline), so what follows starts a line of its own."""
        with self._lock:
            if self._open:
                print(file=sys.stderr, flush=True)
                self._open = False


CONSOLE = Console()


class LineSafeHandler(logging.StreamHandler):
    """A stderr log handler that ends an open progress line before each record."""

    def emit(self, record: logging.LogRecord) -> None:
        CONSOLE.end_line()
        super().emit(record)
