"""One chain of servos on one serial adapter, driven through a vendor packet SDK: the base both
bus drivers share (:class:`~beavr_sim.hardware.leap.driver.LeapHand` on ``dynamixel_sdk``,
:class:`~beavr_sim.hardware.feetech.driver.FeetechBus` on ``scservo_sdk``).

The two SDKs are one design (ROBOTIS's, forked by Feetech): a ``PortHandler`` over pyserial, a
``PacketHandler`` with ``ping`` / ``readTxRx`` / ``writeNByteTxRx`` / ``readRx``, and
``GroupSyncRead`` / ``GroupSyncWrite``. What is the same on both lives here, once:

* the port: opened at the configured baud rate, its reply timeout taken from the config
  (:class:`ReplyTimeoutPort`; the SDKs hard-code it from a 16 ms USB latency timer), port errors
  (``OSError``, pyserial's, ``termios``) turned into one-line :class:`DeviceError` s;
* ping with patience: every id is pinged until it answers; connect fails when no id has
  answered for ``timeout_s`` over a round of pings (a bus that stalls, or a busy machine, is
  waited for while some id answers; a missing id is named); reconnect fails as soon as the bus
  has been silent for one reply window per retry;
* bounded retries: a register read or write, or a sync read, whose reply did not come or came
  corrupt is asked again up to ``retries`` times (each counted in :attr:`SerialBus.retries`);
  only then :class:`DeviceError`. Port failures and the servos' own error bytes are not retried,
  except pyserial's "returned no data" on a register request (a reply woken for before it came,
  as a loaded pty can; an unplugged port keeps raising it and fails when the retries are spent);
* the ``readRx`` workaround: both SDKs' ``GroupSyncRead.rxPacket`` drop each status packet's
  error byte, so a sync read is sent through the group and its replies are read back through
  ``PacketHandler.readRx``, which keeps it; input is discarded before every sync read (the SDKs
  never discard input, so a late reply would be taken for the next one's);
* goals: clipped to the model limits, then to whole counts the servos take, in one sync write;
  ``hold`` re-sends the last goal; ``reconnect`` re-opens the port and re-reads the joints.

A subclass names its SDK (:attr:`SerialBus.sdk`), its servos' units (the conversions, the
register layout of a goal) and its set-up (:meth:`SerialBus._set_up`).
"""

from __future__ import annotations

import contextlib
import math
import select
import termios
import time
from abc import abstractmethod
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import serial

from beavr_sim.hardware.device import Device, DeviceError

#: What a failing serial port raises inside the SDKs.
PORT_ERRORS = (OSError, serial.SerialException, termios.error)


def _empty_read(exc: BaseException) -> bool:
    """pyserial's "ready to read but returned no data": an unplugged port, or (once) a read
    woken before its bytes came. pyserial gives it no type of its own, only this text."""
    return isinstance(exc, serial.SerialException) and "returned no data" in str(exc)


def check_bus_settings(owner: str, config: Any, baudrates: tuple[int, ...], note: str = "") -> None:
    """ValueError naming ``owner.<field>`` unless the settings every bus config has are sane:
    ``port``, ``baudrate`` (one of ``baudrates``), ``timeout_s``, ``reply_timeout_s``,
    ``retries``."""
    if not isinstance(config.port, str) or not config.port:
        raise ValueError(f"{owner}.port must be a device path, got {config.port!r}")
    if config.baudrate not in baudrates:
        raise ValueError(
            f"{owner}.baudrate must be one of {baudrates} (the SDK's{note}), "
            f"got {config.baudrate!r}"
        )
    if not math.isfinite(config.timeout_s) or config.timeout_s <= 0:
        raise ValueError(f"{owner}.timeout_s must be > 0 s, got {config.timeout_s!r}")
    reply = config.reply_timeout_s
    if reply is not None and (not math.isfinite(reply) or reply <= 0):
        raise ValueError(f"{owner}.reply_timeout_s must be None or > 0 s, got {reply!r}")
    if not isinstance(config.retries, int) or not 0 <= config.retries <= 10:
        raise ValueError(f"{owner}.retries must be an int in 0..10, got {config.retries!r}")


