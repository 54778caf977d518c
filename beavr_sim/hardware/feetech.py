"""The RX-1 humanoid's Feetech STS3215 bus driver, via the vendor SDK ``scservo_sdk``.

One :class:`FeetechBus` drives one group of the RX-1's servos (:data:`GROUPS`: ``torso``,
``head``, ``body`` = torso then head, ``right_arm``, ``left_arm``) on one serial adapter at
1 Mbaud, in the model's joint convention (radians). The servo table (id, direction, gear, model
joint) and the conversion ``counts = angle / pi * 2048 * direction * gear + 2048`` follow the
RX-1's own ROS driver (Red-Rabbit-Robotics/rx1, ``rx1_motor``) and live here, in one tested place
(:data:`GROUPS`, :func:`angle_to_counts`, :func:`counts_to_angle`). Two departures from that
driver: it divides by 3.14, not pi (0.05 % more counts per radian: about 2.5 counts at the
shoulder's +-2.51 rad), and truncates to an integer where this rounds.

Multi-turn: a joint behind a 3:1 gearbox covers only +-pi/3 rad in one servo turn (counts
0..4095), less than its model range (shoulder pitch +-2.51 rad: counts 2048 -+ 4916; elbow
[-2.2, 0] rad: down to 2048 - 4300). The RX-1 driver writes the formula's counts as they come,
negative ones sign-magnitude (bit 15), which works because its makers set both angle limits
(Min 9, Max 11) of every geared servo to 0 (Red-Rabbit-Robotics/rx1 issue #3): the STS3215's
multi-turn position operation ("0 when multi-turn absolute position control is used", its memory
table). :data:`RX1_ANGLE_LIMITS` records that setup. Goals here are the formula's counts, clipped
to the model limits and to what each servo's angle limits allow (:func:`allowed_counts`): one
turn, min..max, when they are set; +-7 turns (:data:`MULTI_TURN_MAX_COUNT`) when both are 0.
:meth:`FeetechBus.connect` reads every servo's angle limits and refuses (``DeviceError``, naming
the servos, the joints and the fix) a group whose model joint range does not fit in what its
servos allow, rather than clip the joints there: a clipped joint would hold short of where the
twin goes, every time, where one fix of two EEPROM registers makes it reach. It also refuses a
multi-turn servo whose Phase (18) lacks bit 4 (full-angle feedback): such a servo reports its
position within one turn, so the driver could not tell where the joint is (and "goal = present"
at connect would move it by whole servo turns). Not detectable here: an STS3215 is reported to
forget its turn count when powered off (Red-Rabbit-Robotics/rx1 issue #8), after which it reads
its angle within one turn; power the RX-1 on with its geared joints within one servo turn of
their zero (+-pi/3 rad at a 3:1 joint), or its readings and goals are off by whole turns.

Not modelled: the RX-1's torso pitch and roll servos (ids 2 and 3) form a parallel linkage; its
driver turns (pitch, roll) into the two servo angles with a closed-form IK (``torsoIk``) before
the conversion above (its two callers pass the two torso angles in opposite orders). Here ids 2
and 3 map one-to-one to ``torso_pitch`` and ``torso_roll``, as the twin's model joints are, which
is NOT what the real torso needs: do not drive a real RX-1 torso with this driver before that
linkage is added.

Commands: one sync write per :meth:`FeetechBus.send_positions` of Acceleration (41), Goal
Position (42), Goal Time (44, always 0) and Goal Speed (46), seven bytes per servo, as the
SCServo library's ``SyncWritePosEx`` lays them out (the RX-1 driver's command). Speed and
acceleration are set in joint units (:attr:`FeetechConfig.speed_rad_s`, ``acceleration_rad_s2``)
and scaled by each servo's gear, as the RX-1 driver does. Targets are clipped to the model
limits, then to the counts the servo allows (above). Positions come back, signed, in one sync
read of Present Position (56).

Notes on ``feetech-servo-sdk`` 1.0.0 (module ``scservo_sdk``), from its source: it is only the
packet layer: no control-table constants and no sign handling (``SCS_TOHOST`` / ``SCS_TOSCS``
exist but no read or write uses them); the STS encodes negative positions and speeds as sign and
magnitude (bit 15), which :func:`to_sign_magnitude` / :func:`from_sign_magnitude` do here.
``PacketHandler(0)`` picks little-endian words by setting a process-wide global (an SCS servo's
``PacketHandler(1)`` elsewhere in the process would flip every handler): this driver encodes and
decodes register bytes itself and only ping's model number goes through the SDK's word helper.
``GroupSyncRead.rxPacket`` drops each status packet's error byte, so reads go out through the
group and come back through ``readRx``, which keeps it; one reply timeout (``(6 + size) * n``
bytes' time + 34 ms, measured with ``time.time()``) covers all the replies of a sync read;
``clearPort`` flushes output, never input, so a late reply to an earlier request would be taken
as the answer to the next: input is discarded before every sync read here. ``rxPacket`` rejects
a status packet whose error byte is above 0x7F (it reads as noise, then a timeout).

Tested only against :mod:`beavr_sim.hardware.feetech_emulator` through the real SDK; nothing here
has touched a real RX-1 or a real STS3215.
"""

