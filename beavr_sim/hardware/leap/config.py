"""What a LEAP hand is to its driver: the model <-> motor units and :class:`LeapHandConfig`.

Angles: the model's joint angle plus pi is the motor's angle (pi, 2048 counts, is the flat
hand); one count is 2 pi / 4096 rad. Those conversions live here, in one tested place
(:func:`model_to_counts`, :func:`counts_to_model` and their halves). The X-series control table
the driver writes (addresses, modes, gain and current bounds) is listed here too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from beavr_sim.hardware.serial_bus import check_bus_settings, check_limits
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
    # Repeats of a register read or write or a sync read whose reply did not come or came
    # corrupt (not of port errors or motor errors; all are idempotent), counted in
    # LeapHand.retries. LEAP's own client retries reads too.
    retries: int = 2
    torque_off_on_disconnect: bool = False  # off by default: a hand dropping its grip is unsafe
    name: str = "leap_hand"
    joint_names: tuple[str, ...] | None = None  # default leap_<id>

    def __post_init__(self) -> None:
        check_bus_settings("LeapHandConfig", self, SDK_BAUDRATES)
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
        check_limits("LeapHandConfig", self.lower, self.upper, len(ids))
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
