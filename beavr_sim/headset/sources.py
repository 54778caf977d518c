"""Detector sources: where hand frames come from (the headset, a recorded trace, memory).

A source is polled with the current time and returns the frames that arrived since the last
poll, oldest first: once per control tick on the virtual clock, or as each frame arrives
(:meth:`HandSource.wait`) in the event-driven real-time runners. Sources never raise on bad input: frames the
headset sends malformed are rejected inside the source and counted by its validator.

- :class:`FrameListSource`: frames in memory, released when the clock reaches their time.
- :class:`TraceSource`: a recorded VR trace (MCAP), on the virtual clock (deterministic:
  frame ``t_source`` is trace time) or in real time (trace time offset to ``time.monotonic``).
- :class:`QuestSource`: the BEAVR Quest app over ZeroMQ (``beavr_sim.headset.quest_io``).
- :class:`WebXRSource`: any WebXR headset's browser, on a page this process serves
  (``beavr_sim.headset.webxr_server``; a server thread, frames handed over thread-safely).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

from beavr_sim.traces.format import TraceReader
from beavr_sim.wire.hand import HandFrame

#: Tolerance when comparing frame times with the clock (float trace times).
_EPS = 1e-9


class HandSource(ABC):
    """Something that yields hand frames when polled."""

    #: True when ``t_receive`` of the frames is ``time.monotonic()`` (wall-clock latency).
    real_time: bool = False
    #: True when the source already ran its frames through the loop's validator.
    validates: bool = False

    @abstractmethod
    def poll(self, now: float) -> list[HandFrame]:
        """Frames received up to time ``now`` (the loop's clock), oldest first."""

    def wait(self, timeout_s: float, clock=time.monotonic) -> list[HandFrame]:
        """Real time: the frames as soon as any have arrived, waiting at most ``timeout_s``
        (the event-driven runners process each frame when it arrives, not at a tick). This
        default polls every millisecond; sources that can block on arrival do."""
        deadline = clock() + max(0.0, timeout_s)
        while True:
            frames = self.poll(clock())
            remaining = deadline - clock()
            if frames or remaining <= 0:
                return frames
            time.sleep(min(remaining, 0.001))

    @property
    def sockets(self) -> tuple:
        """Sockets whose readiness means a frame may have arrived (an event loop polls them
        with its own); none for sources that release frames by time (:meth:`next_due`)."""
        return ()

    def next_due(self) -> float | None:
        """Real time: when (``time.monotonic()``) the next frame is due, for sources that
        release frames by time; None when unknown or never."""
        return None

    @property
    def finished(self) -> bool:
        """True when no frame will ever come again (end of a trace)."""
        return False

    def refused_connections(self) -> dict[str, int]:
        """Connections refused before any frame was read (a WebSocket without the session
        token, a Quest app host not on ``--headset-allow``): reason -> count. The summary
        adds them to ``rejected_by_reason``; ``frames_rejected`` counts frames only."""
        return {}

    def close(self) -> None:
        """Release sockets or files."""


class FrameListSource(HandSource):
    """Frames held in memory; each is delivered when ``now`` reaches its ``t_source``.

    On the virtual clock (``real_time=False``) ``now`` is the trace time itself; in real
    time the first poll fixes the offset between trace time and ``time.monotonic()``.
    Delivered frames get ``t_receive`` set to the delivery time on the loop's clock.
    """

    def __init__(self, frames: Sequence[HandFrame], real_time: bool = False):
        self.frames = sorted(frames, key=lambda f: f.t_source)
        self.real_time = real_time
        self._next = 0
        self._offset: float | None = None

    def poll(self, now: float) -> list[HandFrame]:
        if self.real_time:
            if self._offset is None and self.frames:
                self._offset = now - self.frames[0].t_source
            trace_now = now - (self._offset or 0.0)
        else:
            trace_now = now
        out = []
        while (
            self._next < len(self.frames) and self.frames[self._next].t_source <= trace_now + _EPS
        ):
            frame = self.frames[self._next]
            t = frame.t_source + (self._offset or 0.0) if self.real_time else frame.t_source
            t_receive = now if self.real_time else t
            out.append(frame.with_times(t, t_receive))
            self._next += 1
        return out

    def wait(self, timeout_s: float, clock=time.monotonic) -> list[HandFrame]:
        """Real time: sleep until the next frame is due (at most ``timeout_s``), then poll.
        (On the virtual clock, or before the first poll fixed the offset: a poll.)"""
        now = clock()
        if not self.real_time or self._offset is None:
            return self.poll(now)
        if self.finished:
            time.sleep(max(0.0, timeout_s))
            return []
        due = self.frames[self._next].t_source + self._offset
        time.sleep(max(0.0, min(due, now + max(0.0, timeout_s)) - now))
        return self.poll(clock())

    def next_due(self) -> float | None:
        if not self.real_time or self.finished:
            return None
        if self._offset is None:
            return time.monotonic()  # the first poll starts the clock
        return self.frames[self._next].t_source + self._offset

    def rewind(self) -> None:
        """Deliver the frames again from the first (a trace replayed from its start)."""
        self._next = 0
        self._offset = None

    def push(self, frame: HandFrame) -> None:
        """Append a frame (not older than the last one): a source fed while it runs."""
        if self.frames and frame.t_source < self.frames[-1].t_source:
            raise ValueError(
                f"frames must be pushed in time order: {frame.t_source} after "
                f"{self.frames[-1].t_source}"
            )
        self.frames.append(frame)

    @property
    def finished(self) -> bool:
        return self._next >= len(self.frames)

    @property
    def duration_s(self) -> float:
        return self.frames[-1].t_source - self.frames[0].t_source if self.frames else 0.0


class TraceSource(FrameListSource):
    """A recorded VR trace (MCAP file written by ``python -m beavr_sim.traces``)."""

    def __init__(self, path: str | Path, real_time: bool = False):

        self.reader = TraceReader(path)
        self.metadata = asdict(self.reader.metadata)
        frames = [payload for _, kind, payload in self.reader.events() if kind == "hand"]
        super().__init__(frames, real_time=real_time)


class QuestSource(HandSource):
    """The BEAVR Quest app: PULL sockets bound on the headset host (``quest_io``)."""

    real_time = True

    def __init__(self, context, config, validator=None, latest_only: bool = True):
        self.validates = validator is not None
        from beavr_sim.headset.address_gate import AddressGate  # local: heavy (zmq)
        from beavr_sim.headset.quest_io import QuestReceiver  # local: heavy (zmq)

        allowed = config.headset_allow
        self.gate = None if allowed is None else AddressGate(context, allowed)
        try:
            self.receiver = QuestReceiver(
                context, config, validator=validator, latest_only=latest_only, gate=self.gate
            )
        except BaseException:
            if self.gate is not None:
                self.gate.close()
            raise

    def poll(self, now: float) -> list[HandFrame]:
        return self.receiver.poll(0.0)

    def wait(self, timeout_s: float, clock=time.monotonic) -> list[HandFrame]:
        """Blocks on the app's sockets: a frame is parsed the moment it arrives."""
        return self.receiver.poll(timeout_s)

    @property
    def sockets(self) -> tuple:
        return self.receiver.sockets

    def close(self) -> None:
        self.receiver.close()
        if self.gate is not None:
            self.gate.close()

    def refused_connections(self) -> dict[str, int]:
        return {} if self.gate is None else dict(self.gate.refused)


class WebXRSource(HandSource):
    """A WebXR headset's browser: the page and WebSocket of ``webxr_server`` (own thread)."""

    real_time = True

    def __init__(self, config=None, validator=None):
        from beavr_sim.headset.webxr_server import WebXRServer  # local: heavy (websockets, asyncio)

        self.validates = validator is not None
        self.server = WebXRServer(config, validator=validator)

    @property
    def url(self) -> str:
        return self.server.url

    def poll(self, now: float) -> list[HandFrame]:
        return self.server.take(0.0)

    def wait(self, timeout_s: float, clock=time.monotonic) -> list[HandFrame]:
        """Blocks until the server thread hands over a message's frames."""
        return self.server.take(timeout_s)

    def refused_connections(self) -> dict[str, int]:
        return self.server.refused_connections()

    def twin_feed(self, model, data, operator=None, info: dict | None = None):
        """A tick listener that shows the twin on the page (``webxr_scene.TwinFeed``)."""
        from beavr_sim.headset.webxr_scene import TwinFeed  # local: heavy (mujoco)

        rate = self.server.config.twin_rate_hz
        return TwinFeed(self.server, model, data, rate, operator=operator, info=info)

    def close(self) -> None:
        self.server.close()


def monotonic() -> float:
    return time.monotonic()
