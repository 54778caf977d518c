"""The robot parts of the xArm7 + LEAP rig, as data: model file, joint order, home, frames.

Left vs right is data here: a :class:`HandModel` names one MJCF file per side, and a
:class:`HandMount` holds the flange-to-hand transform of each side. Nothing in the code
branches on the side.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from beavr_sim.naming import check_name

SIDES = ("right", "left")


def _deg(values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(float(v) for v in np.deg2rad(values))


@dataclass(frozen=True)
class ArmModel:
    """An arm: its MJCF, joints in hardware (SDK) order, the flange site and home poses."""

    name: str
    mjcf: str
    joints: tuple[str, ...]
    home_by_side: dict[str, tuple[float, ...]]
    ee_site: str = "ee"

    def __post_init__(self) -> None:
        for side, home in self.home_by_side.items():
            check_name("side", side, SIDES)
            if len(home) != len(self.joints):
                raise ValueError(
                    f"{self.name}: home for {side} has {len(home)} values, expected "
                    f"{len(self.joints)} (one per joint {self.joints})"
                )

    def home(self, side: str) -> tuple[float, ...]:
        return self.home_by_side[check_name("side", side, self.home_by_side)]


@dataclass(frozen=True)
class HandModel:
    """A hand: one MJCF per side, joints in motor-id order, palm and fingertip-pad sites."""

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

    def __post_init__(self) -> None:
        for side in self.mjcf_by_side:
            check_name("side", side, SIDES)
        if self.home and len(self.home) != len(self.joints):
            raise ValueError(
                f"{self.name}: home has {len(self.home)} values, expected {len(self.joints)}"
            )
        if not self.home:
            object.__setattr__(self, "home", (0.0,) * len(self.joints))

    def mjcf(self, side: str) -> str:
        return self.mjcf_by_side[check_name("side", side, self.mjcf_by_side)]

    def mirrored(self, q_right, side: str) -> np.ndarray:
        """Joint values on ``side`` that make the mirror image of right-hand shape ``q_right``."""
        signs = self.mirror_signs_by_side.get(check_name("side", side, SIDES), None)
        q = np.asarray(q_right, dtype=float)
        return q * np.asarray(signs) if signs is not None else q.copy()


@dataclass(frozen=True)
class HandMount:
    """Transform from the arm's flange frame to the hand's mount frame, per side.

    ``T_flange_hand``: the hand frame sits ``pos`` (metres, flange frame) from the flange,
    rotated by ``yaw_deg`` about the flange's +z. The hand frame convention (origin on the
    adapter face, +z along the fingers, +x out of the palm) is documented in the hand MJCF.
    """

    pos: tuple[float, float, float]
    yaw_deg_by_side: dict[str, float]

    def quat(self, side: str) -> np.ndarray:
        """Unit quaternion (w, x, y, z) of the flange-to-hand rotation."""
        half = np.deg2rad(self.yaw_deg_by_side[check_name("side", side, self.yaw_deg_by_side)]) / 2
        return np.array([np.cos(half), 0.0, 0.0, np.sin(half)])


XARM7 = ArmModel(
    name="xarm7",
    mjcf="xarm7_leap/xarm7.xml",
    joints=tuple(f"joint{i}" for i in range(1, 8)),
    # BEAVR's xArm home, [0, -25, -1, 26, 0, 50, 0] degrees; the left arm mirrors it
    # through the robot's x-z plane, which negates the roll joints 1, 3, 5, 7.
    home_by_side={
        "right": _deg((0, -25, -1, 26, 0, 50, 0)),
        "left": _deg((0, -25, 1, 26, 0, 50, 0)),
    },
)

LEAP_HAND = HandModel(
    name="leap",
    mjcf_by_side={"right": "xarm7_leap/leap_right.xml", "left": "xarm7_leap/leap_left.xml"},
    joints=tuple(f"leap_{i}" for i in range(16)),
    palm_site="palm_centre",
    fingertip_sites=("thumb_tip", "index_tip", "middle_tip", "ring_tip"),
    # The left hand's thumb CMC joints (12, 13) turn the other way: their ranges are the
    # right hand's negated (see the hand MJCF).
    mirror_signs_by_side={"left": (1.0,) * 12 + (-1.0, -1.0, 1.0, 1.0)},
)

# The hand bolts to the flange through the adapter plate that is part of the hand model;
# the only freedom is the rotation about the flange axis. With these angles the palm faces
# the table at home and the thumb points to the robot's midline, mirrored for the left.
LEAP_ON_XARM7 = HandMount(pos=(0.0, 0.0, 0.0), yaw_deg_by_side={"right": 0.0, "left": 0.0})