def check_limits(owner: str, lower: Any, upper: Any, n: int) -> None:
    """ValueError unless ``lower`` / ``upper`` are each None or ``n`` finite angles, lower <=
    upper."""
    for bound, values in (("lower", lower), ("upper", upper)):
        if values is not None and (len(values) != n or not all(math.isfinite(v) for v in values)):
            raise ValueError(
                f"{owner}.{bound} must be None or {n} finite angles (rad), got {values!r}"
            )
    if lower is not None and upper is not None:
        bad = [i for i, (lo, hi) in enumerate(zip(lower, upper, strict=True)) if lo > hi]
        if bad:
            raise ValueError(
                f"{owner}.lower must be <= upper for every joint; not at indices {bad}"
            )


class ReplyTimeoutPort:
    """Mixin for an SDK's ``PortHandler``: the reply timeout from the config (None keeps the
    SDK's), and a read that waits for the reply instead of spinning. Use as
    ``class _Port(ReplyTimeoutPort, PortHandler)``.

    The SDKs open the port non-blocking and poll it in a loop until the reply or the timeout:
    a core spent per waiting bus, taken from the control loop and from whatever must answer
    (on a busy host, the replies themselves come later). :meth:`readPort` instead sleeps in
    ``select`` until a byte arrives or the reply window ends; what it returns, and when the
    SDK gives up, are unchanged."""

    def __init__(self, port_name: str, reply_timeout_s: float | None) -> None:
        super().__init__(port_name)  # type: ignore[call-arg]
        self.reply_timeout_ms = None if reply_timeout_s is None else 1000.0 * reply_timeout_s
        #: Bytes the SDK has written to this port.
        self.bytes_written = 0

    def writePort(self, packet) -> int:
        written = super().writePort(packet)  # type: ignore[misc]
        self.bytes_written += int(written or 0)
        return written

    def setPacketTimeout(self, packet_length: int) -> None:
        if self.reply_timeout_ms is None:
            super().setPacketTimeout(packet_length)  # type: ignore[misc]
            return
        self.packet_start_time = self.getCurrentTime()  # type: ignore[attr-defined]
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.reply_timeout_ms  # type: ignore[attr-defined]

    def readPort(self, length: int):
        ser = self.ser  # type: ignore[attr-defined]
        if not ser.in_waiting:
            rest_ms = self.packet_timeout - self.getTimeSinceStart()  # type: ignore[attr-defined]
            if rest_ms > 0:
                select.select([ser.fileno()], [], [], rest_ms / 1000.0)
        return super().readPort(length)  # type: ignore[misc]


@dataclass(frozen=True)
class BusText:
    """The words a bus driver's messages use for its hardware."""

    unit: str  # "motor" / "servo"
    adapter: str  # what to check when the port does not open
    power: str  # what to check when nothing answers
    cable: str  # "the USB cable" / "the serial cable"
    ping_note: str = ""  # added to a ping failure's baud rate advice