from __future__ import annotations

import contextlib
import math
import termios
import time
from dataclasses import dataclass

import numpy as np
import serial
from scservo_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

from beavr_sim.hardware.device import Device, DeviceError

# --- the RX-1 servo table (the one place) ----------------------------------------------------


@dataclass(frozen=True)
class Servo:
    """One RX-1 STS3215 servo: its bus id, direction (+1 / -1), gear ratio (joint turns once
    per ``gear`` servo turns) and the model joint it drives (name without the ``body/``,
    ``right/``, ``left/`` prefix)."""

    id: int
    direction: int
    gear: int
    joint: str


def _group(ids, directions, gears, joints) -> tuple[Servo, ...]:
    return tuple(Servo(*row) for row in zip(ids, directions, gears, joints, strict=True))


_ARM_JOINTS = (
    "shoulder_pitch", "shoulder_roll", "arm_yaw", "elbow", "forearm_yaw", "wrist_pitch",
    "wrist_roll",
)  # fmt: skip
TORSO = _group((1, 2, 3), (-1, 1, -1), (3, 3, 3), ("torso_yaw", "torso_pitch", "torso_roll"))
# The head's servos 7 and 8 (directions 1, -1) move the ears: SCS servos (1024 counts per half
# turn, big-endian words) that the model keeps fixed; this driver never drives them.
HEAD = _group((4, 5, 6), (-1, -1, -1), (1, 1, 1), ("neck_yaw", "neck_pitch", "head_roll"))
EAR_SERVO_IDS = (7, 8)
RIGHT_ARM = _group(range(11, 18), (-1, -1, 1, 1, 1, 1, -1), (3, 3, 3, 3, 1, 1, 1), _ARM_JOINTS)
LEFT_ARM = _group(range(21, 28), (-1, -1, 1, -1, 1, -1, -1), (3, 3, 3, 3, 1, 1, 1), _ARM_JOINTS)
GROUPS: dict[str, tuple[Servo, ...]] = {
    "torso": TORSO,
    "head": HEAD,
    "body": TORSO + HEAD,
    "right_arm": RIGHT_ARM,
    "left_arm": LEFT_ARM,
}
SERVOS_BY_ID: dict[int, Servo] = {s.id: s for g in GROUPS.values() for s in g}

# --- unit conversions (the one place) --------------------------------------------------------

COUNTS_PER_REV = 4096
CENTER_COUNTS = 2048  # the joint's zero
MAX_COUNT = COUNTS_PER_REV - 1  # the top of one servo turn: 0..4095
# Multi-turn position operation (angle limits 9 and 11 both 0): a Feetech support note on it
# ("Regarding SMS and STS servo multi-turn and large-angle setting and control", A. Hong, Feetech,
# 2023, linkedin.com/pulse/anglecontrol-abby-hong) gives "plus or minus 7 turns" (and, in the same
# line, 30721 counts = 2700 deg: 7.5 turns). Goals here stay within the smaller figure, 7 turns
# either side of count 0, inside what the sign-magnitude word encodes (+-32767). Not checked on a
# real servo. The RX-1 needs at most about 2048 + 4916 counts (shoulder pitch).
MULTI_TURN_TURNS = 7
MULTI_TURN_MAX_COUNT = MULTI_TURN_TURNS * COUNTS_PER_REV  # 28672
STEPS_PER_RAD = COUNTS_PER_REV / (2.0 * math.pi)  # speed unit: counts (steps) per second
ACC_UNIT = 100.0  # Acceleration (41) counts in 100 steps/s^2
MAX_ACC_REGISTER = 254
# STS3215 no-load speed, datasheet: 0.222 s / 60 deg, 45 rpm (third-party measurement of a
# 12 V C018: ~46 rpm): 2 pi * 45 / 60 = 4.71 rad/s of the servo shaft, 3072 steps/s.
STS3215_NO_LOAD_RAD_S = 2.0 * math.pi * 45.0 / 60.0
MODEL_STS3215 = 777  # Model Number (3), as LeRobot's Feetech tables list it
SIGN_BIT = 15  # positions and speeds: sign and magnitude


