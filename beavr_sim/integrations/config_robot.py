"""``--robot.type=beavr_sim``: the config of :class:`beavr_sim.integrations.robot.BeavrSimRobot`.

``hardware``: ``sim`` (the digital twin is the robot: nothing else is needed), ``emulated``
(the twin plus our protocol emulators of every device, driven through the vendors' SDKs: the
real driver paths) or the path of a rig file (TOML, ``docs/hardware.md``). Every action passes
the twin's collision guard before the twin and any hardware get it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.robots.config import RobotConfig

from beavr_sim.envs.scene import check_hand_variant
from beavr_sim.integrations.options import (
    DEFAULT_EMBODIMENT,
    check_cameras,
    check_embodiment,
    check_image_size,
    check_positive_int,
    check_task,
)

#: The robot type on LeRobot's command line (``--robot.type=beavr_sim``).
ROBOT_TYPE = "beavr_sim"
#: ``hardware`` values other than a rig file.
HARDWARE_MODES = ("sim", "emulated")


@RobotConfig.register_subclass(ROBOT_TYPE)
@dataclass(kw_only=True)
class BeavrSimRobotConfig(RobotConfig):
    """An xArm7 + LEAP rig (one or two arms) or the RX-1, behind the twin's guard."""

    embodiment: str = DEFAULT_EMBODIMENT
    #: The twin's scene: a task's objects and fixtures (the guard keeps the robot off the
    #: fixtures), or ``Playground``.
    task: str = "Playground"
    #: Seed of the scene's layout at connect (the bundled traces were made for seed 0).
    seed: int | None = 0
    #: ``sim``, ``emulated`` or a rig file (TOML).
    hardware: str = "sim"
    #: With hardware: everything but the final write to the devices.
    dry_run: bool = False
    #: The twin's cameras in the observation (``front``, ``overhead``; ``head`` on the RX-1).
    #: Rendered from the twin: a rig file has no camera devices.
    camera_names: list[str] = field(default_factory=lambda: ["front"])
    image_height: int = 480
    image_width: int = 640
    #: The twin's control rate: each ``send_action`` steps its physics one period of 1/fps.
    fps: int = 30
    #: The twin's LEAP hands ("full" or "lite"); None: the rig's hands, else "full".
    hand_variant: str | None = None
    #: Guard every action (joint limits, speed, workspace, contacts). Off only for tests.
    use_guard: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        embodiment = check_embodiment(self.embodiment)
        self.task = check_task(self.task, self.embodiment)
        self.camera_names = list(check_cameras(self.camera_names, embodiment))
        check_image_size(self.image_height, self.image_width)
        check_positive_int("fps", self.fps)
        if self.hardware not in HARDWARE_MODES:
            if not isinstance(self.hardware, str | Path) or not Path(self.hardware).is_file():
                raise FileNotFoundError(
                    f"hardware {self.hardware!r}: not one of {', '.join(HARDWARE_MODES)} and no "
                    "such rig file (TOML, see docs/hardware.md)"
                )
            self.hardware = str(self.hardware)
        elif self.dry_run and self.hardware == "sim":
            raise ValueError("dry_run needs hardware (emulated or a rig file), not sim")
        if self.hand_variant is not None:
            check_hand_variant(embodiment, self.hand_variant)

    @property
    def mirrors_hardware(self) -> bool:
        return self.hardware != "sim"
