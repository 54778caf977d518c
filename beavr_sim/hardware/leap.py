"""The LEAP hand driver: 16 Dynamixel X-series motors over Protocol 2.0, via ``dynamixel_sdk``.

Joint order is motor-id order (index 0-3, middle 4-7, ring 8-11, thumb 12-15). Angles: the
model's joint angle plus pi is the motor's angle (pi, 2048 counts, is the flat hand); one count
is 2 pi / 4096 rad. Those conversions live here, in one tested place (:func:`model_to_counts`,
:func:`counts_to_model` and their halves).

Set-up follows the LEAP hand's published API (leap-hand/LEAP_Hand_API): current-based position
mode (5), position gains P 600 / I 0 / D 200 with 0.75x P and D on the side-to-side motors 0, 4
and 8, and the current limit written to Goal Current (102): 550 mA for the full hand, 350 mA
for the Lite. Targets are clipped to the model's joint limits (as LEAP clips to its limits
before writing) and to one motor turn, then sent in one sync write of Goal Position (116);
positions come back in one sync read of Present Position (132).

Notes on ``dynamixel-sdk`` 4.1.0, from its source: ``GroupSyncRead.txRxPacket`` sends the plain
sync read (0x82; fast sync read 0x8A only through ``fastSyncRead``) and drops each status
packet's error byte, so reads go out through the group and the replies come back through
``PacketHandler.readRx``, which keeps it; ``txPacket`` discards the result of its own byte
stuffing, so instruction packets go out unstuffed (harmless here: goals within 0..4095 never
hold FF FF FD); replies are busy-polled against a timeout of about 34 ms, which
``reply_timeout_s`` can replace, and a lost reply is asked for again ``retries`` times.

Tested only against :mod:`beavr_sim.hardware.dynamixel_emulator` through the real SDK; nothing
here has run on a real LEAP hand.
"""

from __future__ import annotations

import contextlib
import math
import termios
import time
from dataclasses import dataclass

import numpy as np
import serial
from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler
from dynamixel_sdk.robotis_def import COMM_SUCCESS

from beavr_sim.hardware.device import Device, DeviceError
from beavr_sim.robots.parts import LEAP_VARIANT_CURRENT_MA

# --- unit conversions (the one place) --------------------------------------------------------

COUNTS_PER_REV = 4096
RAD_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV
FLAT_COUNTS = 2048  # the flat hand: hardware angle pi, model angle 0
MAX_COUNT = COUNTS_PER_REV - 1  # targets stay within one turn: 0..4095


def model_to_hardware(q: np.ndarray) -> np.ndarray:
    """Model joint angles (rad) -> motor angles (rad): ``q + pi``."""
    return np.asarray(q, dtype=np.float64) + np.pi


def hardware_to_model(h: np.ndarray) -> np.ndarray:
    """Motor angles (rad) -> model joint angles (rad): ``h - pi``."""
    return np.asarray(h, dtype=np.float64) - np.pi


def hardware_to_counts(h: np.ndarray) -> np.ndarray:
    """Motor angles (rad) -> nearest whole counts (int64)."""
    return np.rint(np.asarray(h, dtype=np.float64) / RAD_PER_COUNT).astype(np.int64)


def counts_to_hardware(c: np.ndarray) -> np.ndarray:
    """Counts -> motor angles (rad)."""
    return np.asarray(c, dtype=np.int64) * RAD_PER_COUNT


def model_to_counts(q: np.ndarray) -> np.ndarray:
    """Model joint angles (rad) -> counts; ``model_to_counts(counts_to_model(c)) == c``."""
    return hardware_to_counts(model_to_hardware(q))


def counts_to_model(c: np.ndarray) -> np.ndarray:
    """Counts -> model joint angles (rad)."""
    return hardware_to_model(counts_to_hardware(c))


# --- control table (X series) ----------------------------------------------------------------

ADDR_OPERATING_MODE = 11
ADDR_TORQUE_ENABLE = 64
ADDR_POSITION_D = 80
ADDR_POSITION_I = 82
ADDR_POSITION_P = 84
ADDR_GOAL_CURRENT = 102
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_POSITION = 132
CURRENT_BASED_POSITION_MODE = 5
MAX_GAIN = 16383
MAX_CURRENT_MA = 2352  # XC330-M288 Current Limit (38) maximum
# The current limit per variant (550 mA full, 350 mA Lite) lives with the hand model: the
# simulated hand's torque cap is derived from it (robots/parts.py, docs/models.md).
VARIANT_CURRENT_MA = LEAP_VARIANT_CURRENT_MA
# Baud rates the SDK's PortHandler accepts (getCFlagBaud).
SDK_BAUDRATES = (
    9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
    1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000,
)  # fmt: skip
_PORT_ERRORS = (OSError, serial.SerialException, termios.error)


