"""Starting and stopping recorded episodes: one request queue, fed by every input.

:class:`EpisodeControl` is a thread-safe queue of requests. The inputs only push to it:

- keyboard (:class:`KeyboardControl`): a line on stdin; Enter or ``s`` starts / stops,
  ``d`` discards the episode in progress, ``q`` saves it and quits;
- browser view: the Record / Discard buttons (:mod:`beavr_sim.viz.twin_view`);
- headset: the operator's record gesture, a left-hand pinch held for a second
  (:meth:`beavr_sim.operator.operator.Operator.take_gestures`).

The recording session (:func:`beavr_sim.teleop.session.record_episodes`) takes the requests
once per control tick, so all of them act at tick boundaries, in one thread.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import TextIO

from beavr_sim.naming import check_name

log = logging.getLogger("beavr_sim.teleop.episodes")

#: ``toggle``: start when idle, stop (save) when recording.
REQUESTS = ("toggle", "start", "stop", "discard", "quit")


class EpisodeControl:
    """Requests from any thread; :meth:`take` hands them over in order."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: list[str] = []

    def request(self, what: str, origin: str = "") -> None:
        what = check_name("episode request", what, REQUESTS)
        with self._lock:
            self._pending.append(what)
        log.info("episode request %s%s", what, f" ({origin})" if origin else "")

    def take(self) -> list[str]:
        with self._lock:
            pending, self._pending = self._pending, []
        return pending


class KeyboardControl:
    """Reads command lines from ``stream`` (stdin) in a daemon thread."""

    KEYS = {"": "toggle", "s": "toggle", "d": "discard", "q": "quit"}
    HELP = "keys: Enter = start/stop episode, d + Enter = discard it, q + Enter = save and quit"

    def __init__(self, control: EpisodeControl, stream: TextIO | None = None):
        self.control = control
        self.stream = sys.stdin if stream is None else stream
        self._thread = threading.Thread(target=self._read, name="keyboard", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for line in self.stream:
                key = line.strip().lower()
                what = self.KEYS.get(key)
                if what is None:
                    print(f"unknown key {key!r}; {self.HELP}", file=sys.stderr)
                    continue
                self.control.request(what, "keyboard")
        except (OSError, ValueError):  # stdin closed
            return
