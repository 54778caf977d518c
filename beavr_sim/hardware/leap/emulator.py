"""A Dynamixel Protocol 2.0 bus of X-series motors, emulated on a pseudo-terminal.

What is emulated: the byte stream a U2D2 adapter carries between the host and a chain of
X-series motors (the LEAP hand's XC330s), so that the vendor's own ``dynamixel_sdk``
(``PortHandler`` on :attr:`DynamixelEmulator.port`, ``PacketHandler(2.0)``, ``GroupSyncWrite``,
``GroupSyncRead``) talks to it unchanged:

* packets ``FF FF FD 00 | id | length (LE16) | instruction | params | CRC-16 (LE16)``, the
  Dynamixel CRC (polynomial 0x8005, not reflected, initial value 0), byte stuffing
  (``FF FF FD`` -> ``FF FF FD FD``) on both directions;
* instructions ping (0x01, also broadcast), read (0x02), write (0x03, also broadcast), reboot
  (0x08), sync read (0x82), sync write (0x83) and fast sync read (0x8A: one status packet from
  id 0xFE holding ``error, id, data, CRC`` per motor, each CRC the running CRC of the packet so
  far, not stuffed: the SDK parses it by position);
* status packets (instruction 0x55) with the error byte; unknown instructions get the
  instruction error (0x02), a packet with a bad CRC the CRC error (0x03);
* the part of the X-series control table the LEAP driver uses (model number 0, firmware 6,
  id 7, operating mode 11, current limit 38, torque enable 64, hardware error status 70,
  position D/I/P gains 80/82/84, goal current 102, goal position 116, present current 126,
  present velocity 128, present position 132). As on the real motors, EEPROM fields (address
  < 64) are writable only with torque off (access error 0x07 otherwise); RAM fields (torque,
  gains, goals) are writable any time; read-only or undefined addresses give the access error,
  a write covering part of a field the data length error (0x05), an out-of-range value the
  data range error (0x04), and a refused write changes nothing.

The servo model is deliberately simple and advanced by wall time (the one every emulator
shares, :mod:`beavr_sim.hardware.servo_model`): with torque on, each motor moves
towards its goal position at a bounded speed, and its present current grows with the
position error, capped at the goal current (current-based position mode) or the current limit,
so a big step shows goal and present position diverging. There is no load, no gravity, no
friction. Test hooks: :attr:`~DynamixelEmulator.goal_log`, :attr:`~DynamixelEmulator.motors`,
:meth:`~DynamixelEmulator.vanish`, :meth:`~DynamixelEmulator.inject_error`,
:meth:`~DynamixelEmulator.drop_replies`, and the faults of :meth:`~DynamixelEmulator.inject`
(the pty, framing and faults are :mod:`beavr_sim.hardware.bus_emulator`'s).

Register facts come from the ROBOTIS e-manual (XC330-M288-T control table, Protocol 2.0) and
the installed ``dynamixel_sdk`` source; nothing here was checked against a real LEAP hand.
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

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
STATUS = 0x55

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REBOOT = 0x08
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_FAST_SYNC_READ = 0x8A

# Status-packet error numbers (bits 0-6) and the hardware alert bit.
ERR_RESULT_FAIL = 0x01
ERR_INSTRUCTION = 0x02
ERR_CRC = 0x03
ERR_DATA_RANGE = 0x04
ERR_DATA_LENGTH = 0x05
ERR_DATA_LIMIT = 0x06
ERR_ACCESS = 0x07
ERR_ALERT = 0x80

# Control-table addresses (X series).
# The emulator's own, from the protocol facts, never imported from the driver: an address the
# driver gets wrong then fails against the emulator instead of agreeing with it.
ADDR_MODEL_NUMBER = 0
ADDR_FIRMWARE = 6
ADDR_ID = 7
ADDR_OPERATING_MODE = 11
ADDR_CURRENT_LIMIT = 38
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR = 70
ADDR_POSITION_D = 80
ADDR_POSITION_I = 82
ADDR_POSITION_P = 84
ADDR_GOAL_CURRENT = 102
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_CURRENT = 126
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
EEPROM_END = 64  # addresses below this are EEPROM: locked while torque is on
TABLE_SIZE = 148

MODEL_XC330_M288 = 1240
COUNTS_PER_REV = 4096
RPM_PER_VELOCITY_UNIT = 0.229
MAX_PACKET_LENGTH = 1024  # largest length field accepted (the SDK's RXPACKET_MAX_LEN)
OPERATING_MODES = frozenset({0, 1, 3, 4, 5, 16})
MAX_GAIN = 16383
MULTI_TURN_LIMIT = 1_048_575  # goal position range in modes 4 and 5


@dataclass(frozen=True)
class _Field:
    name: str  # attribute of MotorState
    size: int
    signed: bool
    writable: bool


_FIELDS: dict[int, _Field] = {
    ADDR_MODEL_NUMBER: _Field("model_number", 2, False, False),
    ADDR_FIRMWARE: _Field("firmware", 1, False, False),
    ADDR_ID: _Field("id", 1, False, False),  # writable on real motors; fixed here
    ADDR_OPERATING_MODE: _Field("operating_mode", 1, False, True),
    ADDR_CURRENT_LIMIT: _Field("current_limit", 2, False, True),
    ADDR_TORQUE_ENABLE: _Field("torque_enable", 1, False, True),
    ADDR_HARDWARE_ERROR: _Field("hardware_error", 1, False, False),
    ADDR_POSITION_D: _Field("kd", 2, False, True),
    ADDR_POSITION_I: _Field("ki", 2, False, True),
    ADDR_POSITION_P: _Field("kp", 2, False, True),
    ADDR_GOAL_CURRENT: _Field("goal_current", 2, True, True),
    ADDR_GOAL_POSITION: _Field("goal_position", 4, True, True),
    ADDR_PRESENT_CURRENT: _Field("present_current", 2, True, False),
    ADDR_PRESENT_VELOCITY: _Field("present_velocity", 4, True, False),
    ADDR_PRESENT_POSITION: _Field("present_position", 4, True, False),
}
# Which field (start address) each defined byte belongs to.
_BYTE_OWNER: dict[int, int] = {a + i: a for a, f in _FIELDS.items() for i in range(f.size)}


# --- protocol primitives ---------------------------------------------------------------------


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """The Dynamixel Protocol 2.0 CRC-16 (polynomial 0x8005, MSB first) of ``data``."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes | bytearray) -> bytes:
    """``body`` (instruction/error and parameters) with FD inserted after every FF FF FD."""
    out = bytearray()
    for b in body:
        out.append(b)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes | bytearray) -> bytes:
    """Inverse of :func:`stuff`: drop the FD that follows FF FF FD in the stuffed stream."""
    out = bytearray()
    for i, b in enumerate(body):
        if b == 0xFD and i >= 3 and body[i - 3 : i] == b"\xff\xff\xfd":
            continue
        out.append(b)
    return bytes(out)


