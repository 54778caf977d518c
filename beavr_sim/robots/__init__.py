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
from beavr_sim.robots.parts import (
    LEAP_HAND,
    LEAP_ON_RX1,
    LEAP_ON_XARM7,
    RX1_ARM,
    RX1_BODY,
    XARM7,
    ArmModel,
    BodyModel,
    HandModel,
    HandMount,
)

__all__ = [
    "EMBODIMENTS",
    "LEAP_HAND",
    "LEAP_ON_RX1",
    "LEAP_ON_XARM7",
    "RX1_ARM",
    "RX1_BODY",
    "XARM7",
    "ArmModel",
    "BodyModel",
    "Effector",
    "EffectorSpec",
    "Embodiment",
    "EmbodimentSpec",
    "HandModel",
    "HandMount",
    "JointIndex",
    "make_embodiment",
]
