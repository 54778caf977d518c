"""Robot parts (arm, hand, mount) and the embodiments composed from them."""

from beavr_sim.robots.embodiment import (
    EMBODIMENTS,
    Effector,
    EffectorSpec,
    Embodiment,
    EmbodimentSpec,
    JointIndex,
    make_embodiment,
)
from beavr_sim.robots.parts import LEAP_HAND, LEAP_ON_XARM7, XARM7, ArmModel, HandModel, HandMount

__all__ = [
    "EMBODIMENTS",
    "LEAP_HAND",
    "LEAP_ON_XARM7",
    "XARM7",
    "ArmModel",
    "Effector",
    "EffectorSpec",
    "Embodiment",
    "EmbodimentSpec",
    "HandModel",
    "HandMount",
    "JointIndex",
    "make_embodiment",
]