def build_packet(dxl_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """A complete, stuffed Protocol 2.0 packet (instruction or, with 0x55, status)."""
    body = stuff(bytes([instruction]) + bytes(params))
    head = HEADER + bytes([dxl_id]) + (len(body) + 2).to_bytes(2, "little")
    packet = head + body
    return packet + crc16(packet).to_bytes(2, "little")


def status_packet(dxl_id: int, error: int, params: bytes | bytearray = b"") -> bytes:
    """A status packet from ``dxl_id`` with ``error`` and ``params``."""
    return build_packet(dxl_id, STATUS, bytes([error & 0xFF]) + bytes(params))


def fast_sync_read_packet(blocks: list[tuple[int, int, bytes]]) -> bytes:
    """The one status packet answering a fast sync read: ``(id, error, data)`` per motor, in
    order, each block followed by the running CRC of the packet so far (the last one is the
    packet's CRC). Not stuffed: the SDK reads it by position."""
    length = 1 + sum(4 + len(d) for _, _, d in blocks)
    packet = bytearray(HEADER + bytes([BROADCAST_ID]) + length.to_bytes(2, "little"))
    packet.append(STATUS)
    for dxl_id, error, data in blocks:
        packet += bytes([error & 0xFF, dxl_id]) + data
        packet += crc16(packet).to_bytes(2, "little")
    return bytes(packet)


class PacketParser(FrameParser):
    """Instruction packets from the byte stream (see :class:`FrameParser`), unstuffed. The ids
    of packets with a bad CRC collect in ``crc_errors`` (those motors answer with the CRC
    error)."""

    header = HEADER
    head_size = 7

    def __init__(self) -> None:
        super().__init__()
        self.crc_errors: list[int] = []

    def _total(self, head: bytes) -> int | None:
        length = int.from_bytes(head[5:7], "little")
        return 7 + length if 3 <= length <= MAX_PACKET_LENGTH else None

    def _valid(self, raw: bytes) -> bool:
        return crc16(raw[:-2]) == int.from_bytes(raw[-2:], "little")

    def _rejected(self, raw: bytes) -> None:
        self.crc_errors.append(raw[4])

    def _packet(self, raw: bytes) -> Packet:
        body = unstuff(raw[7:-2])
        return Packet(raw[4], body[0], body[1:])


# --- motors ----------------------------------------------------------------------------------


@dataclass
class MotorState:
    """One emulated X-series motor: control-table fields plus the float servo state.

    ``position`` is the true (float) shaft position in counts; ``present_position`` is what the
    motor reports (rounded). ``error`` is ORed into every status packet the motor sends.
    """

    id: int
    position: float = 2048.0
    model_number: int = MODEL_XC330_M288
    firmware: int = 52  # arbitrary
    operating_mode: int = 3
    current_limit: int = 2352
    torque_enable: int = 0
    hardware_error: int = 0
    kd: int = 500
    ki: int = 0
    kp: int = 1100
    goal_current: int = 2352
    goal_position: int = 2048
    velocity: float = 0.0  # counts / s
    current: float = 0.0  # mA
    error: int = 0
    writes: list[tuple[int, int, int]] = field(default_factory=list)  # (address, size, value)

    @property
    def present_position(self) -> int:
        return round(self.position)

    @property
    def present_velocity(self) -> int:
        rpm = self.velocity * 60.0 / COUNTS_PER_REV
        return round(rpm / RPM_PER_VELOCITY_UNIT)

    @property
    def present_current(self) -> int:
        return round(self.current)

    def table(self) -> bytes:
        """The control table as the motor would return it (undefined bytes read as 0)."""
        out = bytearray(TABLE_SIZE)
        for addr, f in _FIELDS.items():
            value = int(getattr(self, f.name))
            out[addr : addr + f.size] = (value & ((1 << (8 * f.size)) - 1)).to_bytes(
                f.size, "little"
            )
        return bytes(out)


def _check_value(motor: MotorState, addr: int, value: int) -> int:
    """0 if ``value`` is acceptable for the field at ``addr``, else the error number."""
    if addr == ADDR_OPERATING_MODE:
        return 0 if value in OPERATING_MODES else ERR_DATA_RANGE
    if addr == ADDR_CURRENT_LIMIT:
        return 0 if 0 <= value <= 2352 else ERR_DATA_RANGE
    if addr == ADDR_TORQUE_ENABLE:
        return 0 if value in (0, 1) else ERR_DATA_RANGE
    if addr in (ADDR_POSITION_D, ADDR_POSITION_I, ADDR_POSITION_P):
        return 0 if 0 <= value <= MAX_GAIN else ERR_DATA_RANGE
    if addr == ADDR_GOAL_CURRENT:
        return 0 if abs(value) <= motor.current_limit else ERR_DATA_RANGE
    if addr == ADDR_GOAL_POSITION:
        if motor.operating_mode in (4, 5):
            return 0 if abs(value) <= MULTI_TURN_LIMIT else ERR_DATA_RANGE
        return 0 if 0 <= value < COUNTS_PER_REV else ERR_DATA_RANGE
    return 0


# --- the bus ---------------------------------------------------------------------------------


class DynamixelEmulator(EmulatedBus):
    """A chain of emulated X-series motors behind a pseudo-terminal, served by a daemon thread.

    ``emulator.port`` is the slave device path to hand to ``dynamixel_sdk.PortHandler``. The
    bus runs at whatever baud rate the host sets (a pty has no line rate).
    """

    thread_name = "dxl-emulator"

    def __init__(
        self,
        motor_ids: tuple[int, ...] | list[int] = tuple(range(16)),
        *,
        initial_position: int | dict[int, int] = 2048,
        max_velocity_rad_s: float = 6.0,
        current_per_count_ma: float = 2.0,
        model_number: int = MODEL_XC330_M288,
        name: str | None = None,
    ) -> None:
        if not motor_ids or len(set(motor_ids)) != len(motor_ids):
            raise ValueError(f"motor_ids must be unique and non-empty, got {motor_ids!r}")
        if any(not 0 <= i <= 252 for i in motor_ids):
            raise ValueError(f"motor ids must lie in 0..252, got {motor_ids!r}")
        if not max_velocity_rad_s > 0:
            raise ValueError(f"max_velocity_rad_s must be > 0, got {max_velocity_rad_s}")
        self.max_velocity_counts = max_velocity_rad_s * COUNTS_PER_REV / (2 * math.pi)
        self.current_per_count_ma = float(current_per_count_ma)
        self.motors: dict[int, MotorState] = {}
        for i in motor_ids:
            start = per_id(initial_position, i, 2048)
            self.motors[i] = MotorState(
                id=i, position=float(start), goal_position=int(start), model_number=model_number
            )
        #: Every goal position value received (write or sync write, accepted or refused):
        #: ``(time.monotonic(), motor id, counts)``.
        self.goal_log: list[tuple[float, int, int]] = []
        self.parser = PacketParser()
        super().__init__(name)

    # -- test hooks --

    def inject_error(self, dxl_id: int, error_byte: int) -> None:
        """Make motor ``dxl_id`` report ``error_byte`` in every status packet (0 clears it).
        With the alert bit (0x80) set, Hardware Error Status (70) shows an overload (0x20)."""
        with self.lock:
            motor = self.motors[dxl_id]
            motor.error = error_byte & 0xFF
            motor.hardware_error = 0x20 if error_byte & ERR_ALERT else 0

    # -- EmulatedBus hooks (called with the lock held) --

    def _step(self, dt: float) -> None:
        for m in self.motors.values():
            cap = abs(m.goal_current) if m.operating_mode == 5 else m.current_limit
            if not m.torque_enable or cap <= 0:
                m.velocity = 0.0
                m.current = 0.0
                continue
            m.position, m.velocity = step_towards(
                m.position, m.goal_position, dt, self.max_velocity_counts
            )
            remaining = m.goal_position - m.position
            m.current = math.copysign(
                min(cap, self.current_per_count_ma * abs(remaining)), remaining
            )

    def _on_rejected(self) -> bytes:
        replies = bytearray()
        for bad_id in self.parser.crc_errors:
            if bad_id in self.motors:
                replies += self._status(self.motors[bad_id], ERR_CRC)
        self.parser.crc_errors.clear()
        return bytes(replies)

    # -- instruction handling (called with the lock held) --

    def _status(self, m: MotorState, error: int, params: bytes = b"") -> bytes:
        return status_packet(m.id, error | m.error, params)

    def _handle(self, p: Packet) -> bytes:
        if p.id == BROADCAST_ID:
            return self._handle_broadcast(p)
        motor = self.motors.get(p.id)
        if motor is None:
            return b""
        if p.instruction == INST_PING:
            params = motor.model_number.to_bytes(2, "little") + bytes([motor.firmware])
            return self._status(motor, 0, params)
        if p.instruction == INST_READ:
            if len(p.params) != 4:
                return self._status(motor, ERR_DATA_LENGTH)
            addr = int.from_bytes(p.params[0:2], "little")
            size = int.from_bytes(p.params[2:4], "little")
            error, data = self._read(motor, addr, size)
            # The data is padded on error too: the SDK's readNByteTxRx indexes it unchecked.
            return self._status(motor, error, data)
        if p.instruction == INST_WRITE:
            if len(p.params) < 3:
                return self._status(motor, ERR_DATA_LENGTH)
            addr = int.from_bytes(p.params[0:2], "little")
            return self._status(motor, self._write(motor, addr, p.params[2:]))
        if p.instruction == INST_REBOOT:
            motor.torque_enable = 0
            motor.hardware_error = 0
            motor.error = 0
            return self._status(motor, 0)
        return self._status(motor, ERR_INSTRUCTION)

    def _handle_broadcast(self, p: Packet) -> bytes:
        if p.instruction == INST_PING:
            return b"".join(
                self._status(m, 0, m.model_number.to_bytes(2, "little") + bytes([m.firmware]))
                for m in self.motors.values()
            )
        if p.instruction == INST_WRITE and len(p.params) >= 3:
            addr = int.from_bytes(p.params[0:2], "little")
            for m in self.motors.values():
                self._write(m, addr, p.params[2:])
            return b""
        if len(p.params) < 4:
            return b""
        addr = int.from_bytes(p.params[0:2], "little")
        size = int.from_bytes(p.params[2:4], "little")
        rest = p.params[4:]
        if p.instruction == INST_SYNC_WRITE:
            for motor_id, data in sync_write_blocks(rest, size):
                if motor_id in self.motors:
                    self._write(self.motors[motor_id], addr, data)
            return b""
        if p.instruction == INST_SYNC_READ:
            out = bytearray()
            for dxl_id in rest:
                m = self.motors.get(dxl_id)
                if m is not None:
                    error, data = self._read(m, addr, size)
                    out += self._status(m, error, data)
            return bytes(out)
        if p.instruction == INST_FAST_SYNC_READ:
            blocks = []
            for dxl_id in rest:
                m = self.motors.get(dxl_id)
                if m is None:  # the chain breaks: no complete answer at all
                    return b""
                error, data = self._read(m, addr, size)
                blocks.append((m.id, error | m.error, data))
            return fast_sync_read_packet(blocks) if blocks else b""
        return b""

    def _read(self, m: MotorState, addr: int, size: int) -> tuple[int, bytes]:
        if size == 0 or addr + size > TABLE_SIZE:
            return ERR_ACCESS, bytes(size)
        return 0, m.table()[addr : addr + size]

    def _write(self, m: MotorState, addr: int, data: bytes) -> int:
        """Apply a write to one motor; returns the status error number (0: accepted)."""
        end = addr + len(data)
        if ADDR_GOAL_POSITION < end and addr < ADDR_GOAL_POSITION + 4:
            if addr <= ADDR_GOAL_POSITION and end >= ADDR_GOAL_POSITION + 4:
                raw = data[ADDR_GOAL_POSITION - addr : ADDR_GOAL_POSITION - addr + 4]
                counts = int.from_bytes(raw, "little", signed=True)
                self.goal_log.append((time.monotonic(), m.id, counts))
        updates: list[tuple[int, int]] = []
        a = addr
        while a < end:
            owner = _BYTE_OWNER.get(a)
            if owner is None or not _FIELDS[owner].writable:
                return ERR_ACCESS
            f = _FIELDS[owner]
            if owner != a or a + f.size > end:
                return ERR_DATA_LENGTH
            if owner < EEPROM_END and m.torque_enable:
                return ERR_ACCESS
            value = int.from_bytes(data[a - addr : a - addr + f.size], "little", signed=f.signed)
            updates.append((owner, value))
            a += f.size
        for owner, value in updates:
            error = _check_value(m, owner, value)
            if error:
                return error
        for owner, value in updates:
            setattr(m, _FIELDS[owner].name, value)
            m.writes.append((owner, _FIELDS[owner].size, value))
        return 0
