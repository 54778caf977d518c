"""The one typed hand-tracking message of beavr_sim, and the hand frame computed from it.

Canonical joint order (26 joints, the order of Unity XR Hands and of the BEAVR Quest app's
keypoint string; see ``docs/formats.md``)::

     0 wrist            1 palm
     2 thumb_metacarpal 3 thumb_proximal      4 thumb_distal        5 thumb_tip
     6 index_metacarpal 7 index_proximal      8 index_intermediate  9 index_distal  10 index_tip
    11 middle_...      16 ring_...           21 little_...          (same five per finger)

Positions are metres in the tracking source's world frame, converted to **right-handed,
Z-up** (x forward, y left, z up): whatever layout or handedness the source uses, a
:class:`HandFrame` is always in this frame. Joints the source did not track are flagged
``tracked=False`` (their positions are meaningless, and set to NaN by converters that have
nothing better).

The *palm frame* (:func:`T_world_palm`) follows the robot hand's convention (``hand`` body of
the LEAP MJCF): origin at the wrist, +z from the wrist towards the middle knuckle (along the
fingers), +x the palmar normal (out of the palm), y = z x x, so that the thumb is at +y on a
right hand and at -y on a left one. It is built from the wrist and the index, middle and
little proximal (knuckle) joints and Gram-Schmidt orthonormalised.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.teleop import kernels

SIDES = ("right", "left")
FINGERS = ("thumb", "index", "middle", "ring", "little")
_FINGER_JOINTS = {
    "thumb": ("metacarpal", "proximal", "distal", "tip"),
    **{f: ("metacarpal", "proximal", "intermediate", "distal", "tip") for f in FINGERS[1:]},
}
JOINT_NAMES: tuple[str, ...] = ("wrist", "palm") + tuple(
    f"{f}_{j}" for f in FINGERS for j in _FINGER_JOINTS[f]
)
N_JOINTS = len(JOINT_NAMES)  # 26
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES)}

#: Joints that define the palm frame.
PALM_FRAME_JOINTS = ("wrist", "index_proximal", "middle_proximal", "little_proximal")
#: Sign of (index knuckle - little knuckle) x fingers that gives the palmar normal, per side.
PALMAR_NORMAL_SIGN = {"right": 1.0, "left": -1.0}
RESOLUTIONS = ("high", "low")


def joint(name: str) -> int:
    """Index of a joint in the canonical order; raises with the valid names."""
    return JOINT_INDEX[check_name("hand joint", name, JOINT_INDEX)]


@dataclass(frozen=True, eq=False)
class HandFrame:
    """One tracked hand at one instant (right-handed, Z-up, metres).

    ``t_source``: when the source produced it (headset or trace clock, seconds);
    ``t_receive``: when this process received it (``time.monotonic()`` or a virtual clock).
    ``pinch``: the source's pinch gesture on this hand (thumb to ring tip), ``resolution``
    ``"high"`` or ``"low"`` (arm motion scale), ``paused``: the source asks teleop to pause.
    """

    side: str
    t_source: float
    t_receive: float
    joints: np.ndarray
    tracked: np.ndarray = field(default=None)  # type: ignore[assignment]
    pinch: bool = False
    resolution: str = "high"
    paused: bool = False

    def __post_init__(self) -> None:
        check_name("side", self.side, SIDES)
        check_name("resolution", self.resolution, RESOLUTIONS)
        joints = np.asarray(self.joints, dtype=np.float64)
        if joints.shape != (N_JOINTS, 3):
            raise ValueError(
                f"hand frame needs joints of shape ({N_JOINTS}, 3), got {joints.shape}"
            )
        tracked = (
            np.isfinite(joints).all(axis=1)
            if self.tracked is None
            else np.asarray(self.tracked, dtype=bool)
        )
        if tracked.shape != (N_JOINTS,):
            raise ValueError(f"tracked flags need shape ({N_JOINTS},), got {tracked.shape}")
        if not np.isfinite(joints[tracked]).all():
            bad = [JOINT_NAMES[i] for i in np.flatnonzero(tracked & ~np.isfinite(joints).all(1))]
            raise ValueError(f"tracked joints with NaN/inf positions: {bad}")
        for name in ("t_source", "t_receive"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)!r}")
        joints.setflags(write=False)
        tracked.setflags(write=False)
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "tracked", tracked)

    @property
    def palm_frame_tracked(self) -> bool:
        """Whether every joint the palm frame needs is tracked."""
        return bool(self.tracked[_PALM_FRAME_IDS].all())

    def position(self, name: str) -> np.ndarray:
        return self.joints[joint(name)]


_PALM_FRAME_IDS = np.array([JOINT_INDEX[n] for n in PALM_FRAME_JOINTS])
_WRIST, _MIDDLE_KNUCKLE = JOINT_INDEX["wrist"], JOINT_INDEX["middle_proximal"]
_INDEX_KNUCKLE, _LITTLE_KNUCKLE = JOINT_INDEX["index_proximal"], JOINT_INDEX["little_proximal"]


def R_world_palm(joints: np.ndarray, side: str) -> np.ndarray:
    """Rotation of the palm frame from the 26 canonical joints (see the module docstring)."""
    return T_world_palm(joints, side)[:3, :3].copy()


_PALM_ERRORS = {
    1: "degenerate hand: wrist and middle knuckle coincide",
    2: "degenerate hand: knuckles in line with the fingers",
}


def T_world_palm(joints: np.ndarray, side: str) -> np.ndarray:
    """4x4 pose of the palm frame (origin at the wrist) in the frame of ``joints``."""
    sign = PALMAR_NORMAL_SIGN.get(side)
    if sign is None:
        check_name("side", side, SIDES)
    joints = np.asarray(joints, dtype=np.float64)
    T = np.empty((4, 4))
    status = kernels.palm_pose(
        joints, _WRIST, _MIDDLE_KNUCKLE, _INDEX_KNUCKLE, _LITTLE_KNUCKLE, sign, T
    )
    if status:
        raise ValueError(_PALM_ERRORS[status])
    return T


def keypoints_in_palm(joints: np.ndarray, side: str) -> np.ndarray:
    """The 26 joints expressed in the palm frame (26 x 3)."""
    joints = np.asarray(joints, dtype=np.float64)
    out = np.empty(joints.shape)
    kernels.in_frame(joints, T_world_palm(joints, side), out)
    return out
