"""The one typed hand-tracking record of beavr_sim: the headset stage's output, the operator's input.

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

The *palm frame* (computed in :mod:`beavr_sim.operator.palm`) follows the robot hand's
convention (``hand`` body of the LEAP MJCF): origin at the wrist, +z from the wrist towards
the middle knuckle (along the fingers), +x the palmar normal (out of the palm), y = z x x, so
that the thumb is at +y on a right hand and at -y on a left one. It is built from the wrist and the index, middle and
little proximal (knuckle) joints and Gram-Schmidt orthonormalised.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from beavr_sim.naming import check_name

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

    def with_times(self, t_source: float, t_receive: float) -> HandFrame:
        """This frame with other timestamps, without validating the (read-only) arrays again:
        a tenth of ``dataclasses.replace``'s cost, which matters once per frame per tick."""
        t_source, t_receive = float(t_source), float(t_receive)
        if not (np.isfinite(t_source) and np.isfinite(t_receive)):
            raise ValueError(f"frame times must be finite, got {t_source!r}, {t_receive!r}")
        frame = object.__new__(HandFrame)
        frame.__dict__.update(self.__dict__)
        object.__setattr__(frame, "t_source", t_source)
        object.__setattr__(frame, "t_receive", t_receive)
        return frame

    @property
    def palm_frame_tracked(self) -> bool:
        """Whether every joint the palm frame needs is tracked."""
        return bool(self.tracked[_PALM_FRAME_IDS].all())

    def position(self, name: str) -> np.ndarray:
        return self.joints[joint(name)]


_PALM_FRAME_IDS = np.array([JOINT_INDEX[n] for n in PALM_FRAME_JOINTS])
