"""Readiness waits for tests: poll a condition until it holds, with a generous hang guard.

A test waits on the thing it needs (a counter reached, a message seen, a flag cleared), never
on a fixed sleep; the guard only turns a hang into a failure that names what never happened.
"""

from __future__ import annotations

import time
from collections.abc import Callable

#: Seconds a readiness wait may take before the test fails (a hang, not a slow machine).
HANG_GUARD_S = 30.0


def wait_until(
    condition: Callable[[], object],
    what: str,
    timeout_s: float = HANG_GUARD_S,
    poll_s: float = 0.005,
) -> None:
    """Return once ``condition()`` is true; AssertionError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:g} s")
        time.sleep(poll_s)
