"""A Feetech SCS/STS bus of STS3215 servos, emulated on a pseudo-terminal.

What is emulated: the byte stream between the host and a chain of STS3215 servos (the RX-1's),
so that the vendor's own ``scservo_sdk`` (``PortHandler`` on :attr:`FeetechEmulator.port`,
``PacketHandler(0)``, ``GroupSyncWrite``, ``GroupSyncRead``) talks to it unchanged:

* packets ``FF FF | id | length | instruction | params | checksum``, with ``length`` = number
  of params + 2 and ``checksum = ~(id + length + instruction + sum(params)) & 0xFF``;
* instructions ping (0x01), read (0x02: ``address, size``), write (0x03: ``address, data``),
  sync read (0x82: ``address, size, id...``, one status packet per listed servo, in order) and
  sync write (0x83: ``address, size, (id, data)...``, no reply); packets to the broadcast id
  0xFE get no reply;
* status packets ``FF FF | id | length | error | params | checksum``; the error byte is the
  servo's protection flags (bit 0 voltage, 1 angle sensor, 2 overheat, 3 overcurrent,
  5 overload), set only through :meth:`FeetechEmulator.inject_error`;
* the part of the STS control table the RX-1 driver uses, words little-endian, positions and
  speeds sign and magnitude (bit 15): firmware version 0-1, model number 3 (777), id 5, baud
  rate 6, angle limits 9 / 11, phase 18, operating mode 33, torque enable 40, acceleration 41
  (100 steps per s^2; 0: no limit), goal position 42, goal time 44, goal speed 46 (steps/s; 0:
  the servo's top speed), torque limit 48, lock 55, present position 56, present speed 58,
  present load 60, voltage 62, temperature 63, status 65, moving 66, present current 69.

Choices where the facts at hand stop (nothing here was checked against a real servo): a packet
with a bad checksum is ignored, with no reply, as the servo cannot trust the id it carries and
the STS status byte has no checksum bit: the host sees a timeout and asks again. Unknown
instructions are ignored too. A write to a read-only, undefined or EEPROM address (the EEPROM
fields are fixed here) changes nothing and is answered with error 0; values a field cannot hold
are ignored (torque enable other than 0 / 1: the real servo's 128 recalibrates its centre, which
is never wanted here); goal positions are clamped to the angle limits, as the servo does in
position mode. A goal write does not switch torque on.

Multi-turn: a servo whose angle limits are both 0 (``angle_limits=(0, 0)``, the default, as the
RX-1 runs its geared servos) takes any goal the sign-magnitude word encodes (the real servo's
multi-turn reach, "+-7 turns" in Feetech's words, is not modelled) and its shaft position goes
past one turn either way. It reports that full, signed position when bit 4 of its Phase (18) is
set (the default here, :data:`PHASE_FULL_ANGLE_FEEDBACK`), else the position within one turn
(0..4095), as an STS3215 with single-turn feedback does. A servo with limits set (e.g.
``(0, 4095)``, the factory's) clamps its goals to them and stays within one turn. Not modelled:
the turn count a real servo is reported to lose when powered off.

The servo model is the one every emulator shares (:mod:`beavr_sim.hardware.servo_model`),
advanced by wall time: with torque on, each servo moves towards its goal at its goal speed (or its top
speed) with its acceleration, braking to stop on the goal. Test hooks:
:attr:`~FeetechEmulator.goal_log`, :attr:`~FeetechEmulator.servos`,
:meth:`~FeetechEmulator.vanish`, :meth:`~FeetechEmulator.inject_error`,
:meth:`~FeetechEmulator.drop_replies`, and the faults of :meth:`~FeetechEmulator.inject` (the
pty, framing and faults are :mod:`beavr_sim.hardware.bus_emulator`'s).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from beavr_sim.hardware.bus_emulator import (
    EmulatedBus,
    FrameParser,
    Packet,
    per_id,
    sync_write_blocks,
)
from beavr_sim.hardware.servo_model import step_towards

HEADER = b"\xff\xff"
BROADCAST_ID = 0xFE

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83

# Status-packet error bits (the servo's protection flags, as the SDK names them).
ERRBIT_VOLTAGE = 0x01
ERRBIT_ANGLE = 0x02
ERRBIT_OVERHEAT = 0x04
ERRBIT_OVERCURRENT = 0x08
ERRBIT_OVERLOAD = 0x20

# Control-table addresses (STS series).
# The emulator's own, from the protocol facts, never imported from the driver: an address the
# driver gets wrong then fails against the emulator instead of agreeing with it.
ADDR_FIRMWARE_MAJOR = 0
ADDR_FIRMWARE_MINOR = 1
ADDR_MODEL_NUMBER = 3
ADDR_ID = 5
ADDR_BAUD_RATE = 6
ADDR_MIN_ANGLE_LIMIT = 9
ADDR_MAX_ANGLE_LIMIT = 11
ADDR_PHASE = 18
ADDR_OPERATING_MODE = 33
ADDR_TORQUE_ENABLE = 40
ADDR_ACCELERATION = 41
ADDR_GOAL_POSITION = 42
ADDR_GOAL_TIME = 44
ADDR_GOAL_SPEED = 46
ADDR_TORQUE_LIMIT = 48
ADDR_LOCK = 55
ADDR_PRESENT_POSITION = 56
ADDR_PRESENT_SPEED = 58
ADDR_PRESENT_LOAD = 60
ADDR_PRESENT_VOLTAGE = 62
ADDR_PRESENT_TEMPERATURE = 63
ADDR_STATUS = 65
ADDR_MOVING = 66
ADDR_PRESENT_CURRENT = 69
EEPROM_END = 40  # addresses below this are EEPROM (fixed here)
TABLE_SIZE = 86

MODEL_STS3215 = 777
COUNTS_PER_REV = 4096
MAX_COUNT = COUNTS_PER_REV - 1
MAX_MAGNITUDE = 0x7FFF  # the largest |position| a sign-magnitude word (bit 15) holds
PHASE_FULL_ANGLE_FEEDBACK = 0x10  # Phase (18) bit 4: report the full (multi-turn) angle
MULTI_TURN = (0, 0)  # angle limits of a servo in multi-turn position operation
ONE_TURN = (0, MAX_COUNT)  # the factory's angle limits
TOP_SPEED_STEPS = 3072  # STS3215 no-load speed, 45 rpm, in steps/s
ACC_UNIT = 100  # Acceleration (41) counts in 100 steps/s^2
MAX_LENGTH = 246  # largest length field: the SDK's 250-byte packets less header, id, length


def checksum(body: bytes | bytearray) -> int:
    """The packet checksum over ``id, length, instruction/error, params``."""
    return ~sum(body) & 0xFF


def build_packet(servo_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """A complete packet (an instruction, or a status packet with the error byte in place of
    the instruction)."""
    body = bytes([servo_id, len(params) + 2, instruction]) + bytes(params)
    return HEADER + body + bytes([checksum(body)])


def status_packet(servo_id: int, error: int, params: bytes | bytearray = b"") -> bytes:
    """A status packet from ``servo_id`` with ``error`` and ``params``."""
    return build_packet(servo_id, error & 0xFF, params)


def encode(value: int, size: int, sign_bit: int | None) -> bytes:
    """A register value as the servo stores it: sign and magnitude at ``sign_bit`` (if any),
    little-endian."""
    if sign_bit is not None and value < 0:
        value = -value | (1 << sign_bit)
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def decode(data: bytes, sign_bit: int | None) -> int:
    """Inverse of :func:`encode`."""
    value = int.from_bytes(data, "little")
    if sign_bit is not None and value & (1 << sign_bit):
        return -(value & ~(1 << sign_bit))
    return value


class PacketParser(FrameParser):
    """Instruction packets from the byte stream (see :class:`FrameParser`); a packet whose
    checksum fails gets no reply. ``checksum_errors`` counts them."""

    header = HEADER
    head_size = 4

    def __init__(self) -> None:
        super().__init__()
        self.checksum_errors = 0

    def _total(self, head: bytes) -> int | None:
        servo_id, length = head[2], head[3]
        if servo_id == 0xFF or length < 2 or length > MAX_LENGTH:
            return None  # FF FF FF: the first FF was noise; or an impossible length
        return 4 + length

    def _valid(self, raw: bytes) -> bool:
        return checksum(raw[2:-1]) == raw[-1]

    def _rejected(self, raw: bytes) -> None:
        self.checksum_errors += 1

    def _packet(self, raw: bytes) -> Packet:
        return Packet(raw[2], raw[4], raw[5:-1])


# --- servos ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Field:
    name: str  # attribute of ServoState
    size: int
    sign_bit: int | None
    writable: bool


_FIELDS: dict[int, _Field] = {
    ADDR_FIRMWARE_MAJOR: _Field("firmware_major", 1, None, False),
    ADDR_FIRMWARE_MINOR: _Field("firmware_minor", 1, None, False),
    ADDR_MODEL_NUMBER: _Field("model_number", 2, None, False),
    ADDR_ID: _Field("id", 1, None, False),
    ADDR_BAUD_RATE: _Field("baud_rate", 1, None, False),
    ADDR_MIN_ANGLE_LIMIT: _Field("min_angle_limit", 2, None, False),
    ADDR_MAX_ANGLE_LIMIT: _Field("max_angle_limit", 2, None, False),
    ADDR_PHASE: _Field("phase", 1, None, False),
    ADDR_OPERATING_MODE: _Field("operating_mode", 1, None, False),
    ADDR_TORQUE_ENABLE: _Field("torque_enable", 1, None, True),
    ADDR_ACCELERATION: _Field("acceleration", 1, None, True),
    ADDR_GOAL_POSITION: _Field("goal_position", 2, 15, True),
    ADDR_GOAL_TIME: _Field("goal_time", 2, None, True),
    ADDR_GOAL_SPEED: _Field("goal_speed", 2, 15, True),
    ADDR_TORQUE_LIMIT: _Field("torque_limit", 2, None, True),
    ADDR_LOCK: _Field("lock", 1, None, True),
    ADDR_PRESENT_POSITION: _Field("present_position", 2, 15, False),
    ADDR_PRESENT_SPEED: _Field("present_speed", 2, 15, False),
    ADDR_PRESENT_LOAD: _Field("present_load", 2, 10, False),
    ADDR_PRESENT_VOLTAGE: _Field("present_voltage", 1, None, False),
    ADDR_PRESENT_TEMPERATURE: _Field("present_temperature", 1, None, False),
    ADDR_STATUS: _Field("error", 1, None, False),
    ADDR_MOVING: _Field("moving", 1, None, False),
    ADDR_PRESENT_CURRENT: _Field("present_current", 2, 15, False),
}


@dataclass
class ServoState:
    """One emulated STS3215: control-table fields plus the float servo state.

    ``position`` is the true (float) shaft position in counts, past one turn either way when
    multi-turn, ``velocity`` its speed (counts/s); ``present_position`` is what the servo
    reports (rounded; within one turn for a multi-turn servo without full-angle feedback).
    ``error`` is the status byte of every packet the servo sends.
    """

    id: int
    position: float = 2048.0
    velocity: float = 0.0
    model_number: int = MODEL_STS3215
    firmware_major: int = 3
    firmware_minor: int = 10
    baud_rate: int = 0  # 1 Mbaud
    min_angle_limit: int = 0  # both 0: multi-turn
    max_angle_limit: int = MAX_COUNT
    phase: int = PHASE_FULL_ANGLE_FEEDBACK
    operating_mode: int = 0  # position mode
    torque_enable: int = 0
    acceleration: int = 0
    goal_position: int = 2048
    goal_time: int = 0
    goal_speed: int = 0
    torque_limit: int = 1000
    lock: int = 1
    present_voltage: int = 120  # 0.1 V
    present_temperature: int = 30  # deg C
    error: int = 0
    writes: list[tuple[int, int, int]] = field(default_factory=list)  # (address, size, value)

    @property
    def multi_turn(self) -> bool:
        return self.min_angle_limit == 0 and self.max_angle_limit == 0

    @property
    def present_position(self) -> int:
        if self.multi_turn and not self.phase & PHASE_FULL_ANGLE_FEEDBACK:
            return round(self.position) % COUNTS_PER_REV
        return max(-MAX_MAGNITUDE, min(MAX_MAGNITUDE, round(self.position)))

    @property
    def present_speed(self) -> int:
        return round(self.velocity)

    @property
    def present_load(self) -> int:
        return 0

    @property
    def present_current(self) -> int:
        return 0

    @property
    def moving(self) -> int:
        return int(self.velocity != 0.0)

    def table(self) -> bytes:
        """The control table as the servo would return it (undefined bytes read as 0)."""
        out = bytearray(TABLE_SIZE)
        for addr, f in _FIELDS.items():
            out[addr : addr + f.size] = encode(int(getattr(self, f.name)), f.size, f.sign_bit)
        return bytes(out)


# --- the bus ---------------------------------------------------------------------------------


class FeetechEmulator(EmulatedBus):
    """A chain of emulated STS3215 servos behind a pseudo-terminal, served by a daemon thread.

    ``emulator.port`` is the slave device path to hand to ``scservo_sdk.PortHandler``.
    ``initial_position``: counts, for all servos or per id (signed, past one turn for a
    multi-turn servo; within its limits for one with limits set). ``angle_limits``: (Min, Max)
    Angle Limit, for all servos or per id (missing ids: multi-turn); :data:`MULTI_TURN`
    ``(0, 0)``, the default, as the RX-1 runs its geared servos, or one turn, e.g.
    :data:`ONE_TURN`. ``top_speed_steps``: the speed (steps/s) a servo moves at with Goal Speed 0,
    and the most it ever moves at.
    """

    thread_name = "feetech-emulator"

    def __init__(
        self,
        servo_ids: tuple[int, ...] | list[int],
        *,
        initial_position: int | dict[int, int] = 2048,
        angle_limits: tuple[int, int] | dict[int, tuple[int, int]] = MULTI_TURN,
        top_speed_steps: float = TOP_SPEED_STEPS,
        model_number: int = MODEL_STS3215,
        name: str | None = None,
    ) -> None:
        ids = tuple(servo_ids)
        if not ids or len(set(ids)) != len(ids) or any(not 0 <= i <= 253 for i in ids):
            raise ValueError(f"servo_ids must be unique ids in 0..253, got {servo_ids!r}")
        if not top_speed_steps > 0:
            raise ValueError(f"top_speed_steps must be > 0, got {top_speed_steps}")
        self.top_speed_steps = float(top_speed_steps)
        #: The servos by id (test hook: read or set their state under :attr:`lock`).
        self.servos: dict[int, ServoState] = {}
        for i in ids:
            start = per_id(initial_position, i, 2048)
            lo, hi = per_id(angle_limits, i, MULTI_TURN)
            if (lo, hi) != MULTI_TURN and not 0 <= lo < hi <= MAX_COUNT:
                raise ValueError(
                    f"servo {i}: angle_limits must be (0, 0) (multi-turn) or 0 <= min < max <= "
                    f"{MAX_COUNT} (one turn), got {(lo, hi)!r}"
                )
            top = MAX_MAGNITUDE if (lo, hi) == MULTI_TURN else MAX_COUNT
            bottom = -top if (lo, hi) == MULTI_TURN else 0
            if not bottom <= start <= top:
                raise ValueError(
                    f"servo {i}: initial_position {start} must be in {bottom}..{top} for angle "
                    f"limits {(lo, hi)!r}"
                )
            self.servos[i] = ServoState(
                id=i,
                position=float(start),
                goal_position=int(start),
                model_number=model_number,
                min_angle_limit=int(lo),
                max_angle_limit=int(hi),
            )
        #: Every goal position value received (write or sync write), as sent:
        #: ``(time.monotonic(), servo id, counts)``; the goals of one packet share the time.
        self.goal_log: list[tuple[float, int, int]] = []
        self.parser = PacketParser()
        super().__init__(name)

    # -- test hooks --

    def inject_error(self, servo_id: int, error_byte: int) -> None:
        """Make servo ``servo_id`` report ``error_byte`` (e.g. :data:`ERRBIT_OVERLOAD`) in every
        status packet and in Status (65); 0 clears it. The SDK takes a status packet whose
        error byte is above 0x7F for noise."""
        with self.lock:
            self.servos[servo_id].error = error_byte & 0xFF

    # -- EmulatedBus hooks (called with the lock held) --

    def _step(self, dt: float) -> None:
        for s in self.servos.values():
            if not s.torque_enable:
                s.velocity = 0.0
                continue
            speed = s.goal_speed if s.goal_speed > 0 else self.top_speed_steps
            accel = s.acceleration * ACC_UNIT if s.acceleration > 0 else math.inf
            s.position, s.velocity = step_towards(
                s.position,
                s.goal_position,
                dt,
                min(speed, self.top_speed_steps),
                s.velocity,
                accel,
            )

    # -- instruction handling --

    def _handle(self, p: Packet) -> bytes:
        if p.id == BROADCAST_ID:
            return self._handle_broadcast(p)
        servo = self.servos.get(p.id)
        if servo is None:
            return b""
        if p.instruction == INST_PING:
            return status_packet(servo.id, servo.error)
        if p.instruction == INST_READ:
            if len(p.params) != 2:
                return b""
            return self._read(servo, p.params[0], p.params[1])
        if p.instruction == INST_WRITE:
            if len(p.params) < 2:
                return b""
            self._write(servo, p.params[0], p.params[1:], time.monotonic())
            return status_packet(servo.id, servo.error)
        return b""

    def _handle_broadcast(self, p: Packet) -> bytes:
        if p.instruction == INST_WRITE and len(p.params) >= 2:
            now = time.monotonic()
            for s in self.servos.values():
                self._write(s, p.params[0], p.params[1:], now)
            return b""
        if len(p.params) < 2:
            return b""
        addr, size, rest = p.params[0], p.params[1], p.params[2:]
        if p.instruction == INST_SYNC_WRITE:
            now = time.monotonic()
            for servo_id, data in sync_write_blocks(rest, size):
                if servo_id in self.servos:
                    self._write(self.servos[servo_id], addr, data, now)
            return b""
        if p.instruction == INST_SYNC_READ:
            return b"".join(
                self._read(self.servos[i], addr, size) for i in rest if i in self.servos
            )
        return b""

    def _read(self, s: ServoState, addr: int, size: int) -> bytes:
        if size + 2 > MAX_LENGTH:
            return b""
        table = s.table()
        data = table[addr : addr + size]
        return status_packet(s.id, s.error, data + bytes(size - len(data)))

    def _write(self, s: ServoState, addr: int, data: bytes, now: float) -> None:
        """Apply a write to one servo: every writable field it covers whole, no other."""
        end = addr + len(data)
        for a, f in _FIELDS.items():
            if not (addr <= a and a + f.size <= end):
                continue
            value = decode(data[a - addr : a - addr + f.size], f.sign_bit)
            if a == ADDR_GOAL_POSITION:
                self.goal_log.append((now, s.id, value))
            if not f.writable or a < EEPROM_END:
                continue
            if a == ADDR_TORQUE_ENABLE and value not in (0, 1):
                continue
            if a == ADDR_GOAL_POSITION and s.operating_mode == 0:
                if s.min_angle_limit or s.max_angle_limit:
                    value = max(s.min_angle_limit, min(s.max_angle_limit, value))
            setattr(s, f.name, value)
            s.writes.append((a, f.size, value))