def angle_to_counts(angle, direction, gear) -> np.ndarray:
    """Model joint angles (rad) -> servo counts: ``angle / pi * 2048 * direction * gear + 2048``,
    rounded to the nearest count (int64). Broadcasts over arrays of angles, directions, gears."""
    a = np.asarray(angle, dtype=np.float64)
    scale = np.asarray(direction, dtype=np.float64) * np.asarray(gear, dtype=np.float64)
    return np.rint(a / np.pi * CENTER_COUNTS * scale + CENTER_COUNTS).astype(np.int64)


def counts_to_angle(counts, direction, gear) -> np.ndarray:
    """Servo counts -> model joint angles (rad); ``angle_to_counts(counts_to_angle(c)) == c``."""
    c = np.asarray(counts, dtype=np.float64)
    scale = np.asarray(direction, dtype=np.float64) * np.asarray(gear, dtype=np.float64)
    return (c - CENTER_COUNTS) * np.pi / (CENTER_COUNTS * scale) + 0.0  # + 0.0: no -0.0


def to_sign_magnitude(value: int, sign_bit: int = SIGN_BIT) -> int:
    """A signed register value as the STS stores it: magnitude, with ``sign_bit`` set if < 0."""
    return (-value | (1 << sign_bit)) if value < 0 else value


def from_sign_magnitude(raw: int, sign_bit: int = SIGN_BIT) -> int:
    """Inverse of :func:`to_sign_magnitude`."""
    return -(raw & ~(1 << sign_bit)) if raw & (1 << sign_bit) else raw


def allowed_counts(min_limit: int, max_limit: int) -> tuple[int, int]:
    """The goal counts an STS3215 in position mode reaches with these angle limits (Min 9, Max
    11): both 0, multi-turn, +-:data:`MULTI_TURN_MAX_COUNT`; otherwise one turn, min..max (the
    servo clamps its goals to them). ValueError for limits an STS3215 does not take."""
    if min_limit == 0 and max_limit == 0:
        return -MULTI_TURN_MAX_COUNT, MULTI_TURN_MAX_COUNT
    if not 0 <= min_limit < max_limit <= MAX_COUNT:
        raise ValueError(
            f"angle limits {min_limit}..{max_limit} are neither 0 and 0 (multi-turn) nor "
            f"0 <= min < max <= {MAX_COUNT} (one turn)"
        )
    return min_limit, max_limit


#: The angle limits (Min 9, Max 11) the RX-1's servos run with, by id: its makers set both to 0
#: (multi-turn) on every servo behind a 3D-printed gearbox (Red-Rabbit-Robotics/rx1 issue #3);
#: the others (gear 1) are taken to keep the factory 0..4095, which their model ranges fit in.
#: What :mod:`beavr_sim.hardware.emulators` gives its emulated servos.
RX1_ANGLE_LIMITS: dict[int, tuple[int, int]] = {
    s.id: (0, 0) if s.gear > 1 else (0, MAX_COUNT) for s in SERVOS_BY_ID.values()
}


# --- control table (STS series) --------------------------------------------------------------

ADDR_MODEL_NUMBER = 3
ADDR_MIN_ANGLE_LIMIT = 9  # Max Angle Limit (11) follows it
ADDR_PHASE = 18
ADDR_OPERATING_MODE = 33
ADDR_TORQUE_ENABLE = 40
ADDR_ACCELERATION = 41
ADDR_GOAL_POSITION = 42
ADDR_GOAL_TIME = 44
ADDR_GOAL_SPEED = 46
ADDR_PRESENT_POSITION = 56
POSITION_MODE = 0
# Phase (18) bit 4, angle feedback: 0 reports the position within one turn, 1 the full
# (multi-turn) angle (the STS memory table; Feetech's multi-turn note: "+16"; LeRobot clears it
# on its STS3215s to keep readings within 0..4095).
PHASE_FULL_ANGLE_FEEDBACK = 0x10
COMMAND_SIZE = 7  # acceleration, goal position, goal time, goal speed: 41..47
# Baud rates the SDK's PortHandler accepts (getCFlagBaud).
SDK_BAUDRATES = (4800, 9600, 14400, 19200, 38400, 57600, 115200, 128000, 250000, 500000, 1000000)
_PORT_ERRORS = (OSError, serial.SerialException, termios.error)


