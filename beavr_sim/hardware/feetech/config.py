"""What an RX-1 servo group is to its driver: the servo table, the units and :class:`FeetechConfig`.

The servo table (id, direction, gear, model joint; :data:`GROUPS`) and the conversion
``counts = angle / pi * 2048 * direction * gear + 2048`` (:func:`angle_to_counts`,
:func:`counts_to_angle`) follow the RX-1's own ROS driver (Red-Rabbit-Robotics/rx1,
``rx1_motor``) and live here, in one tested place, with the sign-magnitude encoding of the STS
registers, the multi-turn reach (:func:`allowed_counts`, :data:`RX1_ANGLE_LIMITS`) and the STS
control-table addresses the driver uses. Why each is so: :mod:`beavr_sim.hardware.feetech.driver`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from beavr_sim.hardware.serial_bus import check_bus_settings, check_limits

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
    # Repeats of a register read or write or a sync read whose reply did not come or came
    # corrupt (not of port errors or servo errors; all are idempotent), counted in
    # FeetechBus.retries.
    retries: int = 2
    # Off by default: a geared arm or torso without torque falls under gravity.
    torque_off_on_disconnect: bool = False
    name: str | None = None  # default rx1_<group>

    def __post_init__(self) -> None:
        if self.group not in GROUPS:
            raise ValueError(
                f"FeetechConfig.group must be one of {sorted(GROUPS)}, got {self.group!r}"
            )
        check_bus_settings("FeetechConfig", self, SDK_BAUDRATES, "; the RX-1 runs at 1000000")
        n = len(self.servos)
        if self.joint_names is not None and (
            len(self.joint_names) != n or len(set(self.joint_names)) != n
        ):
            raise ValueError(
                f"FeetechConfig.joint_names must be {n} unique names for group {self.group!r} "
                f"({[s.joint for s in self.servos]}), got {self.joint_names!r}"
            )
        check_limits("FeetechConfig", self.lower, self.upper, n)
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
