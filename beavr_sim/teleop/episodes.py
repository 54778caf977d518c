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
from collections.abc import Callable
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
    """Reads command lines from ``stream`` (stdin) in a daemon thread.

    Episode keys go to ``control`` (None: no recording); ``actions`` adds keys of its own,
    each a (help text, callable) pair, e.g. the hardware mirror's ``e`` (emergency stop) and
    ``r`` (release).
    """

    KEYS = {"": "toggle", "s": "toggle", "d": "discard", "q": "quit"}
    HELP = "keys: Enter = start/stop episode, d + Enter = discard it, q + Enter = save and quit"

    def __init__(
        self,
        control: EpisodeControl | None,
        stream: TextIO | None = None,
        actions: dict[str, tuple[str, Callable[[], None]]] | None = None,
    ):
        self.control = control
        self.actions = dict(actions or {})
        self.stream = sys.stdin if stream is None else stream
        self._thread = threading.Thread(target=self._read, name="keyboard", daemon=True)
        self._thread.start()

    @property
    def help(self) -> str:
        parts = [self.HELP] if self.control is not None else []
        parts += [f"{k} + Enter = {text}" for k, (text, _) in self.actions.items()]
        return "; ".join(parts) if parts else ""

    def _read(self) -> None:
        try:
            for line in self.stream:
                key = line.strip().lower()
                if key in self.actions:
                    self.actions[key][1]()
                    continue
                what = self.KEYS.get(key) if self.control is not None else None
                if what is None:
                    print(f"unknown key {key!r}; {self.help}", file=sys.stderr)
                    continue
                self.control.request(what, "keyboard")
        except (OSError, ValueError):  # stdin closed
            return
