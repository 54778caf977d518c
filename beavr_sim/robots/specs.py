"""What an embodiment is made of, as data: :class:`EffectorSpec` (an arm with a hand, placed)
and :class:`EmbodimentSpec` (the effectors, and the body that may carry them). The built-ins
(:mod:`beavr_sim.robots.embodiment`) and robot files (:mod:`beavr_sim.robots.from_file`) both
produce these; :class:`~beavr_sim.robots.embodiment.Embodiment` composes one into a scene.
"""

from __future__ import annotations

from dataclasses import dataclass

from beavr_sim.naming import check_name
from beavr_sim.robots.parts import (
    LEAP_HAND,
    LEAP_ON_XARM7,
    SIDES,
    XARM7,
    ArmModel,
    BodyModel,
    HandModel,
    HandMount,
)


@dataclass(frozen=True)
class EffectorSpec:
    """One arm with a hand, placed at ``base_pos`` (world, metres) turned ``base_yaw_deg``.

    On an embodiment with a body, the arm attaches to the body's site for its side instead,
    and ``base_pos`` states where that site is in the world at the body's home pose (tasks
    and experts read it; a test checks it against the compiled model).
    """

    name: str
    side: str
    base_pos: tuple[float, float, float]
    base_yaw_deg: float = 0.0
    arm: ArmModel = XARM7
    hand: HandModel = LEAP_HAND
    mount: HandMount = LEAP_ON_XARM7

    def __post_init__(self) -> None:
        check_name("side", self.side, SIDES)
        if not self.name or "/" in self.name:
            raise ValueError(f"effector name must be non-empty without '/', got {self.name!r}")
        if len(self.base_pos) != 3:
            raise ValueError(f"base_pos must have 3 values, got {self.base_pos!r}")

    @property
    def prefix(self) -> str:
        return f"{self.name}/"


#: Prefix of the body's names in the scene (``body/torso_yaw``).
BODY_PREFIX = "body/"


@dataclass(frozen=True)
class EmbodimentSpec:
    """Effectors, and optionally the body that carries them (``body`` at ``body_pos``).

    ``workspace``: the table rectangle ``((x0, x1), (y0, y1))`` (world, m) where tasks lay out
    objects, when the default in front of the arm bases does not suit (a humanoid behind the
    table). ``camera_shift``: the scene's fixed cameras move by this (world, m) to frame it.
    ``guard_box``: ``(lower, upper)`` corners (world, m) of the box every moving robot geom must
    stay in (the twin guard's workspace rule), when the table's box does not hold the robot
    (arms that start behind the table).
    """

    name: str
    effectors: tuple[EffectorSpec, ...]
    description: str = ""
    body: BodyModel | None = None
    body_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    workspace: tuple[tuple[float, float], tuple[float, float]] | None = None
    camera_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    guard_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None

    def __post_init__(self) -> None:
        names = [e.name for e in self.effectors]
        if not names or len(set(names)) != len(names):
            raise ValueError(
                f"{self.name}: effector names must be unique and non-empty, got {names}"
            )
        if self.body is not None:
            for e in self.effectors:
                check_name(f"side with an arm site on {self.body.name}", e.side,
                           self.body.arm_sites_by_side)  # fmt: skip
            if BODY_PREFIX.rstrip("/") in names:
                raise ValueError(f"{self.name}: effector name 'body' is reserved for the body")