@dataclass(frozen=True)
class LeapHandConfig:
    """How to reach and set up one LEAP hand. Validated on construction."""

    port: str
    baudrate: int = 4_000_000
    motor_ids: tuple[int, ...] = tuple(range(16))
    variant: str = "full"
    current_limit_ma: int | None = None  # overrides the variant's 550 / 350 mA
    kp: int = 600
    ki: int = 0
    kd: int = 200
    side_gain: float = 0.75  # factor on P and D of the side-to-side motors
    side_motor_ids: tuple[int, ...] = (0, 4, 8)
    lower: tuple[float, ...] | None = None  # model joint limits (rad), motor-id order
    upper: tuple[float, ...] | None = None
    timeout_s: float = 0.5  # connect: how long to keep pinging a motor that does not answer
    # Wait for each reply; None keeps the SDK's (2 x its 16 ms USB latency timer + 2 ms + the
    # bytes' time on the wire, about 34 ms at 4 Mbps).
    reply_timeout_s: float | None = None
    # Repeats of a register write or a sync read whose reply did not come (not of port errors
    # or motor errors); both are idempotent. LEAP's own client retries reads too.
    retries: int = 1
    torque_off_on_disconnect: bool = False  # off by default: a hand dropping its grip is unsafe
    name: str = "leap_hand"
    joint_names: tuple[str, ...] | None = None  # default leap_<id>

    def __post_init__(self) -> None:
        if not isinstance(self.port, str) or not self.port:
            raise ValueError(f"LeapHandConfig.port must be a device path, got {self.port!r}")
        if self.baudrate not in SDK_BAUDRATES:
            raise ValueError(
                f"LeapHandConfig.baudrate must be one of {SDK_BAUDRATES} (the SDK's), "
                f"got {self.baudrate!r}"
            )
        ids = self.motor_ids
        if (
            not isinstance(ids, tuple)
            or not ids
            or any(not isinstance(i, int) or not 0 <= i <= 252 for i in ids)
            or len(set(ids)) != len(ids)
        ):
            raise ValueError(
                f"LeapHandConfig.motor_ids must be a non-empty tuple of unique ints in 0..252, "
                f"got {ids!r}"
            )
        if self.variant not in VARIANT_CURRENT_MA:
            raise ValueError(
                f"LeapHandConfig.variant must be one of {sorted(VARIANT_CURRENT_MA)}, "
                f"got {self.variant!r}"
            )
        cur = self.current_limit_ma
        if cur is not None and (not isinstance(cur, int) or not 0 < cur <= MAX_CURRENT_MA):
            raise ValueError(
                f"LeapHandConfig.current_limit_ma must be None or an int in 1..{MAX_CURRENT_MA} "
                f"(mA), got {cur!r}"
            )
        for gain in ("kp", "ki", "kd"):
            value = getattr(self, gain)
            if not isinstance(value, int) or not 0 <= value <= MAX_GAIN:
                raise ValueError(
                    f"LeapHandConfig.{gain} must be an int in 0..{MAX_GAIN}, got {value!r}"
                )
        side = self.side_gain
        if not math.isfinite(side) or side <= 0 or round(max(self.kp, self.kd) * side) > MAX_GAIN:
            raise ValueError(
                f"LeapHandConfig.side_gain must be > 0 with side_gain * kp and side_gain * kd "
                f"<= {MAX_GAIN}, got {side!r}"
            )
        if not set(self.side_motor_ids) <= set(ids):
            raise ValueError(
                f"LeapHandConfig.side_motor_ids must be among motor_ids {ids}, "
                f"got {self.side_motor_ids!r}"
            )
        for bound in ("lower", "upper"):
            values = getattr(self, bound)
            if values is not None and (
                len(values) != len(ids) or not all(math.isfinite(v) for v in values)
            ):
                raise ValueError(
                    f"LeapHandConfig.{bound} must be None or {len(ids)} finite angles (rad), "
                    f"got {values!r}"
                )
        if self.lower is not None and self.upper is not None:
            bad = [
                i for i, (lo, hi) in enumerate(zip(self.lower, self.upper, strict=True)) if lo > hi
            ]
            if bad:
                raise ValueError(
                    f"LeapHandConfig.lower must be <= upper for every joint; not at indices {bad}"
                )
        if not math.isfinite(self.timeout_s) or self.timeout_s <= 0:
            raise ValueError(f"LeapHandConfig.timeout_s must be > 0 s, got {self.timeout_s!r}")
        if self.reply_timeout_s is not None and (
            not math.isfinite(self.reply_timeout_s) or self.reply_timeout_s <= 0
        ):
            raise ValueError(
                f"LeapHandConfig.reply_timeout_s must be None or > 0 s, "
                f"got {self.reply_timeout_s!r}"
            )
        if not isinstance(self.retries, int) or not 0 <= self.retries <= 10:
            raise ValueError(
                f"LeapHandConfig.retries must be an int in 0..10, got {self.retries!r}"
            )
        if self.joint_names is not None and len(self.joint_names) != len(ids):
            raise ValueError(
                f"LeapHandConfig.joint_names must have {len(ids)} names, "
                f"got {len(self.joint_names)}"
            )

    @property
    def goal_current_ma(self) -> int:
        """The current limit written to Goal Current (102)."""
        if self.current_limit_ma is not None:
            return self.current_limit_ma
        return VARIANT_CURRENT_MA[self.variant]

    def gains(self, motor_id: int) -> tuple[int, int, int]:
        """(P, I, D) for ``motor_id``: side-to-side motors get ``side_gain`` on P and D."""
        if motor_id in self.side_motor_ids:
            return round(self.kp * self.side_gain), self.ki, round(self.kd * self.side_gain)
        return self.kp, self.ki, self.kd

    def count_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Inclusive goal-position bounds in counts per motor: the model limits (if any) moved
        inward to whole counts, within one motor turn."""
        n = len(self.motor_ids)
        lo = np.zeros(n, dtype=np.int64)
        hi = np.full(n, MAX_COUNT, dtype=np.int64)
        tol = 1e-6  # counts: a limit that is a whole count stays that count
        if self.lower is not None:
            lo_c = model_to_hardware(self.lower) / RAD_PER_COUNT
            lo = np.maximum(lo, np.ceil(lo_c - tol).astype(np.int64))
        if self.upper is not None:
            hi_c = model_to_hardware(self.upper) / RAD_PER_COUNT
            hi = np.minimum(hi, np.floor(hi_c + tol).astype(np.int64))
        # A range narrower than one count (or outside the turn): the count nearest to it.
        empty = lo > hi
        if empty.any():
            mid = np.clip(np.rint((lo + hi) / 2.0), 0, MAX_COUNT).astype(np.int64)
            lo = np.where(empty, mid, lo)
            hi = np.where(empty, mid, hi)
        return lo, hi


class _Port(PortHandler):
    """The SDK's PortHandler with the reply timeout taken from the config (the SDK hard-codes
    it from a 16 ms USB latency timer)."""

    def __init__(self, port_name: str, reply_timeout_s: float | None) -> None:
        super().__init__(port_name)
        self.reply_timeout_ms = None if reply_timeout_s is None else 1000.0 * reply_timeout_s

    def setPacketTimeout(self, packet_length: int) -> None:
        if self.reply_timeout_ms is None:
            super().setPacketTimeout(packet_length)
            return
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.reply_timeout_ms


class LeapHand(Device):
    """One LEAP hand on a U2D2 serial adapter. See the module docstring."""

    def __init__(self, config: LeapHandConfig) -> None:
        self.config = config
        self.name = config.name
        self.joint_names = config.joint_names or tuple(f"leap_{i}" for i in config.motor_ids)
        self.commands_sent = 0
        self.errors = 0  # failures reported as DeviceError
        self.comm_retries = 0  # replies that did not come and were asked for again
        self.holding = False
        self.last_target: np.ndarray | None = None  # model rad, as written (after clipping)
        self._lo_counts, self._hi_counts = config.count_limits()
        self._port: PortHandler | None = None
        self._ph = PacketHandler(2.0)
        self._writer: GroupSyncWrite | None = None
        self._reader: GroupSyncRead | None = None

    @property
    def connected(self) -> bool:
        return self._port is not None

    # -- Device --

    def connect(self) -> None:
        if self._port is not None:
            return
        cfg = self.config
        port = _Port(cfg.port, cfg.reply_timeout_s)
        try:
            opened = port.openPort() and port.setBaudRate(cfg.baudrate)
        except _PORT_ERRORS as exc:
            self.errors += 1
            self._close(port)
            raise DeviceError(
                f"{self.name}: cannot open serial port {cfg.port!r} ({exc}); check the USB "
                f"cable and the U2D2 adapter, the device path (ls /dev/serial/by-id/) and "
                f"permission to open it (dialout group)"
            ) from exc
        if not opened:
            self.errors += 1
            self._close(port)
            raise DeviceError(
                f"{self.name}: serial port {cfg.port!r} refused baudrate {cfg.baudrate}; "
                f"check the baudrate ({SDK_BAUDRATES})"
            )
        self._port = port
        self._writer = GroupSyncWrite(port, self._ph, ADDR_GOAL_POSITION, 4)
        self._reader = GroupSyncRead(port, self._ph, ADDR_PRESENT_POSITION, 4)
        for i in cfg.motor_ids:
            self._reader.addParam(i)
        try:
            self._ping_all()
            self._set_up()
        except BaseException:
            self._close(port)
            self._port = self._writer = self._reader = None
            raise
        self.holding = False
        self.last_target = None

    def read_positions(self) -> np.ndarray:
        return counts_to_model(self._read_counts())

    def send_positions(self, positions: np.ndarray) -> np.ndarray:
        q = self.check_positions(positions)
        self._require_connected()
        lo = self.config.lower
        hi = self.config.upper
        if lo is not None or hi is not None:
            q = np.clip(q, -np.inf if lo is None else lo, np.inf if hi is None else hi)
        # Clip in radians first (no int overflow for huge targets), then to whole counts.
        h = np.clip(model_to_hardware(q), 0.0, MAX_COUNT * RAD_PER_COUNT)
        counts = np.clip(hardware_to_counts(h), self._lo_counts, self._hi_counts)
        self._write_goal_counts(counts)
        self.holding = False
        self.last_target = counts_to_model(counts)
        return self.last_target.copy()

    def hold(self) -> None:
        """Re-send the last target (or, if none was sent, the measured pose: staying where the
        hand is, even outside the limits, never moves it) and stay there; the next
        :meth:`send_positions` resumes following."""
        self._require_connected()
        if self.last_target is None:
            counts = self._read_counts()
        else:
            counts = model_to_counts(self.last_target)
        self._write_goal_counts(counts)
        self.last_target = counts_to_model(counts)
        self.holding = True

    def disconnect(self) -> None:
        port = self._port
        if port is None:
            return
        self._port = self._writer = self._reader = None
        if self.config.torque_off_on_disconnect:
            for i in self.config.motor_ids:
                with contextlib.suppress(Exception):
                    self._ph.write1ByteTxRx(port, i, ADDR_TORQUE_ENABLE, 0)
        self._close(port)

    # -- internals --

    def _require_connected(self) -> PortHandler:
        if self._port is None:
            raise DeviceError(f"{self.name}: not connected to {self.config.port!r}; call connect()")
        return self._port

    def _fail(self, message: str) -> DeviceError:
        self.errors += 1
        if self._port is not None:
            self._port.is_using = False  # the SDK leaves it set when a serial call raises
        return DeviceError(f"{self.name}: {message}")

    def _comm_text(self, result: int) -> str:
        return self._ph.getTxRxResult(result) or f"result {result}"

    def _ping_all(self) -> None:
        cfg = self.config
        port = self._require_connected()
        deadline = time.monotonic() + cfg.timeout_s
        for i in cfg.motor_ids:
            while True:
                try:
                    _, result, _ = self._ph.ping(port, i)
                except _PORT_ERRORS as exc:
                    raise self._fail(
                        f"serial port {cfg.port!r} failed while pinging: {exc}"
                    ) from exc
                if result == COMM_SUCCESS:
                    break
                if time.monotonic() >= deadline:
                    raise self._fail(
                        f"motor id {i} did not answer a ping on {cfg.port!r} at {cfg.baudrate} "
                        f"baud ({self._comm_text(result)}); check the hand's power supply, the "
                        f"USB cable, the baudrate and the motor ids (expected {cfg.motor_ids})"
                    )

    def _write_register(self, motor_id: int, addr: int, size: int, value: int, what: str) -> None:
        port = self._require_connected()
        write = {1: self._ph.write1ByteTxRx, 2: self._ph.write2ByteTxRx}[size]
        for attempt in range(self.config.retries + 1):
            try:
                result, error = write(port, motor_id, addr, value & ((1 << (8 * size)) - 1))
            except _PORT_ERRORS as exc:
                raise self._fail(f"serial port {self.config.port!r} failed: {exc}") from exc
            if result == COMM_SUCCESS:
                break
            if attempt < self.config.retries:
                self.comm_retries += 1
        if result != COMM_SUCCESS:
            raise self._fail(
                f"writing {what} = {value} to motor {motor_id} on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check power and the USB cable"
            )
        if error:
            raise self._fail(
                f"motor {motor_id} refused {what} = {value} "
                f"({self._ph.getRxPacketError(error) or f'error 0x{error:02x}'})"
            )

    def _set_up(self) -> None:
        cfg = self.config
        for i in cfg.motor_ids:
            self._write_register(i, ADDR_TORQUE_ENABLE, 1, 0, "torque enable")
            self._write_register(
                i, ADDR_OPERATING_MODE, 1, CURRENT_BASED_POSITION_MODE, "operating mode"
            )
            p, i_gain, d = cfg.gains(i)
            self._write_register(i, ADDR_POSITION_P, 2, p, "position P gain")
            self._write_register(i, ADDR_POSITION_I, 2, i_gain, "position I gain")
            self._write_register(i, ADDR_POSITION_D, 2, d, "position D gain")
            self._write_register(i, ADDR_GOAL_CURRENT, 2, cfg.goal_current_ma, "goal current (mA)")
        # Goal = present before torque on, so a stale goal from an earlier session cannot make
        # the hand jump.
        self._write_goal_counts(self._read_counts(), count=False)
        for i in cfg.motor_ids:
            self._write_register(i, ADDR_TORQUE_ENABLE, 1, 1, "torque enable")

    def _read_counts(self) -> np.ndarray:
        for attempt in range(self.config.retries + 1):
            counts, missing = self._sync_read_once()
            if missing is None:
                return counts
            if attempt < self.config.retries:
                self.comm_retries += 1
        motor_id, result = missing
        raise self._fail(
            f"no present position from motor {motor_id} on {self.config.port!r} "
            f"({self._comm_text(result)}); check the hand's power and the USB cable"
        )

    def _sync_read_once(self) -> tuple[np.ndarray, tuple[int, int] | None]:
        """One sync read of Present Position: (counts, None), or (partial, (motor id, SDK
        result)) when a reply did not come. Port failures and motor errors raise."""
        port = self._require_connected()
        assert self._reader is not None
        # GroupSyncRead.txRxPacket drops each status packet's error byte, so the transmit goes
        # through the group and the replies through readRx, which returns it.
        counts = np.empty(len(self.config.motor_ids), dtype=np.int64)
        try:
            result = self._reader.txPacket()
            if result != COMM_SUCCESS:
                raise self._fail(
                    f"sync read request on {self.config.port!r} failed "
                    f"({self._comm_text(result)}); check the USB cable"
                )
            for k, i in enumerate(self.config.motor_ids):
                data, result, error = self._ph.readRx(port, i, 4)
                if result != COMM_SUCCESS:
                    return counts, (i, result)
                if error:
                    raise self._fail(
                        f"motor {i} reports {self._ph.getRxPacketError(error) or hex(error)} "
                        f"(status error 0x{error:02x}); read Hardware Error Status (70) and "
                        f"reboot the motor"
                    )
                counts[k] = int.from_bytes(bytes(data[:4]), "little", signed=True)
        except _PORT_ERRORS as exc:
            raise self._fail(
                f"serial port {self.config.port!r} failed while reading: {exc}; check the USB cable"
            ) from exc
        return counts, None

    def _write_goal_counts(self, counts: np.ndarray, *, count: bool = True) -> None:
        self._require_connected()
        assert self._writer is not None
        self._writer.clearParam()
        for i, c in zip(self.config.motor_ids, counts.tolist(), strict=True):
            self._writer.addParam(i, list((int(c) & 0xFFFFFFFF).to_bytes(4, "little")))
        try:
            result = self._writer.txPacket()
        except _PORT_ERRORS as exc:
            raise self._fail(
                f"serial port {self.config.port!r} failed while writing: {exc}; check the USB cable"
            ) from exc
        if result != COMM_SUCCESS:
            raise self._fail(
                f"sync write of goal positions on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check the USB cable"
            )
        if count:
            self.commands_sent += 1

    @staticmethod
    def _close(port: PortHandler) -> None:
        with contextlib.suppress(Exception):
            port.closePort()
