"""What both emulated serial buses share (Dynamixel: :mod:`beavr_sim.hardware.leap.emulator`,
Feetech: :mod:`beavr_sim.hardware.feetech.emulator`): the pty they are served on, the packet
framing loop, the log of what they received and the faults they can be put under.

:class:`EmulatedBus` is a pseudo-terminal whose slave path (:attr:`EmulatedBus.port`) the vendor
SDK opens as a serial port, and a daemon thread that hands the bytes it receives to the
protocol (a subclass) and writes back its replies, after advancing the servos (the one servo
model, :mod:`beavr_sim.hardware.servo_model`) by the wall clock. :meth:`EmulatedBus.start`
returns once that thread is serving, so a driver's first ping is never early.

:class:`FrameParser` cuts instruction packets out of the byte stream: garbage before a header is
dropped; a packet whose length is implausible or whose checksum fails is dropped one byte at a
time, so parsing resyncs on the next header.

Faults (:mod:`beavr_sim.hardware.faults`): :meth:`EmulatedBus.inject` takes a
:class:`~beavr_sim.hardware.faults.FaultSpec`; a request that arrives while the bus is frozen or
disconnected is lost unanswered (and does nothing), each reply may be dropped or garbled (its
last byte, the checksum, flipped), and every reply may be sent late. Older test hooks:
:meth:`~EmulatedBus.vanish` (the pty closes: the adapter unplugged),
:meth:`~EmulatedBus.drop_replies`.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pty
import select
import threading
import time
import tty
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Self

from beavr_sim.hardware.faults import Fate, FaultSpec, FaultState, Verdict

#: How long a partial packet may stall before the bus gives up on it and resyncs.
PARTIAL_PACKET_TIMEOUT_S = 0.05


@dataclass(frozen=True)
class Packet:
    """One received instruction packet (unstuffed)."""

    id: int
    instruction: int
    params: bytes


def per_id(setting, servo_id: int, default):
    """A per-servo setting given for all servos (one value) or per id (a dict; ids it lacks get
    ``default``)."""
    return setting.get(servo_id, default) if isinstance(setting, dict) else setting


def sync_write_blocks(rest: bytes, size: int) -> list[tuple[int, bytes]]:
    """The ``(id, data)`` blocks of a sync write's parameters after its address and size
    (none when they do not divide into ``size + 1`` byte blocks)."""
    if size == 0 or len(rest) % (size + 1):
        return []
    return [(rest[k], rest[k + 1 : k + 1 + size]) for k in range(0, len(rest), size + 1)]


class FrameParser(ABC):
    """Incremental parser of instruction packets. Subclasses give the :attr:`header`, how many
    bytes tell the length (:attr:`head_size`) and the hooks; ``dropped`` counts skipped bytes."""

    header: bytes
    head_size: int

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.dropped = 0

    @abstractmethod
    def _total(self, head: bytes) -> int | None:
        """The whole packet's length from its first :attr:`head_size` bytes; None when
        implausible (the first byte is skipped)."""

    @abstractmethod
    def _valid(self, raw: bytes) -> bool:
        """Whether the checksum of the whole packet ``raw`` holds (else :meth:`_rejected`)."""

    @abstractmethod
    def _packet(self, raw: bytes) -> Packet:
        """The packet in ``raw`` (valid)."""

    def _rejected(self, raw: bytes) -> None:
        """Called for a packet whose checksum failed."""

    def feed(self, data: bytes) -> list[Packet]:
        self.buffer += data
        packets: list[Packet] = []
        while True:
            start = self.buffer.find(self.header)
            if start < 0:
                keep = self._header_prefix()
                self.dropped += len(self.buffer) - keep
                del self.buffer[: len(self.buffer) - keep]
                return packets
            if start:
                self.dropped += start
                del self.buffer[:start]
            if len(self.buffer) < self.head_size:
                return packets
            total = self._total(bytes(self.buffer[: self.head_size]))
            if total is None:
                self._skip()
                continue
            if len(self.buffer) < total:
                return packets
            raw = bytes(self.buffer[:total])
            if not self._valid(raw):
                self._rejected(raw)
                self._skip()
                continue
            del self.buffer[:total]
            packets.append(self._packet(raw))

    def drop_partial(self) -> None:
        """Give up on a packet that stopped arriving mid-way (resync on the next header)."""
        if self.buffer:
            self._skip()

    def _header_prefix(self) -> int:
        """How many trailing bytes of the buffer may begin a header."""
        for n in range(min(len(self.header) - 1, len(self.buffer)), 0, -1):
            if self.buffer.endswith(self.header[:n]):
                return n
        return 0

    def _skip(self) -> None:
        del self.buffer[:1]
        self.dropped += 1


class EmulatedBus(ABC):
    """A serial bus behind a pseudo-terminal, served by a daemon thread.

    Subclasses give the :attr:`parser` (a :class:`FrameParser`), answer one packet
    (:meth:`_handle`) and advance their servos (:meth:`_step`). Everything they do runs with
    :attr:`lock` held. The bus runs at whatever baud rate the host sets (a pty has no line
    rate).
    """

    thread_name = "servo-bus"
    parser: FrameParser

    def __init__(self, name: str | None = None) -> None:
        #: Exceptions raised while handling packets (the thread survives them).
        self.faults: list[BaseException] = []
        #: The injected faults (:meth:`inject`) and their counters.
        self.fault_state = FaultState(name or self.thread_name)
        #: Every instruction packet received: ``(time.monotonic(), id, instruction)``.
        self.packet_log: list[tuple[float, int, int]] = []
        self.lock = threading.RLock()
        self._master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        #: The slave device path to open as the serial port.
        self.port: str = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._serving = threading.Event()
        self._vanish = threading.Event()
        self._vanished = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_advance = time.monotonic()
        self._drop_replies = 0
        #: Bytes read from the port and done with (handled, or lost to a fault).
        self.bytes_handled = 0

    # -- protocol hooks (called with the lock held) --

    @abstractmethod
    def _handle(self, packet: Packet) -> bytes:
        """The reply bytes to one instruction packet (b"" for none)."""

    @abstractmethod
    def _step(self, dt: float) -> None:
        """Advance every servo by ``dt`` seconds."""

    def _on_rejected(self) -> bytes:
        """Replies owed for packets the parser rejected (checksum), if the protocol answers
        them."""
        return b""

    # -- lifecycle --

    def start(self, timeout: float = 10.0) -> Self:
        """Start serving; returns once the thread is in its loop (RuntimeError if it is not
        within ``timeout`` s)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name=self.thread_name, daemon=True)
            self._thread.start()
        if not self._serving.wait(timeout):
            raise RuntimeError(f"{self.thread_name} on {self.port} did not start serving")
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

    # -- faults and test hooks --

    def inject(self, spec: FaultSpec) -> None:
        """Put the bus under ``spec`` (its device name is not checked here)."""
        self.fault_state.add(spec)

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

    def caught_up(self, bytes_sent: int) -> bool:
        """Whether the first ``bytes_sent`` bytes written to the port have been handled (or
        the port is gone): a write that gets no reply (a sync write) has reached the servos.
        A test hook for waiting on readiness; the writer's count is
        :attr:`~beavr_sim.hardware.serial_bus.SerialBus.bytes_sent`. A count, not "nothing is
        pending": a pty delivers what was written a moment after the write returns."""
        return self.bytes_handled >= bytes_sent or self._vanished.is_set()

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
        self._serving.set()
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
                if self.fault_state.admit() is not Verdict.SERVE:
                    self.bytes_handled += len(data)
                    continue  # frozen or gone: the bytes are lost
                with self.lock:
                    self._answer(self.parser.feed(data))
                self.bytes_handled += len(data)
            if not data and self.parser.buffer:
                now = time.monotonic()
                idle_since = idle_since or now
                if now - idle_since > PARTIAL_PACKET_TIMEOUT_S:
                    with self.lock:
                        self.parser.drop_partial()
                        self._answer(self.parser.feed(b""))
                    idle_since = None

    def _answer(self, packets: list[Packet]) -> None:
        """Handle ``packets`` and send each reply (faults permitting)."""
        replies = [self._guarded(self._on_rejected)]
        for packet in packets:
            self.packet_log.append((time.monotonic(), packet.id, packet.instruction))
            replies.append(self._guarded(self._handle, packet))
        replies = [r for r in replies if r]
        if replies and self._drop_replies > 0:
            self._drop_replies -= 1
            return
        for reply in replies:
            fate = self.fault_state.fate()
            if fate is Fate.DROP or self._vanish.is_set():
                continue
            if fate is Fate.CORRUPT:
                reply = reply[:-1] + bytes([reply[-1] ^ 0xFF])
            delay = self.fault_state.delay_s
            if delay > 0:
                time.sleep(delay)
            self._send(reply)

    def _guarded(self, handler, *args) -> bytes:
        try:
            return handler(*args)
        except Exception as exc:  # never let odd bytes kill the bus
            self.faults.append(exc)
            return b""

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
