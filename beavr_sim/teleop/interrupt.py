"""Ctrl-C and SIGTERM as an orderly stop of a teleop session.

:class:`StopSignal` is a flag the session's loops ask once per tick (``loop.interrupted``):
:func:`stop_on_signals` sets it on the first SIGINT or SIGTERM, so the run ends at a tick
boundary and the session closes the rig, the recorder and the views in order and still
prints its summary. A second signal raises :class:`KeyboardInterrupt` at once (for a session
stuck before its loop runs, e.g. a device that does not answer). The exit code of an
interrupted session is ``128 + signal number`` (130 SIGINT, 143 SIGTERM), as a shell reports it.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: The signals that stop a session in order.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignal:
    """Set once from a signal handler; called, says whether the session should stop."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.signum = 0

    def __call__(self) -> bool:
        return self._event.is_set()

    def set(self, signum: int) -> None:
        self.signum = int(signum)
        self._event.set()

    @property
    def name(self) -> str:
        """``SIGINT`` / ``SIGTERM`` ("" while not set)."""
        return signal.Signals(self.signum).name if self.signum else ""

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def never() -> bool:
    """The stop flag of a loop nobody interrupts."""
    return False


@contextmanager
def stop_on_signals(stop: StopSignal) -> Iterator[StopSignal]:
    """SIGINT and SIGTERM set ``stop`` (the second raises KeyboardInterrupt) while inside;
    the previous handlers come back on exit. Outside the main thread (where Python cannot
    install handlers) nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, frame) -> None:
        if stop():
            raise KeyboardInterrupt
        stop.set(signum)
        print(
            f"\n{stop.name}: stopping in order (again to abort at once)",
            file=sys.stderr,
            flush=True,
        )

    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield stop
    finally:
        for s, old in previous.items():
            signal.signal(s, old)