@dataclass(frozen=True)
class FeetechConfig:
    """How to reach and drive one group of RX-1 servos. Validated on construction."""

    port: str
    group: str
    baudrate: int = 1_000_000  # the RX-1's
    joint_names: tuple[str, ...] | None = None  # full model names; default the group's joints
    lower: tuple[float, ...] | None = None  # model joint limits (rad), group order
    upper: tuple[float, ...] | None = None
    # Joint speed cap (rad/s) written to Goal Speed (46) as steps/s x gear, and acceleration
    # (rad/s^2) to Acceleration (41) in 100 steps/s^2 x gear. Defaults: the RX-1 driver's arm
    # values (1.0 rad/s, 3.0 rad/s^2; its torso uses 1.5, its head 7.0 rad/s^2). None writes
    # 0: the servo's own maximum.
    speed_rad_s: float | None = 1.0
    acceleration_rad_s2: float | None = 3.0
    model_number: int | None = MODEL_STS3215  # expected at every id; None skips the check
    timeout_s: float = 0.5  # connect: how long to keep pinging a servo that does not answer
    # Wait for each reply; None keeps the SDK's (2 x a 16 ms USB latency timer + 2 ms + the
    # bytes' time on the wire, about 34 ms).
    reply_timeout_s: float | None = None
    # Repeats of a register write or a sync read whose reply did not come (not of port errors
    # or servo errors); both are idempotent.
    retries: int = 1
    # Off by default: a geared arm or torso without torque falls under gravity.
    torque_off_on_disconnect: bool = False
    name: str | None = None  # default rx1_<group>

    def __post_init__(self) -> None:
        if not isinstance(self.port, str) or not self.port:
            raise ValueError(f"FeetechConfig.port must be a device path, got {self.port!r}")
        if self.group not in GROUPS:
            raise ValueError(
                f"FeetechConfig.group must be one of {sorted(GROUPS)}, got {self.group!r}"
            )
        if self.baudrate not in SDK_BAUDRATES:
            raise ValueError(
                f"FeetechConfig.baudrate must be one of {SDK_BAUDRATES} (the SDK's; the RX-1 "
                f"runs at 1000000), got {self.baudrate!r}"
            )
        n = len(self.servos)
        if self.joint_names is not None and (
            len(self.joint_names) != n or len(set(self.joint_names)) != n
        ):
            raise ValueError(
                f"FeetechConfig.joint_names must be {n} unique names for group {self.group!r} "
                f"({[s.joint for s in self.servos]}), got {self.joint_names!r}"
            )
        for bound in ("lower", "upper"):
            values = getattr(self, bound)
            if values is not None and (
                len(values) != n or not all(math.isfinite(v) for v in values)
            ):
                raise ValueError(
                    f"FeetechConfig.{bound} must be None or {n} finite angles (rad), got {values!r}"
                )
        if self.lower is not None and self.upper is not None:
            bad = [
                i for i, (lo, hi) in enumerate(zip(self.lower, self.upper, strict=True)) if lo > hi
            ]
            if bad:
                raise ValueError(
                    f"FeetechConfig.lower must be <= upper for every joint; not at indices {bad}"
                )
        gear = max(s.gear for s in self.servos)
        v = self.speed_rad_s
        v_max = STS3215_NO_LOAD_RAD_S / gear
        if v is not None and (not math.isfinite(v) or not 0 < v <= v_max):
            raise ValueError(
                f"FeetechConfig.speed_rad_s must be None (the servos' own maximum) or in "
                f"(0, {v_max:.3f}] rad/s for group {self.group!r} (STS3215 no-load speed "
                f"{STS3215_NO_LOAD_RAD_S:.3f} rad/s over gear {gear}), got {v!r}"
            )
        a = self.acceleration_rad_s2
        if a is not None:
            lo = 0.5 * ACC_UNIT / STEPS_PER_RAD / min(s.gear for s in self.servos)
            hi = (MAX_ACC_REGISTER + 0.5) * ACC_UNIT / STEPS_PER_RAD / gear
            if not math.isfinite(a) or not lo <= a < hi:
                raise ValueError(
                    f"FeetechConfig.acceleration_rad_s2 must be None (the servos' own maximum) "
                    f"or in [{lo:.3f}, {hi:.3f}) rad/s^2 for group {self.group!r} (Acceleration "
                    f"register 1..{MAX_ACC_REGISTER} x 100 steps/s^2 over the gears), got {a!r}"
                )
        if self.model_number is not None and (
            not isinstance(self.model_number, int) or not 0 <= self.model_number <= 0xFFFF
        ):
            raise ValueError(
                f"FeetechConfig.model_number must be None or an int in 0..65535, "
                f"got {self.model_number!r}"
            )
        if not math.isfinite(self.timeout_s) or self.timeout_s <= 0:
            raise ValueError(f"FeetechConfig.timeout_s must be > 0 s, got {self.timeout_s!r}")
        if self.reply_timeout_s is not None and (
            not math.isfinite(self.reply_timeout_s) or self.reply_timeout_s <= 0
        ):
            raise ValueError(
                f"FeetechConfig.reply_timeout_s must be None or > 0 s, got {self.reply_timeout_s!r}"
            )
        if not isinstance(self.retries, int) or not 0 <= self.retries <= 10:
            raise ValueError(f"FeetechConfig.retries must be an int in 0..10, got {self.retries!r}")
        if self.name is not None and (not isinstance(self.name, str) or not self.name):
            raise ValueError(
                f"FeetechConfig.name must be None or a non-empty string, got {self.name!r}"
            )

    @property
    def servos(self) -> tuple[Servo, ...]:
        return GROUPS[self.group]

    @property
    def servo_ids(self) -> tuple[int, ...]:
        return tuple(s.id for s in self.servos)

    @property
    def directions(self) -> np.ndarray:
        return np.array([s.direction for s in self.servos], dtype=np.int64)

    @property
    def gears(self) -> np.ndarray:
        return np.array([s.gear for s in self.servos], dtype=np.int64)

    @property
    def device_name(self) -> str:
        return self.name or f"rx1_{self.group}"

    @property
    def device_joint_names(self) -> tuple[str, ...]:
        return self.joint_names or tuple(s.joint for s in self.servos)

    @property
    def max_velocity(self) -> float:
        """The joint speed cap (rad/s): :attr:`speed_rad_s`, or without it the slowest joint's
        share of the STS3215's no-load speed (its gear's)."""
        if self.speed_rad_s is not None:
            return self.speed_rad_s
        return STS3215_NO_LOAD_RAD_S / max(s.gear for s in self.servos)

    def speed_registers(self) -> np.ndarray:
        """Goal Speed (46) per servo, steps/s (0: the servo's maximum)."""
        if self.speed_rad_s is None:
            return np.zeros(len(self.servos), dtype=np.int64)
        return np.rint(self.speed_rad_s * self.gears * STEPS_PER_RAD).astype(np.int64)

    def acceleration_registers(self) -> np.ndarray:
        """Acceleration (41) per servo, 100 steps/s^2 (0: the servo's maximum)."""
        if self.acceleration_rad_s2 is None:
            return np.zeros(len(self.servos), dtype=np.int64)
        regs = self.acceleration_rad_s2 * self.gears * STEPS_PER_RAD / ACC_UNIT
        return np.rint(regs).astype(np.int64)

    def count_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Inclusive goal bounds in counts per servo: the model limits (if any) moved inward to
        whole counts (a direction of -1 swaps which limit is which), within the multi-turn range
        +-:data:`MULTI_TURN_MAX_COUNT`; a side without a limit gets the end of that range. What
        each servo's angle limits allow narrows these at :meth:`FeetechBus.connect`."""
        n = len(self.servos)
        d, g = self.directions, self.gears
        top = MULTI_TURN_MAX_COUNT
        ends = []
        for bound, default in ((self.lower, -np.inf), (self.upper, np.inf)):
            q = np.full(n, default) if bound is None else np.asarray(bound, dtype=np.float64)
            ends.append(q / np.pi * CENTER_COUNTS * d * g + CENTER_COUNTS)  # unrounded counts
        tol = 1e-6  # counts: a limit that is a whole count stays that count
        lo_c = np.clip(np.minimum(*ends) - tol, -top - 1.0, top + 1.0)
        hi_c = np.clip(np.maximum(*ends) + tol, -top - 1.0, top + 1.0)
        lo = np.maximum(np.ceil(lo_c).astype(np.int64), -top)
        hi = np.minimum(np.floor(hi_c).astype(np.int64), top)
        # A range narrower than one count (or outside the range): the count nearest to it.
        empty = lo > hi
        if empty.any():
            mid = np.clip(np.rint((lo + hi) / 2.0), -top, top).astype(np.int64)
            lo = np.where(empty, mid, lo)
            hi = np.where(empty, mid, hi)
        return lo, hi

    def limited_count_sides(self) -> tuple[np.ndarray, np.ndarray]:
        """Per servo, whether the low and the high end of :meth:`count_limits` come from a model
        limit (a direction of -1 swaps which limit is which)."""
        up = self.directions > 0
        has_lower, has_upper = self.lower is not None, self.upper is not None
        return np.where(up, has_lower, has_upper), np.where(up, has_upper, has_lower)


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


