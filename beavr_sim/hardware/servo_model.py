"""What every emulated servo bus shares: the servo motion model and the pty it is served on.

The motion model (:func:`step_towards`) is deliberately simple: with torque on, a servo moves
towards its goal at a bounded speed and, optionally, a bounded acceleration (braking so that it
stops at the goal), advanced by wall time. There is no load, gravity, friction or backlash.
Positions and speeds are in the servo's own counts; the emulators own the units.

:class:`EmulatedBus` is the serving half: a pseudo-terminal whose slave path
(:attr:`EmulatedBus.port`) the vendor SDK opens as a serial port, a daemon thread that hands the
bytes it receives to the protocol (a subclass) and writes back its replies, the wall clock that
advances the servos before every batch of bytes, and the test hooks common to every bus
(:meth:`~EmulatedBus.vanish`, :meth:`~EmulatedBus.drop_replies`). Used by
:mod:`beavr_sim.hardware.dynamixel_emulator` and :mod:`beavr_sim.hardware.feetech_emulator`.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import pty
import select
import threading
import time
import tty
from abc import ABC, abstractmethod
from typing import Self

#: How long a partial packet may stall before the bus gives up on it and resyncs.
PARTIAL_PACKET_TIMEOUT_S = 0.05


def step_towards(
    position: float,
    goal: float,
    dt: float,
    max_speed: float,
    velocity: float = 0.0,
    max_accel: float = math.inf,
) -> tuple[float, float]:
    """One step of the servo model: ``(position, velocity)`` after ``dt`` seconds of moving from
    ``position`` towards ``goal`` at most ``max_speed`` (units/s), changing speed by at most
    ``max_accel`` (units/s^2) and braking to stop at the goal. A step that reaches the goal ends
    exactly on it. With ``max_accel`` infinite, the speed is ``max_speed`` until the goal.
    """
    if dt <= 0:
        return position, velocity
    err = goal - position
    if err == 0:
        return position, 0.0
    # The fastest speed from which the servo can still stop at the goal.
    stop_speed = math.sqrt(2.0 * max_accel * abs(err)) if math.isfinite(max_accel) else math.inf
    wanted = math.copysign(min(max_speed, stop_speed), err)
    if math.isfinite(max_accel):
        dv = max_accel * dt
        wanted = velocity + max(-dv, min(dv, wanted - velocity))
    step = wanted * dt
    if (step >= err > 0) or (step <= err < 0):
        return goal, err / dt
    return position + step, step / dt


class EmulatedBus(ABC):
    """A serial bus behind a pseudo-terminal, served by a daemon thread.

    Subclasses implement the protocol: :meth:`_receive` (bytes in, reply bytes out), the servo
    step :meth:`_step` and the partial-packet hooks. Everything they do runs with :attr:`lock`
    held. The bus runs at whatever baud rate the host sets (a pty has no line rate).
    """

    thread_name = "servo-bus"

    def __init__(self) -> None:
        #: Exceptions raised while handling packets (the thread survives them).
        self.faults: list[BaseException] = []
        self.lock = threading.RLock()
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        #: The slave device path to open as the serial port.
        self.port: str = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._vanish = threading.Event()
        self._vanished = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_advance = time.monotonic()
        self._drop_replies = 0

    # -- protocol hooks (called with the lock held) --

    @abstractmethod
    def _receive(self, data: bytes) -> bytes:
        """Parse ``data`` (possibly part of a packet) and answer what it completes."""

    @abstractmethod
    def _step(self, dt: float) -> None:
        """Advance every servo by ``dt`` seconds."""

    @abstractmethod
    def _has_partial(self) -> bool:
        """Whether the parser holds the start of a packet that has not finished arriving."""

    @abstractmethod
    def _drop_partial(self) -> bytes:
        """Give up on a stalled partial packet (resync); the replies to what that completes."""

    # -- lifecycle --

    def start(self) -> Self:
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name=self.thread_name, daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread and close the pty (idempotent)."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- test hooks --

    def vanish(self, timeout: float = 1.0) -> None:
        """Stop answering and close the pty master: the serial port unplugged mid-run."""
        self._vanish.set()
        self._wake()
        if self._thread is None or not self._thread.is_alive():
            self._close_pty()
            self._vanished.set()
        self._vanished.wait(timeout)

    def drop_replies(self, n: int = 1) -> None:
        """Lose the replies to the next ``n`` batches of instructions (a glitch on the wire)."""
        with self.lock:
            self._drop_replies = n

    def advance(self, now: float | None = None) -> None:
        """Advance every servo's model to ``now`` (monotonic seconds)."""
        with self.lock:
            now = time.monotonic() if now is None else now
            dt = now - self._last_advance
            if dt <= 0:
                return
            self._last_advance = now
            self._step(dt)

    # -- the serving thread --

    def _wake(self) -> None:
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")

    def _serve(self) -> None:
        idle_since: float | None = None
        while not self._stop.is_set():
            if self._vanish.is_set():
                self._close_pty()
                self._vanished.set()
                self._stop.wait()
                return
            try:
                ready, _, _ = select.select([self._master, self._wake_r], [], [], 0.01)
            except (OSError, ValueError):
                if self._stop.is_set() or self._vanish.is_set():
                    continue
                time.sleep(0.01)
                continue
            if self._wake_r in ready:
                with contextlib.suppress(OSError):
                    os.read(self._wake_r, 64)
            data = b""
            if self._master in ready:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError:
                    time.sleep(0.01)
            self.advance()
            if data:
                idle_since = None
                with self.lock:
                    self._reply(self._guarded(self._receive, data))
            elif self._has_partial():
                now = time.monotonic()
                idle_since = idle_since or now
                if now - idle_since > PARTIAL_PACKET_TIMEOUT_S:
                    with self.lock:
                        self._reply(self._guarded(self._drop_partial))
                    idle_since = None

    def _guarded(self, handler, *args) -> bytes:
        try:
            return handler(*args)
        except Exception as exc:  # never let odd bytes kill the bus
            self.faults.append(exc)
            return b""

    def _reply(self, replies: bytes) -> None:
        if replies and self._drop_replies > 0:
            self._drop_replies -= 1
        elif replies and not self._vanish.is_set():
            self._send(replies)

    def _send(self, data: bytes) -> None:
        deadline = time.monotonic() + 0.1
        view = memoryview(data)
        while view and time.monotonic() < deadline:
            try:
                n = os.write(self._master, view)
                view = view[n:]
            except BlockingIOError:
                select.select([], [self._master], [], 0.01)
            except OSError:
                return

    def _close_pty(self) -> None:
        for attr in ("_master", "_slave"):
            fd = getattr(self, attr)
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
                setattr(self, attr, -1)
