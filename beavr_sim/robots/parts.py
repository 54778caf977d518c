"""The robot parts, as data: model file, joint order, home, frames.

Two rigs are built from these parts: xArm7 arms with LEAP hands, and the RX-1 humanoid (a
:class:`BodyModel`: torso and head, carrying two RX-1 arms) with LEAP hands.

Left vs right is data here: a :class:`HandModel` (and an arm whose sides differ) names one MJCF
file per side, and a :class:`HandMount` holds the flange-to-hand transform of each side.
Nothing in the code branches on the side.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from beavr_sim.naming import check_name

if TYPE_CHECKING:
    from beavr_sim.robots.robot_file import HandFile

SIDES = ("right", "left")


def _deg(values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(float(v) for v in np.deg2rad(values))


@dataclass(frozen=True)
class ArmServo:
    """How an arm's controller follows a stream of joint targets, as the twin models it
    (:class:`beavr_sim.envs.drive.InterpolatedServo`): interpolated between targets with
    velocity feed-forward, under these joint caps (rad/s, rad/s^2)."""

    max_velocity: float
    max_acceleration: float

    def __post_init__(self) -> None:
        if not (self.max_velocity > 0 and self.max_acceleration > 0):
            raise ValueError(
                f"ArmServo caps must be positive, got {self.max_velocity}, {self.max_acceleration}"
            )


#: The xArm in servo mode (``set_servo_angle_j``). Speed: pi rad/s (180 deg/s, the xArm7's
#: joint speed and the SDK's cap). Acceleration: the SDK's 20 rad/s^2 caps *planned* moves
#: (``mvacc``); servo-mode streams are not planned, so the reference is capped at the guard's
#: acceleration rule (``GuardConfig.arm_max_acceleration``, 150 rad/s^2) instead: the twin then
#: follows every command the guard accepted along the segment the guard checked (a tighter cap
#: made the joints fall behind unevenly and the hand leave that segment), and the links'
#: accelerations are bounded by the joint torque limits in the physics.
XARM7_SERVO = ArmServo(max_velocity=float(np.pi), max_acceleration=150.0)


@dataclass(frozen=True)
class ArmModel:
    """An arm: its MJCF, joints in hardware (SDK) order, the flange site and home poses.

    ``mjcf`` serves both sides unless ``mjcf_by_side`` names a file for a side (an arm whose
    left and right differ, like the RX-1's). ``root_body`` is the arm's base link;
    ``upper_arm_links`` and ``forearm_links`` name the links the operator's IK keeps the hand
    away from and off the table. ``pinch_heading_deg_by_side``: the heading (degrees about the
    vertical, 0 = along the base's +x) of a palm-down hand that the arm reaches the table with
    most freely, per side (sides not listed: 0); scripted grasps choose headings around it.
    ``pour_heading_deg_by_side``: the heading of a palm-down hand holding a cup from which the
    arm can roll the hand 110 deg thumb-down over the table, to pour (sides not listed: the
    pinch heading).
    """

    name: str
    mjcf: str
    joints: tuple[str, ...]
    home_by_side: dict[str, tuple[float, ...]]
    ee_site: str = "ee"
    mjcf_by_side: dict[str, str] = field(default_factory=dict)
    root_body: str = "link_base"
    upper_arm_links: tuple[str, ...] = ()
    forearm_links: tuple[str, ...] = ()
    pinch_heading_deg_by_side: dict[str, float] = field(default_factory=dict)
    pour_heading_deg_by_side: dict[str, float] = field(default_factory=dict)
    #: Whether the arm holds the hand where it is when a fingertip pushes on the table (an
    #: industrial arm does; a servo-driven one gives way a few mm, and the fingertip slips).
    holds_against_fingertips: bool = True
    #: How the arm follows joint targets in the twin: interpolated with velocity feed-forward
    #: (an :class:`ArmServo`), or ``None``: each target goes straight to the position servos.
    servo: ArmServo | None = None

    def __post_init__(self) -> None:
        for side in (
            *self.mjcf_by_side,
            *self.pinch_heading_deg_by_side,
            *self.pour_heading_deg_by_side,
        ):
            check_name("side", side, SIDES)
        for side in self.home_by_side:
            if not (self.mjcf or side in self.mjcf_by_side):
                raise ValueError(f"{self.name}: no MJCF file for side {side!r}")
        for side, home in self.home_by_side.items():
            check_name("side", side, SIDES)
            if len(home) != len(self.joints):
                raise ValueError(
                    f"{self.name}: home for {side} has {len(home)} values, expected "
                    f"{len(self.joints)} (one per joint {self.joints})"
                )

    def home(self, side: str) -> tuple[float, ...]:
        return self.home_by_side[check_name("side", side, self.home_by_side)]

    def pinch_heading(self, side: str) -> float:
        """The palm-down heading (rad, base frame) this arm reaches the table with on ``side``."""
        return float(np.deg2rad(self.pinch_heading_deg_by_side.get(side, 0.0)))

    def pour_heading(self, side: str) -> float:
        """The palm-down heading (rad, base frame) to hold a cup with on ``side`` to pour."""
        if side in self.pour_heading_deg_by_side:
            return float(np.deg2rad(self.pour_heading_deg_by_side[side]))
        return self.pinch_heading(side)

    def mjcf_for(self, side: str) -> str:
        """The MJCF file (relative to ``assets/mjcf``) of this arm's ``side``."""
        check_name("side", side, self.home_by_side)
        return self.mjcf_by_side.get(side, self.mjcf)


@dataclass(frozen=True)
class HandModel:
    """A hand: one MJCF per side, joints in motor-id order, palm and fingertip-pad sites.

    ``current_limit_ma_by_variant``: per hardware variant of the hand (the LEAP hand's
    ``"full"`` and ``"lite"``), the current limit (mA) its servos run under; with
    ``torque_constant`` (N m/A) it sets each finger joint's torque cap (:meth:`torque_cap`),
    which the scene applies to the hand's actuators. Empty: the hand file's limits stand.

    ``palm_body`` and ``collision_bodies`` (the palm and the fingertip links) are the bodies
    the operator's arm IK keeps off the table, the fixtures and the upper arm.
    ``max_velocity``: the hand joints' speed cap (rad/s) where lower than the guard's
    (``None``: the guard's). ``source``: the robot file's ``[hands.NAME]`` table of a hand
    from a model file (the operator retargets it with
    :mod:`beavr_sim.operator.retarget_model`); ``None``: the LEAP hand.
    """

    name: str
    mjcf_by_side: dict[str, str]
    joints: tuple[str, ...]
    palm_site: str
    fingertip_sites: tuple[str, ...]
    root_body: str = "hand"
    home: tuple[float, ...] = field(default=())
    #: Per side, the sign that maps a right-hand joint value to this side's joint value for
    #: the mirror-image finger shape (sides not listed: all +1).
    mirror_signs_by_side: dict[str, tuple[float, ...]] = field(default_factory=dict)
    current_limit_ma_by_variant: dict[str, float] = field(default_factory=dict)
    torque_constant: float = 0.0
    palm_body: str = "palm"
    collision_bodies: tuple[str, ...] = (
        "palm", "thumb_distal", "index_distal", "middle_distal", "ring_distal",
    )  # fmt: skip
    max_velocity: float | None = None
    source: HandFile | None = None

    def __post_init__(self) -> None:
        for side in self.mjcf_by_side:
            check_name("side", side, SIDES)
        if self.current_limit_ma_by_variant and not (
            self.torque_constant > 0
            and all(ma > 0 for ma in self.current_limit_ma_by_variant.values())
        ):
            raise ValueError(
                f"{self.name}: current limits per variant need a positive torque_constant "
                f"(N m/A) and positive limits (mA), got {self.torque_constant!r} and "
                f"{self.current_limit_ma_by_variant!r}"
            )
        if self.home and len(self.home) != len(self.joints):
            raise ValueError(
                f"{self.name}: home has {len(self.home)} values, expected {len(self.joints)}"
            )
        if not self.home:
            object.__setattr__(self, "home", (0.0,) * len(self.joints))

    def mjcf(self, side: str) -> str:
        return self.mjcf_by_side[check_name("side", side, self.mjcf_by_side)]

    @property
    def variants(self) -> tuple[str, ...]:
        """The hardware variants this hand comes in (empty: one, its file's)."""
        return tuple(self.current_limit_ma_by_variant)

    def torque_cap(self, variant: str) -> float:
        """The finger joints' torque cap (N m) of ``variant``: torque constant x current limit."""
        ma = self.current_limit_ma_by_variant[
            check_name(f"{self.name} hand variant", variant, self.current_limit_ma_by_variant)
        ]
        return self.torque_constant * ma / 1000.0

    def mirrored(self, q_right, side: str) -> np.ndarray:
        """Joint values on ``side`` that make the mirror image of right-hand shape ``q_right``."""
        signs = self.mirror_signs_by_side.get(check_name("side", side, SIDES), None)
        q = np.asarray(q_right, dtype=float)
        return q * np.asarray(signs) if signs is not None else q.copy()


@dataclass(frozen=True)
class HandMount:
    """Transform from the arm's flange frame to a frame of the hand, per side.

    The hand body ``anchor_body`` (``""``: the hand's root, its mount frame) sits ``pos``
    (metres, flange frame) from the flange, rotated by ``yaw_deg`` about the flange's +z. The
    hand frame convention (origin on the adapter face, +z along the fingers, +x out of the
    palm) is documented in the hand MJCF. An arm whose facts place the hand's palm frame (the
    RX-1 URDF places the LEAP URDF's ``palm_lower``) anchors ``"palm"``, our hand's body of
    that frame, so the facts carry over unchanged.
    """

    pos: tuple[float, float, float]
    yaw_deg_by_side: dict[str, float]
    anchor_body: str = ""

    def quat(self, side: str) -> np.ndarray:
        """Unit quaternion (w, x, y, z) of the flange-to-hand rotation."""
        half = np.deg2rad(self.yaw_deg_by_side[check_name("side", side, self.yaw_deg_by_side)]) / 2
        return np.array([np.cos(half), 0.0, 0.0, np.sin(half)])


@dataclass(frozen=True)
class BodyModel:
    """A body that carries the arms (a humanoid's torso and head), fixed at its base.

    Its joints (in hardware order) are part of the embodiment: they hold a configurable pose
    (``home``) and come after the effectors' joints in actions and ``agent_pos``. Each side's
    arm attaches at ``arm_sites_by_side[side]``.
    """

    name: str
    mjcf: str
    joints: tuple[str, ...]
    home: tuple[float, ...]
    arm_sites_by_side: dict[str, str]
    root_body: str = "base"
    #: Cameras of the body file (e.g. the head camera), by their local names.
    cameras: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.home) != len(self.joints):
            raise ValueError(
                f"{self.name}: home has {len(self.home)} values, expected {len(self.joints)} "
                f"(one per joint {self.joints})"
            )
        for side in self.arm_sites_by_side:
            check_name("side", side, SIDES)

    def with_home(self, **pose: float) -> BodyModel:
        """This body holding another pose: joint name -> angle (rad); others keep theirs."""
        for name in pose:
            check_name("body joint", name, self.joints)
        home = tuple(float(pose.get(j, h)) for j, h in zip(self.joints, self.home, strict=True))
        return BodyModel(
            self.name, self.mjcf, self.joints, home, self.arm_sites_by_side, self.root_body,
            self.cameras,
        )  # fmt: skip


XARM7 = ArmModel(
    name="xarm7",
    mjcf="xarm7_leap/xarm7.xml",
    joints=tuple(f"joint{i}" for i in range(1, 8)),
    upper_arm_links=("link_base", "link1", "link2", "link3"),
    forearm_links=("link5", "link6", "link7"),
    # BEAVR's xArm home, [0, -25, -1, 26, 0, 50, 0] degrees; the left arm mirrors it
    # through the robot's x-z plane, which negates the roll joints 1, 3, 5, 7.
    home_by_side={
        "right": _deg((0, -25, -1, 26, 0, 50, 0)),
        "left": _deg((0, -25, 1, 26, 0, 50, 0)),
    },
    servo=XARM7_SERVO,
)

#: The LEAP hand's current limit per variant (mA): what the LEAP API writes to every motor's
#: Goal Current (102) in current-based position mode (leap-hand/LEAP_Hand_API). The one place
#: these live: the driver (``hardware/leap/config.py``) imports them.
LEAP_VARIANT_CURRENT_MA = {"full": 550, "lite": 350}
#: The LEAP hand's motors, Dynamixel XC330-M288-T: stall torque 0.93 N m at 1.80 A at 5.0 V
#: (ROBOTIS e-manual; the hand runs on 5 V), as a torque constant (N m/A): a linear estimate
#: through zero (docs/models.md, "LEAP servos").
XC330_M288_TORQUE_CONSTANT = 0.93 / 1.80


def dynamixel_position_kp(p_gain: float, torque_constant: float) -> float:
    """A Dynamixel X's Position P Gain (84) in current-based position mode as a joint stiffness
    (N m/rad): the e-manual's KPP = P / 128, read as Goal Current units (1 mA) per count of
    position error (4096 counts per turn), times the torque constant (docs/models.md)."""
    return p_gain / 128 * 1e-3 * 4096 / (2 * np.pi) * torque_constant


LEAP_HAND = HandModel(
    name="leap",
    mjcf_by_side={"right": "xarm7_leap/leap_right.xml", "left": "xarm7_leap/leap_left.xml"},
    joints=tuple(f"leap_{i}" for i in range(16)),
    palm_site="palm_centre",
    fingertip_sites=("thumb_tip", "index_tip", "middle_tip", "ring_tip"),
    # The left hand's thumb CMC joints (12, 13) turn the other way: their ranges are the
    # right hand's negated (see the hand MJCF).
    mirror_signs_by_side={"left": (1.0,) * 12 + (-1.0, -1.0, 1.0, 1.0)},
    current_limit_ma_by_variant=LEAP_VARIANT_CURRENT_MA,
    torque_constant=XC330_M288_TORQUE_CONSTANT,
)

# The hand bolts to the flange through the adapter plate that is part of the hand model;
# the only freedom is the rotation about the flange axis. With these angles the palm faces
# the table at home and the thumb points to the robot's midline, mirrored for the left.
LEAP_ON_XARM7 = HandMount(pos=(0.0, 0.0, 0.0), yaw_deg_by_side={"right": 0.0, "left": 0.0})


#: The RX-1 arm (URDF ``leap_rx1.urdf``): seven revolute joints in Feetech servo order (right
#: ids 11-17, left 21-27). The left and right files differ (mirrored shoulder, and the hand
#: sits 7 cm further down the left forearm), so each side has its own.
RX1_ARM = ArmModel(
    name="rx1_arm",
    mjcf="",
    mjcf_by_side={"right": "rx1/rx1_arm_right.xml", "left": "rx1/rx1_arm_left.xml"},
    joints=(
        "shoulder_pitch",
        "shoulder_roll",
        "arm_yaw",
        "elbow",
        "forearm_yaw",
        "wrist_pitch",
        "wrist_roll",
    ),
    # Hands 0.13 m above the table just past its near edge, palms down, fingers forward (the
    # hand frame 11 deg down), elbows bent: found by IK (the elbow's lower limit, -126 deg, is
    # 8 deg away). The left differs from a mirror image: its hand sits 7 cm further down the
    # forearm.
    home_by_side={
        "right": _deg((-4, 5, 6, -118, 6, 36, -2)),
        "left": _deg((7, -8, -10, -112, -9, 29, 4)),
    },
    root_body="shoulder_base",
    upper_arm_links=("shoulder_base", "shoulder", "upper_arm"),
    forearm_links=("forearm", "wrist_pitch", "wrist_roll"),
    # The wrist bends only +-45 deg, so a palm-down hand points about where the forearm does:
    # with the elbow out to the side, forward and in towards the midline. Palm down, the
    # right hand reaches the table in front of the robot over headings of about 0 to 70 deg
    # (the left -70 to 0), and barely at all pointing outwards (IK over the workspace).
    pinch_heading_deg_by_side={"right": 35.0, "left": -35.0},
    # Rolling the hand thumb-down to pour takes the wrist roll and the arm yaw to their limits
    # from the pinch heading (the tipped cup drifts off the target); 20 deg further in leaves
    # them room (the pour succeeded on 18 of seeds 0-19 at 55 deg, 14 at 45, 12 at 70, with
    # the arm's first, softer gains).
    pour_heading_deg_by_side={"right": 55.0, "left": -55.0},
    # The thumb tip pressing on the table lifts the hand about 4 mm (the arm's and the torso's
    # servos give) and slips in under a cup instead of backing it.
    holds_against_fingertips=False,
)

#: The RX-1's torso and head (servo ids 1-6); the ears are fixed. The head looks down at the
#: table in front of the robot.
RX1_BODY = BodyModel(
    name="rx1_body",
    mjcf="rx1/rx1_body.xml",
    joints=("torso_yaw", "torso_pitch", "torso_roll", "neck_yaw", "neck_pitch", "head_roll"),
    home=_deg((0, 0, 0, 0, 40, 0)),
    arm_sites_by_side={"right": "right_shoulder", "left": "left_shoulder"},
    cameras=("head",),
)

#: The LEAP hand on the RX-1 wrist: our ``palm`` body is the LEAP URDF's ``palm_lower`` frame,
#: which the RX-1 URDF places; the arm's ``ee`` site is that placement.
LEAP_ON_RX1 = HandMount(
    pos=(0.0, 0.0, 0.0), yaw_deg_by_side={"right": 0.0, "left": 0.0}, anchor_body="palm"
)
