"""Starting and stopping recorded episodes: one request queue, fed by every input.

:class:`EpisodeControl` is a thread-safe queue of requests. The inputs only push to it:

- keyboard (:class:`KeyboardControl`): a line on stdin; Enter or ``s`` starts / stops,
  ``d`` discards the episode in progress, ``q`` saves it and quits;
- browser view: the Record / Discard buttons (:mod:`beavr_sim.viz.twin_view`);
- headset: the operator's record gesture, a left-hand pinch held for a second
  (:meth:`beavr_sim.operator.operator.Operator.take_gestures`).

The recording session (:func:`beavr_sim.teleop.session.record_episodes`, or under
``--multiprocess`` the twin process's :class:`~beavr_sim.teleop.twin_runs.TwinRuns`) takes the
requests once per control tick through :class:`EpisodeRequests`, so all of them act at tick
boundaries, in one thread. Under ``--multiprocess`` the keyboard is the supervisor's and its
requests reach the twin as session commands (:func:`session_command`, :func:`request_of`); the
headset gesture is recognised by the operator process and forwarded as an operator event.

A request is never lost silently: one that arrives while the rig syncs to the episode's start
stays queued and is taken at the episode's first tick (a stop there ends the episode at once);
one that does not apply when it is taken (a stop while idle, a start while recording) is
refused with a one-line log and counted (:attr:`EpisodeRequests.ignored`).

:func:`episode_label` is the session's one line of where its episodes are (idle / sync /
REC), shown on the progress line and, through ``teleop.view.episode_line``, in the browser
view's recording panel, in both layouts.
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


def session_command(what: str) -> str:
    """The session command (``SessionMsg.command``) carrying the episode request ``what``."""
    return "record_" + check_name("episode request", what, REQUESTS)


def request_of(command: str) -> str | None:
    """The episode request a session command carries (None: it carries none)."""
    what = command.removeprefix("record_")
    return what if command.startswith("record_") and what in REQUESTS else None


class EpisodeRequests:
    """``stop_when`` for a recording loop: takes the episode requests (and turns the record
    gestures ``gestures()`` counts since it was last asked into toggles); true when one of
    ``accepted`` came, which is kept in :attr:`last`."""

    def __init__(self, control: EpisodeControl, gestures: Callable[[], int] = lambda: 0):
        self.control = control
        self.gestures = gestures
        self.last: list[str] = []
        #: Requests refused because they did not apply when taken (each logged once).
        self.ignored = 0

    def taker(self, *accepted: str) -> Callable[[], bool]:
        for what in accepted:
            check_name("episode request", what, REQUESTS)

        def stop_when() -> bool:
            for _ in range(self.gestures()):
                self.control.request("toggle", "headset gesture")
            taken = self.control.take()
            self.last = [r for r in taken if r in accepted]
            for what in taken:
                if what not in accepted:
                    self.ignored += 1
                    log.warning(
                        "episode request %s ignored: only %s apply now", what, ", ".join(accepted)
                    )
            return bool(self.last)

        return stop_when


#: What an idle session waits for, and what ends a recorded episode.
STARTS = ("toggle", "start", "quit")
STOPS = ("toggle", "stop", "discard", "quit")

#: Where a session's episode is: waiting for a start, the rig syncing to its start, recording.
PHASES = {
    "idle": "idle (start: Enter, Record button, long left pinch)",
    "sync": "sync",
    "rec": "REC",
}


def episode_label(name: str, phase: str, last: str = "") -> str:
    """The session's episode line, e.g. ``"episode 2/5: REC · last: saved"`` (``name``:
    ``SessionRuns.name()``; ``phase``: one of :data:`PHASES`; ``last``: what became of the
    last episode, ``SessionRuns.last_outcome``)."""
    line = f"{name}: {PHASES[check_name('episode phase', phase, tuple(PHASES))]}"
    return line + (f" · last: {last}" if last else "")


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

    def join(self, timeout: float | None = None) -> bool:
        """Waits until the stream ended and every line of it was handled; true if it did."""
        self._thread.join(timeout)
        return not self._thread.is_alive()

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