class SerialBus(Device):
    """One servo chain on one serial port through a vendor SDK. See the module docstring.

    Subclasses set :attr:`sdk` (the SDK module), :attr:`port_class`, :attr:`text`,
    :attr:`torque_address`, :attr:`position_block` / :attr:`goal_block` (address, size) and
    implement the unit hooks and :meth:`_set_up`. The config needs ``port``, ``baudrate``,
    ``timeout_s``, ``reply_timeout_s``, ``retries``, ``torque_off_on_disconnect``, ``lower``,
    ``upper``.
    """

    sdk: ModuleType
    port_class: type
    text: BusText
    torque_address: int
    position_block: tuple[int, int]
    goal_block: tuple[int, int]

    def __init__(self, config: Any, ids: tuple[int, ...]) -> None:
        self.config = config
        self._ids = ids
        self.commands_sent = 0
        self.errors = 0  # failures reported as DeviceError
        self.retries = 0  # requests whose reply did not come (or came corrupt), asked again
        self.holding = False
        self.last_target: np.ndarray | None = None  # model rad, as written (after clipping)
        self._port: Any = None
        self._ph: Any = None
        self._writer: Any = None
        self._reader: Any = None
        self._bytes_on_closed_ports = 0

    @property
    def connected(self) -> bool:
        return self._port is not None

    @property
    def bytes_sent(self) -> int:
        """Bytes written to the serial port since this bus was made, over every reconnect."""
        live = self._port.bytes_written if self._port is not None else 0
        return self._bytes_on_closed_ports + live

    # -- what a subclass provides --

    @abstractmethod
    def _packet_handler(self) -> Any:
        """The SDK's PacketHandler for this bus (made on every connect)."""

    @abstractmethod
    def _set_up(self) -> None:
        """After every id answered a ping: check and configure the servos, goal = present,
        torque on. Raises DeviceError through :meth:`_fail`."""

    @abstractmethod
    def _to_model(self, counts: np.ndarray) -> np.ndarray:
        """Present or goal counts -> model joint angles (rad)."""

    @abstractmethod
    def _to_counts(self, q: np.ndarray) -> np.ndarray:
        """Model joint angles (rad), already within the model limits -> goal counts the
        servos take."""

    @abstractmethod
    def _decode_position(self, data: bytes) -> int:
        """One servo's Present Position bytes -> counts."""

    @abstractmethod
    def _goal_bytes(self, k: int, counts: int) -> bytes:
        """The goal block (:attr:`goal_block`) of the ``k``-th servo for ``counts``."""

    def _on_ping(self, servo_id: int, model_number: int) -> None:
        """Called for every id that answered a ping on connect."""

    def _after_ping(self) -> None:
        """Called once every id answered (e.g. to check their model numbers)."""

    # -- Device --

    def connect(self) -> None:
        if self._port is not None:
            return
        self._open()
        try:
            self._ping_all(self.config.timeout_s)
            self._after_ping()
            self._set_up()
        except BaseException:
            self._drop_port()
            raise
        self.holding = False
        self.last_target = None

    def reconnect(self) -> np.ndarray:
        """Re-open the port, ping every servo (patience: one reply window per id and retry),
        re-read the joints. Servos that kept their torque keep their goal (a brown-out that
        reset them gets the full set-up of :meth:`connect`). DeviceError when they do not
        answer; safe to call again."""
        self._drop_port()
        self._open()
        try:
            self._ping_all(self._reply_window_s() * (self.config.retries + 1), per_ping=True)
            self._after_ping()
            if self._torque_on_everywhere():
                last = self.last_target
            else:
                self._set_up()
                last = None
            q = self.read_positions()
        except BaseException:
            self._drop_port()
            raise
        self.last_target = last
        return q

    def read_positions(self) -> np.ndarray:
        return self._to_model(self._read_counts())

    def send_positions(self, positions: np.ndarray) -> np.ndarray:
        q = self.check_positions(positions)
        self._require_connected()
        lo, hi = self.config.lower, self.config.upper
        if lo is not None or hi is not None:
            q = np.clip(q, -np.inf if lo is None else lo, np.inf if hi is None else hi)
        counts = self._to_counts(q)
        self._write_goal_counts(counts)
        self.holding = False
        self.last_target = self._to_model(counts)
        return self.last_target.copy()

    def hold(self) -> None:
        """Re-send the last target (or, if none was sent, the measured pose: staying where the
        servos are, even outside the limits, never moves them) and stay there; the next
        :meth:`send_positions` resumes following."""
        self._require_connected()
        if self.last_target is None:
            counts = self._read_counts()
        else:
            counts = self._goal_counts_of(self.last_target)
        self._write_goal_counts(counts)
        self.last_target = self._to_model(counts)
        self.holding = True

    def _goal_counts_of(self, q: np.ndarray) -> np.ndarray:
        """The counts of a target this driver sent (the inverse of :meth:`_to_model`)."""
        return self._to_counts(q)

    def disconnect(self) -> None:
        port = self._port
        if port is None:
            return
        if self.config.torque_off_on_disconnect and self._ph is not None:
            for i in self._ids:
                with contextlib.suppress(Exception):
                    self._ph.write1ByteTxRx(port, i, self.torque_address, 0)
        self._drop_port()

    # -- the port --

    def _open(self) -> None:
        cfg = self.config
        port = self.port_class(cfg.port, cfg.reply_timeout_s)
        try:
            opened = port.setBaudRate(cfg.baudrate)  # opens the port at that rate
        except PORT_ERRORS as exc:
            self.errors += 1
            _close(port)
            raise DeviceError(
                f"{self.name}: cannot open serial port {cfg.port!r} ({exc}); check the USB cable "
                f"and {self.text.adapter}, the device path (ls /dev/serial/by-id/) and permission "
                f"to open it (dialout group)"
            ) from exc
        if not opened:
            self.errors += 1
            _close(port)
            raise DeviceError(
                f"{self.name}: serial port {cfg.port!r} refused baudrate {cfg.baudrate}; check the "
                f"baudrate ({type(cfg).__name__}.baudrate)"
            )
        self._ph = self._packet_handler()
        self._port = port
        self._writer = self.sdk.GroupSyncWrite(port, self._ph, *self.goal_block)
        self._reader = self.sdk.GroupSyncRead(port, self._ph, *self.position_block)
        for i in self._ids:
            self._reader.addParam(i)

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        self._writer = self._reader = None
        if port is not None:
            self._bytes_on_closed_ports += port.bytes_written
            _close(port)

    def _require_connected(self) -> Any:
        if self._port is None:
            raise DeviceError(f"{self.name}: not connected to {self.config.port!r}; call connect()")
        return self._port

    def _reply_window_s(self) -> float:
        """How long one request waits for its reply (the SDK's 34 ms when not configured)."""
        reply = self.config.reply_timeout_s
        return 0.034 if reply is None else reply

    # -- messages --

    def _fail(self, message: str) -> DeviceError:
        self.errors += 1
        if self._port is not None:
            self._port.is_using = False  # the SDKs leave it set when a serial call raises
        return DeviceError(f"{self.name}: {message}")

    def _comm_text(self, result: int) -> str:
        return self._ph.getTxRxResult(result) or f"result {result}"

    def _error_text(self, error: int) -> str:
        return self._ph.getRxPacketError(error) or f"error 0x{error:02x}"

    def _port_failed(self, exc: BaseException, doing: str) -> DeviceError:
        return self._fail(
            f"serial port {self.config.port!r} failed while {doing}: {exc}; check {self.text.cable}"
        )

    # -- requests --

    def _ping_all(self, patience_s: float, *, per_ping: bool = False) -> None:
        """Ping every id until it answers; DeviceError naming the silent ids once none has
        answered for ``patience_s``: judged after each round over the silent ids (a bus that
        stalls for a while, then answers, is waited for), or with ``per_ping`` after every
        ping (a reconnect: a silent bus fails within ``patience_s``)."""
        cfg, unit = self.config, self.text.unit
        port = self._require_connected()
        missing = list(self._ids)
        results: dict[int, int] = {}
        last_answer = time.monotonic()
        while missing:
            for i in list(missing):
                try:
                    model, result, _ = self._ph.ping(port, i)
                except PORT_ERRORS as exc:
                    if not _empty_read(exc):
                        raise self._port_failed(exc, "pinging") from exc
                    # No answer yet (as in _retried): pinged again within the patience.
                    model, result = 0, self.sdk.COMM_RX_TIMEOUT
                    port.is_using = False
                    self._discard_input()
                results[i] = result
                if result == self.sdk.COMM_SUCCESS:
                    missing.remove(i)
                    last_answer = time.monotonic()
                    self._on_ping(i, model)
                elif per_ping and time.monotonic() - last_answer >= patience_s:
                    break
            if missing and time.monotonic() - last_answer >= patience_s:
                raise self._fail(
                    f"{unit} id(s) {missing} did not answer a ping on {cfg.port!r} at "
                    f"{cfg.baudrate} baud ({self._comm_text(results[missing[0]])}); check "
                    f"{self.text.power}, {self.text.cable}, the baudrate{self.text.ping_note} "
                    f"and the {unit} ids (expected {list(self._ids)})"
                )

    def _retried(self, request, what: str) -> tuple:
        """``request()`` -> ``(result, ...)``, asked again up to ``retries`` times while its
        reply does not come or comes corrupt; port failures raise DeviceError."""
        for attempt in range(self.config.retries + 1):
            try:
                reply = request()
            except PORT_ERRORS as exc:
                if not (_empty_read(exc) and attempt < self.config.retries):
                    raise self._port_failed(exc, what) from exc
                # One empty read is a reply not there yet (a pty under load can wake a
                # reader before its bytes arrive); an unplugged port keeps failing.
                self.retries += 1
                self._port.is_using = False  # the SDKs leave it set when a serial call raises
                self._discard_input()
                continue
            if reply[0] == self.sdk.COMM_SUCCESS:
                return reply
            if attempt < self.config.retries:
                self.retries += 1
                self._discard_input()
        return reply

    def _discard_input(self) -> None:
        with contextlib.suppress(*PORT_ERRORS, AttributeError):
            self._port.ser.reset_input_buffer()

    def _read_register(self, servo_id: int, addr: int, size: int, what: str) -> bytes:
        """``size`` bytes from ``addr`` of one servo (retried when no reply comes)."""
        port = self._require_connected()
        unit = self.text.unit

        def request() -> tuple:
            data, result, error = self._ph.readTxRx(port, servo_id, addr, size)
            if result == self.sdk.COMM_SUCCESS and len(data) < size:
                result = self.sdk.COMM_RX_CORRUPT  # a reply without the data
            return result, data, error

        result, data, error = self._retried(request, f"reading {what}")
        if result != self.sdk.COMM_SUCCESS:
            raise self._fail(
                f"reading {what} of {unit} {servo_id} on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check {self.text.power} and {self.text.cable}"
            )
        if error:
            raise self._fail(f"{unit} {servo_id} reports {self._error_text(error)} ({what})")
        return bytes(data[:size])

    def _write_register(self, servo_id: int, addr: int, size: int, value: int, what: str) -> None:
        port = self._require_connected()
        write = {1: self._ph.write1ByteTxRx, 2: self._ph.write2ByteTxRx}[size]
        raw = value & ((1 << (8 * size)) - 1)
        unit = self.text.unit
        result, error = self._retried(lambda: write(port, servo_id, addr, raw), f"writing {what}")
        if result != self.sdk.COMM_SUCCESS:
            raise self._fail(
                f"writing {what} = {value} to {unit} {servo_id} on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check {self.text.power} and {self.text.cable}"
            )
        if error:
            raise self._fail(
                f"{unit} {servo_id} refused {what} = {value} ({self._error_text(error)})"
            )

    def _torque_on_everywhere(self) -> bool:
        return all(
            self._read_register(i, self.torque_address, 1, "torque enable")[0] == 1
            for i in self._ids
        )

    def _read_counts(self) -> np.ndarray:
        missing: tuple[int, int] | None = None
        for attempt in range(self.config.retries + 1):
            counts, missing = self._sync_read_once()
            if missing is None:
                return counts
            if attempt < self.config.retries:
                self.retries += 1
        assert missing is not None
        servo_id, result = missing
        raise self._fail(
            f"no present position from {self.text.unit} {servo_id} on {self.config.port!r} "
            f"({self._comm_text(result)}); check {self.text.power} and {self.text.cable}"
        )

    def _sync_read_once(self) -> tuple[np.ndarray, tuple[int, int] | None]:
        """One sync read of Present Position: (counts, None), or (partial, (servo id, SDK
        result)) when a reply did not come or came corrupt. Port failures and the servos'
        error bytes raise."""
        port = self._require_connected()
        ok, size = self.sdk.COMM_SUCCESS, self.position_block[1]
        counts = np.empty(len(self._ids), dtype=np.int64)
        try:
            port.ser.reset_input_buffer()  # the SDKs never discard input: drop late replies
            result = self._reader.txPacket()
            if result != ok:
                raise self._fail(
                    f"sync read request on {self.config.port!r} failed "
                    f"({self._comm_text(result)}); check {self.text.cable}"
                )
            for k, i in enumerate(self._ids):
                data, result, error = self._ph.readRx(port, i, size)
                if result != ok:
                    return counts, (i, result)
                if error:
                    raise self._fail(self._status_error_text(i, error))
                if len(data) < size:
                    return counts, (i, self.sdk.COMM_RX_CORRUPT)  # a reply without the data
                counts[k] = self._decode_position(bytes(data[:size]))
        except PORT_ERRORS as exc:
            raise self._port_failed(exc, "reading") from exc
        return counts, None

    def _status_error_text(self, servo_id: int, error: int) -> str:
        return f"{self.text.unit} {servo_id} reports {self._error_text(error)}"

    def _write_goal_counts(self, counts: np.ndarray, *, count: bool = True) -> None:
        self._require_connected()
        self._writer.clearParam()
        for k, (i, c) in enumerate(zip(self._ids, counts.tolist(), strict=True)):
            self._writer.addParam(i, list(self._goal_bytes(k, int(c))))
        try:
            result = self._writer.txPacket()
        except PORT_ERRORS as exc:
            raise self._port_failed(exc, "writing") from exc
        if result != self.sdk.COMM_SUCCESS:
            raise self._fail(
                f"sync write of goal positions on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check {self.text.cable}"
            )
        if count:
            self.commands_sent += 1


def _close(port: Any) -> None:
    with contextlib.suppress(Exception):
        port.closePort()