class FeetechBus(Device):
    """One group of RX-1 STS3215 servos on one serial adapter. See the module docstring."""

    #: The RX-1 driver's loop rate; the servos take a new goal at any time.
    stream_hz = 100.0

    def __init__(self, config: FeetechConfig) -> None:
        self.config = config
        self.name = config.device_name
        self.joint_names = config.device_joint_names
        self.max_velocity = config.max_velocity
        self.commands_sent = 0
        self.errors = 0  # failures reported as DeviceError
        self.comm_retries = 0  # replies that did not come and were asked for again
        self.holding = False
        self.last_target: np.ndarray | None = None  # model rad, as written (after clipping)
        self.model_numbers: dict[int, int] = {}  # as the servos reported them on connect
        #: (Min, Max) Angle Limit per servo id, as read on connect; (0, 0): multi-turn.
        self.angle_limits: dict[int, tuple[int, int]] = {}
        self._ids = config.servo_ids
        self._dirs = config.directions
        self._gears = config.gears
        self._model_lo, self._model_hi = config.count_limits()
        self._set_count_range(self._model_lo, self._model_hi)  # narrowed on connect
        self._speeds = config.speed_registers()
        self._accs = config.acceleration_registers()
        self._port: PortHandler | None = None
        self._ph = None
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
            opened = port.setBaudRate(cfg.baudrate)  # opens the port at that rate
        except _PORT_ERRORS as exc:
            self.errors += 1
            self._close(port)
            raise DeviceError(
                f"{self.name}: cannot open serial port {cfg.port!r} ({exc}); check the USB "
                f"cable and the servo adapter board, the device path (ls /dev/serial/by-id/) "
                f"and permission to open it (dialout group)"
            ) from exc
        if not opened:
            self.errors += 1
            self._close(port)
            raise DeviceError(
                f"{self.name}: serial port {cfg.port!r} refused baudrate {cfg.baudrate}; "
                f"check the baudrate ({SDK_BAUDRATES})"
            )
        # Sets the SDK's process-wide word order to little-endian (STS) on every connect.
        self._ph = PacketHandler(0)
        self._port = port
        self._writer = GroupSyncWrite(port, self._ph, ADDR_ACCELERATION, COMMAND_SIZE)
        self._reader = GroupSyncRead(port, self._ph, ADDR_PRESENT_POSITION, 2)
        for i in self._ids:
            self._reader.addParam(i)
        try:
            self._ping_all()
            self._check_modes()
            self._check_angle_limits()
            # Goal = present before torque on: a stale goal cannot make the robot jump.
            self._write_goal_counts(self._read_counts(), count=False)
            for i in self._ids:
                self._write_register(i, ADDR_TORQUE_ENABLE, 1, "torque enable")
        except BaseException:
            self._close(port)
            self._port = self._writer = self._reader = None
            raise
        self.holding = False
        self.last_target = None

    def read_positions(self) -> np.ndarray:
        return counts_to_angle(self._read_counts(), self._dirs, self._gears)

    def send_positions(self, positions: np.ndarray) -> np.ndarray:
        q = self.check_positions(positions)
        self._require_connected()
        lo, hi = self.config.lower, self.config.upper
        if lo is not None or hi is not None:
            q = np.clip(q, -np.inf if lo is None else lo, np.inf if hi is None else hi)
        # Clip in radians first (no int overflow for huge targets), then to whole counts.
        q = np.clip(q, self._q_lo, self._q_hi)
        counts = np.clip(
            angle_to_counts(q, self._dirs, self._gears), self._lo_counts, self._hi_counts
        )
        self._write_goal_counts(counts)
        self.holding = False
        self.last_target = counts_to_angle(counts, self._dirs, self._gears)
        return self.last_target.copy()

    def hold(self) -> None:
        """Re-send the last target (or, if none was sent, the measured pose) and stay there;
        the next :meth:`send_positions` resumes following.

        An STS servo in position mode keeps going to its last goal on its own, so holding needs
        no new goal; re-sending the last one covers a lost sync write (it has no reply). Writing
        the present position instead would be wrong on the geared joints: under gravity they
        sit some counts below their goal, and every hold would lower the arm by that much.
        """
        self._require_connected()
        if self.last_target is None:
            counts = self._read_counts()
        else:
            counts = angle_to_counts(self.last_target, self._dirs, self._gears)
        self._write_goal_counts(counts)
        self.last_target = counts_to_angle(counts, self._dirs, self._gears)
        self.holding = True

    def disconnect(self) -> None:
        port = self._port
        if port is None:
            return
        self._port = self._writer = self._reader = None
        if self.config.torque_off_on_disconnect and self._ph is not None:
            for i in self._ids:
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

    def _error_text(self, error: int) -> str:
        return self._ph.getRxPacketError(error) or f"error 0x{error:02x}"

    def _ping_all(self) -> None:
        cfg = self.config
        port = self._require_connected()
        deadline = time.monotonic() + cfg.timeout_s
        missing = list(self._ids)
        results: dict[int, int] = {}
        while missing:
            for i in list(missing):
                try:
                    model, result, _ = self._ph.ping(port, i)
                except _PORT_ERRORS as exc:
                    raise self._fail(
                        f"serial port {cfg.port!r} failed while pinging: {exc}"
                    ) from exc
                results[i] = result
                if result == COMM_SUCCESS:
                    missing.remove(i)
                    self.model_numbers[i] = model
            if missing and time.monotonic() >= deadline:
                raise self._fail(
                    f"servo id(s) {missing} did not answer a ping on {cfg.port!r} at "
                    f"{cfg.baudrate} baud ({self._comm_text(results[missing[0]])}); check the "
                    f"servos' power supply, the serial port, the baudrate (the RX-1 runs at "
                    f"1 Mbaud) and the servo ids (group {cfg.group!r}: {list(self._ids)})"
                )
        wrong = {i: m for i, m in self.model_numbers.items() if m != cfg.model_number}
        if cfg.model_number is not None and wrong:
            raise self._fail(
                f"servo id(s) {sorted(wrong)} on {cfg.port!r} report model number(s) "
                f"{[wrong[i] for i in sorted(wrong)]}, expected {cfg.model_number} (STS3215); "
                f"check the servo ids (an SCS ear servo, ids {list(EAR_SERVO_IDS)}, must never "
                f"be driven as an STS)"
            )

    def _set_count_range(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """The goal counts sent from now on, and the joint angles they span (for clipping in
        radians before rounding)."""
        self._lo_counts, self._hi_counts = lo, hi
        ends = counts_to_angle(np.stack([lo, hi]), self._dirs, self._gears)
        self._q_lo, self._q_hi = ends.min(axis=0), ends.max(axis=0)

    def _read_register(self, servo_id: int, addr: int, size: int, what: str) -> bytes:
        """``size`` bytes from ``addr`` of one servo (retried when no reply comes)."""
        port = self._require_connected()
        for attempt in range(self.config.retries + 1):
            try:
                data, result, error = self._ph.readTxRx(port, servo_id, addr, size)
            except _PORT_ERRORS as exc:
                raise self._fail(f"serial port {self.config.port!r} failed: {exc}") from exc
            if result == COMM_SUCCESS and len(data) < size:
                result = -7  # COMM_RX_CORRUPT: a reply without the data
            if result == COMM_SUCCESS:
                break
            if attempt < self.config.retries:
                self.comm_retries += 1
        if result != COMM_SUCCESS:
            raise self._fail(
                f"reading {what} of servo {servo_id} on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check power and the serial cable"
            )
        if error:
            raise self._fail(f"servo {servo_id} reports {self._error_text(error)}")
        return bytes(data[:size])

    def _check_modes(self) -> None:
        for i in self._ids:
            mode = self._read_register(i, ADDR_OPERATING_MODE, 1, "the operating mode")[0]
            if mode != POSITION_MODE:
                raise self._fail(
                    f"servo {i} is in operating mode {mode}, not position mode "
                    f"({POSITION_MODE}); set Operating_Mode (33) to 0 with Feetech's tools"
                )

    def _check_angle_limits(self) -> None:
        """Read every servo's angle limits; refuse a servo whose model joint range does not fit
        in the counts they allow, or a multi-turn one that reports its position within one turn
        only; then narrow the goal range to what each servo allows."""
        limits: dict[int, tuple[int, int]] = {}
        for i in self._ids:
            raw = self._read_register(i, ADDR_MIN_ANGLE_LIMIT, 4, "the angle limits (9, 11)")
            limits[i] = (int.from_bytes(raw[:2], "little"), int.from_bytes(raw[2:], "little"))
        allowed: list[tuple[int, int]] = []
        for i in self._ids:
            try:
                allowed.append(allowed_counts(*limits[i]))
            except ValueError as exc:
                raise self._fail(
                    f"servo {i}: {exc}; set them with Feetech's FD tool: both 0 for "
                    f"multi-turn, as the RX-1 runs every servo behind a 3:1 gearbox"
                ) from None
        a_lo, a_hi = (np.array(column, dtype=np.int64) for column in zip(*allowed, strict=True))
        lo, hi = self._model_lo, self._model_hi
        lo_known, hi_known = self.config.limited_count_sides()
        misfit = (lo_known & (lo < a_lo)) | (hi_known & (hi > a_hi)) | (hi < a_lo) | (lo > a_hi)
        if misfit.any():
            bad = [k for k in range(len(self._ids)) if misfit[k]]
            needed = [
                (f"{lo[k]}" if lo_known[k] else "-inf", f"{hi[k]}" if hi_known[k] else "inf")
                for k in range(len(self._ids))
            ]
            details = "; ".join(
                f"{self._ids[k]} {self.joint_names[k]}: needs counts {needed[k][0]}.."
                f"{needed[k][1]}, angle limits {limits[self._ids[k]]} allow {a_lo[k]}..{a_hi[k]}"
                for k in bad
            )
            raise self._fail(
                f"servo(s) {[self._ids[k] for k in bad]} cannot reach their model joint range "
                f"({details}); a servo whose angle limits (Min 9, Max 11) are set stays within "
                f"one turn, counts 0..4095: set both to 0 with Feetech's FD tool, multi-turn "
                f"position operation, as the RX-1 runs every servo behind a 3:1 gearbox "
                f"(Red-Rabbit-Robotics/rx1 issue #3), and set bit 4 of its Phase (18) so it "
                f"reports the full angle (or, for a range within one turn, widen the limits)"
            )
        multi = [i for i in self._ids if limits[i] == (0, 0)]
        one_turn_feedback = [
            i
            for i in multi
            if not self._read_register(i, ADDR_PHASE, 1, "the phase (18)")[0]
            & PHASE_FULL_ANGLE_FEEDBACK
        ]
        if one_turn_feedback:
            raise self._fail(
                f"servo(s) {one_turn_feedback} run multi-turn (angle limits 0 and 0) but report "
                f"their position within one turn (Phase (18) bit 4 clear): the driver could not "
                f"tell where their joints are; set bit 4 of Phase (add 16) with Feetech's FD tool"
            )
        self.angle_limits = limits
        self._set_count_range(np.maximum(lo, a_lo), np.minimum(hi, a_hi))

    def _write_register(self, servo_id: int, addr: int, value: int, what: str) -> None:
        port = self._require_connected()
        for attempt in range(self.config.retries + 1):
            try:
                result, error = self._ph.write1ByteTxRx(port, servo_id, addr, value & 0xFF)
            except _PORT_ERRORS as exc:
                raise self._fail(f"serial port {self.config.port!r} failed: {exc}") from exc
            if result == COMM_SUCCESS:
                break
            if attempt < self.config.retries:
                self.comm_retries += 1
        if result != COMM_SUCCESS:
            raise self._fail(
                f"writing {what} = {value} to servo {servo_id} on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check power and the serial cable"
            )
        if error:
            raise self._fail(
                f"servo {servo_id} reports {self._error_text(error)} after {what} = {value}"
            )

    def _read_counts(self) -> np.ndarray:
        for attempt in range(self.config.retries + 1):
            counts, missing = self._sync_read_once()
            if missing is None:
                return counts
            if attempt < self.config.retries:
                self.comm_retries += 1
        servo_id, result = missing
        raise self._fail(
            f"no present position from servo {servo_id} on {self.config.port!r} "
            f"({self._comm_text(result)}); check the servos' power and the serial cable"
        )

    def _sync_read_once(self) -> tuple[np.ndarray, tuple[int, int] | None]:
        """One sync read of Present Position: (counts, None), or (partial, (servo id, SDK
        result)) when a reply did not come. Port failures and servo errors raise."""
        port = self._require_connected()
        assert self._reader is not None
        counts = np.empty(len(self._ids), dtype=np.int64)
        try:
            # The SDK never discards input: drop late replies to an earlier request.
            port.ser.reset_input_buffer()
            result = self._reader.txPacket()
            if result != COMM_SUCCESS:
                raise self._fail(
                    f"sync read request on {self.config.port!r} failed "
                    f"({self._comm_text(result)}); check the serial cable"
                )
            for k, i in enumerate(self._ids):
                data, result, error = self._ph.readRx(port, i, 2)
                if result != COMM_SUCCESS:
                    return counts, (i, result)
                if error:
                    raise self._fail(
                        f"servo {i} reports {self._error_text(error)} (status 0x{error:02x}); "
                        f"check its load, temperature and supply voltage, then enable torque "
                        f"again (a protection may have cut it)"
                    )
                if len(data) < 2:
                    return counts, (i, -7)  # COMM_RX_CORRUPT: a reply without the data
                counts[k] = from_sign_magnitude(int.from_bytes(bytes(data[:2]), "little"))
        except _PORT_ERRORS as exc:
            raise self._fail(
                f"serial port {self.config.port!r} failed while reading: {exc}; check the "
                f"serial cable"
            ) from exc
        return counts, None

    def _write_goal_counts(self, counts: np.ndarray, *, count: bool = True) -> None:
        self._require_connected()
        assert self._writer is not None
        self._writer.clearParam()
        for i, c, v, a in zip(
            self._ids, counts.tolist(), self._speeds.tolist(), self._accs.tolist(), strict=True
        ):
            data = (
                bytes([a])
                + to_sign_magnitude(int(c)).to_bytes(2, "little")
                + bytes(2)  # Goal Time: 0, the speed register rules
                + to_sign_magnitude(int(v)).to_bytes(2, "little")
            )
            self._writer.addParam(i, list(data))
        try:
            result = self._writer.txPacket()
        except _PORT_ERRORS as exc:
            raise self._fail(
                f"serial port {self.config.port!r} failed while writing: {exc}; check the "
                f"serial cable"
            ) from exc
        if result != COMM_SUCCESS:
            raise self._fail(
                f"sync write of goal positions on {self.config.port!r} failed "
                f"({self._comm_text(result)}); check the serial cable"
            )
        if count:
            self.commands_sent += 1

    @staticmethod
    def _close(port: PortHandler) -> None:
        with contextlib.suppress(Exception):
            port.closePort()
