"""What an xArm7 is to its driver: its joint limits and :class:`XArmConfig`.

The joint limits are the SDK's ``XCONF.Robot.JOINT_LIMITS`` for the xArm7 (X4 type), which the
MJCF model uses too; the controller (and :mod:`beavr_sim.hardware.xarm.emulator`) refuses
targets outside them. ``XArmConfig`` is validated on construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: xArm7 joint limits (rad): the SDK's ``XCONF.Robot.JOINT_LIMITS`` for the xArm7 X4 type,
#: which the MJCF model uses too.
XARM7_JOINT_LIMITS: tuple[tuple[float, float], ...] = (
    (-2 * math.pi, 2 * math.pi),
    (-2.059488, 2.094395),
    (-2 * math.pi, 2 * math.pi),
    (-0.191986, 3.92699),
    (-2 * math.pi, 2 * math.pi),
    (-1.692969, math.pi),
    (-2 * math.pi, 2 * math.pi),
)


@dataclass(frozen=True)
class XArmConfig:
    """How to reach one xArm7 and which controller safety settings to apply on connect.

    ``reduced_joint_ranges`` (rad, 7 (low, high) pairs inside the xArm7 limits),
    ``tcp_boundary_mm`` ([x_max, x_min, y_max, y_min, z_max, z_min]) and ``max_joint_speed``
    (rad/s) are reduced-mode settings: sent only when ``reduced_mode`` is on.
    ``max_joint_acc`` (rad/s^2) is always sent. ``connect_timeout_s`` bounds the whole
    connect; ``command_timeout_s`` is the SDK's per-request reply timeout afterwards.
    """

    host: str
    port: int | None = None
    enable_report: bool = False
    collision_sensitivity: int = 3
    self_collision_detection: bool = True
    reduced_mode: bool = True
    reduced_joint_ranges: tuple[tuple[float, float], ...] | None = None
    tcp_boundary_mm: tuple[float, ...] | None = None
    max_joint_speed: float = 2.5  # above the operator IK's 2 rad/s, under the arm's pi
    max_joint_acc: float = 10.0
    connect_timeout_s: float = 3.0
    command_timeout_s: float = 1.0
    # Repeats of a request whose reply did not come in command_timeout_s or came garbled (SDK
    # codes 3-7), counted in XArm7.retries; controller errors are not repeated.
    retries: int = 2

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not self.host.strip():
            raise ValueError(f"XArmConfig.host: a non-empty IP or host name, got {self.host!r}")
        if self.port is not None and (
            isinstance(self.port, bool)
            or not isinstance(self.port, int)
            or not 0 < self.port < 65536
        ):
            raise ValueError(
                f"XArmConfig.port: None (SDK default 502) or 1..65535, got {self.port!r}"
            )
        if self.enable_report and self.port is not None:
            raise ValueError(
                "XArmConfig.enable_report: True needs port=None (the SDK's report ports cannot "
                "be redirected); use enable_report=False with a custom port"
            )
        for field in ("enable_report", "self_collision_detection", "reduced_mode"):
            if not isinstance(getattr(self, field), bool):
                raise ValueError(f"XArmConfig.{field}: True or False, got {getattr(self, field)!r}")
        cs = self.collision_sensitivity
        if isinstance(cs, bool) or not isinstance(cs, int) or not 0 <= cs <= 5:
            raise ValueError(f"XArmConfig.collision_sensitivity: an integer 0..5, got {cs!r}")
        _check_range("max_joint_speed", self.max_joint_speed, 0.0, math.pi, "rad/s")
        _check_range("max_joint_acc", self.max_joint_acc, 0.0, 20.0, "rad/s^2")
        _check_range("connect_timeout_s", self.connect_timeout_s, 0.0, 600.0, "s")
        _check_range("command_timeout_s", self.command_timeout_s, 0.0, 60.0, "s")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int):
            raise ValueError(f"XArmConfig.retries: an integer 0..10, got {self.retries!r}")
        if not 0 <= self.retries <= 10:
            raise ValueError(f"XArmConfig.retries: an integer 0..10, got {self.retries!r}")
        if not self.reduced_mode and (self.reduced_joint_ranges or self.tcp_boundary_mm):
            raise ValueError(
                "XArmConfig.reduced_mode: must be True when reduced_joint_ranges or "
                "tcp_boundary_mm is given (they apply only in reduced mode)"
            )
        if self.reduced_joint_ranges is not None:
            object.__setattr__(
                self, "reduced_joint_ranges", _joint_ranges(self.reduced_joint_ranges)
            )
        if self.tcp_boundary_mm is not None:
            object.__setattr__(self, "tcp_boundary_mm", _tcp_boundary(self.tcp_boundary_mm))


def _check_range(field: str, value: object, low: float, high: float, unit: str) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or not low < value <= high:  # type: ignore[arg-type]
        raise ValueError(
            f"XArmConfig.{field}: a number in ({low}, {high:.6g}] {unit}, got {value!r}"
        )


def _joint_ranges(value: object) -> tuple[tuple[float, float], ...]:
    field = "XArmConfig.reduced_joint_ranges"
    try:
        pairs = tuple((float(lo), float(hi)) for lo, hi in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{field}: 7 (low, high) pairs in radians, got {value!r}") from None
    if len(pairs) != 7:
        raise ValueError(f"{field}: 7 (low, high) pairs in radians, got {len(pairs)}")
    for j, ((lo, hi), (jlo, jhi)) in enumerate(zip(pairs, XARM7_JOINT_LIMITS, strict=True), 1):
        if not (math.isfinite(lo) and math.isfinite(hi) and jlo <= lo < hi <= jhi):
            raise ValueError(
                f"{field}: joint {j} needs {jlo:.4f} <= low < high <= {jhi:.4f} rad, got ({lo}, {hi})"
            )
    return pairs


def _tcp_boundary(value: object) -> tuple[float, ...]:
    field = "XArmConfig.tcp_boundary_mm"
    try:
        b = tuple(float(x) for x in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(
            f"{field}: 6 numbers [x_max, x_min, y_max, y_min, z_max, z_min] mm"
        ) from None
    if len(b) != 6 or not all(math.isfinite(x) for x in b):
        raise ValueError(
            f"{field}: 6 finite numbers [x_max, x_min, y_max, y_min, z_max, z_min] mm, got {value!r}"
        )
    for axis, (hi, lo) in zip("xyz", (b[0:2], b[2:4], b[4:6]), strict=True):
        if not hi > lo:
            raise ValueError(f"{field}: {axis}_max must exceed {axis}_min, got {hi} <= {lo}")
    return b
