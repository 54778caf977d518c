"""``--robot.type=beavr_sim``: the config of :class:`beavr_sim.integrations.robot.BeavrSimRobot`.

``hardware``: ``sim`` (the digital twin is the robot: nothing else is needed), ``emulated``
(the twin plus our protocol emulators of every device, driven through the vendors' SDKs: the
real driver paths) or the path of a rig file (TOML, ``docs/hardware.md``). Every action passes
the twin's collision guard before the twin and any hardware get it.

Images: the twin's renders (``camera_names``) and real cameras the LeRobot way (``cameras``: a
dict of LeRobot camera configs, as LeRobot's own robots take them) plus a rig file's
``[cameras.NAME]`` tables; a real camera states ``width``, ``height`` and ``fps`` (the
dataset declares each image's shape before the cameras open). ``camera_poses`` (a rig file,
as teleop's ``--camera-poses``, read by the same loader) stands the twin's cameras at its
tables' ``T_world_camera`` poses. A twin camera with a real camera of its name is observed as
``NAME_twin``, the real one as ``NAME`` (:mod:`beavr_sim.cameras.names`, teleop's rule too).
Every error is one line naming the camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.cameras.configs import CameraConfig
from lerobot.robots.config import RobotConfig

from beavr_sim.cameras.errors import CameraSpecError
from beavr_sim.cameras.names import recorded_twin_names
from beavr_sim.cameras.poses import load_camera_poses
from beavr_sim.cameras.real import DEPTH_SUFFIX
from beavr_sim.cameras.spec import CONFIG_TYPES, check_camera_name, merge_cameras, rig_cameras
from beavr_sim.envs.camera_pose import PlacedCamera
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
    #: With ``hardware=emulated``: faults the protocol emulators rehearse, as teleop's
    #: ``--emulate-faults`` (``right_arm:freeze=2@5``, docs/hardware.md); None: none.
    emulate_faults: str | None = None
    #: The twin's cameras in the observation (``front``, ``overhead``; ``head`` on the RX-1),
    #: rendered from the twin (real ones: ``cameras``).
    camera_names: list[str] = field(default_factory=lambda: ["front"])
    image_height: int = 480
    image_width: int = 640
    #: Real cameras, LeRobot's camera configs by name (``--robot.cameras="{wrist: {type:
    #: opencv, index_or_path: 0, width: 640, height: 480, fps: 30}}"``), recorded as
    #: ``observation.images.NAME`` next to the twin's; opened at connect (docs/cameras.md).
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    #: A file of ``[cameras.NAME]`` tables (a rig file) whose ``T_world_camera`` poses place
    #: the twin's cameras (as teleop's ``--camera-poses``): the scene's camera of that name
    #: moves there, another name is added (and may be in ``camera_names``). None: no file.
    camera_poses: str | None = None
    #: A real camera whose newest frame is older than this fails ``get_observation`` (as
    #: LeRobot's own robots' ``read_latest``: 0.5 s): never a frozen frame recorded as live.
    camera_max_age_s: float = 0.5
    #: The twin's control rate: each ``send_action`` steps its physics one period of 1/fps.
    fps: int = 30
    #: The twin's LEAP hands ("full" or "lite"); None: the rig's hands, else "full".
    hand_variant: str | None = None
    #: Guard every action (joint limits, speed, workspace, contacts). Off only for tests.
    use_guard: bool = True

    def __post_init__(self) -> None:
        embodiment = check_embodiment(self.embodiment)
        self.task = check_task(self.task, self.embodiment)
        placed = tuple(c.name for c in self.placed_cameras())
        self.camera_names = list(check_cameras(self.camera_names, embodiment, placed))
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
        if not isinstance(self.cameras, dict):
            raise CameraSpecError(
                f"cameras must be a dict of camera name -> LeRobot camera config, got "
                f"{self.cameras!r}"
            )
        check_real_cameras(self.real_camera_configs(), self.camera_names)
        super().__post_init__()  # LeRobot's own check of ``cameras`` (passes after ours)
        if not self.camera_max_age_s > 0:
            raise ValueError(f"camera_max_age_s must be > 0, got {self.camera_max_age_s!r}")

    def real_camera_configs(self) -> dict[str, CameraConfig]:
        """The real cameras: a rig file's ``[cameras.NAME]`` tables (``hardware`` = a rig
        file, as ``teleop --mirror-hardware`` records them) and ``cameras``; a name in both is
        an error."""
        rig = rig_cameras(self.hardware) if self.hardware not in HARDWARE_MODES else {}
        return merge_cameras(rig, self.cameras, "cameras")

    def placed_cameras(self) -> tuple[PlacedCamera, ...]:
        """The twin cameras ``camera_poses`` places (none: ())."""
        if self.camera_poses is None:
            return ()
        if not Path(self.camera_poses).is_file():
            raise FileNotFoundError(
                f"camera_poses {self.camera_poses!r}: no such file (a rig file's [cameras.NAME] "
                "tables with T_world_camera, docs/cameras.md)"
            )
        return load_camera_poses(self.camera_poses)

    @property
    def mirrors_hardware(self) -> bool:
        return self.hardware != "sim"


def check_real_cameras(cameras: dict[str, object], twin_cameras: list[str]) -> None:
    """Real cameras' names and configs: each a LeRobot ``CameraConfig`` with ``width``,
    ``height`` and ``fps``; a twin camera of a real one's name is observed as ``NAME_twin``,
    which must be no other camera's name. Raises one line naming the camera."""
    for name, config in cameras.items():
        check_camera_name(name, "cameras")
        if not isinstance(config, CameraConfig):
            raise CameraSpecError(
                f"camera {name!r}: {config!r} is not a LeRobot camera config; "
                f"types: {', '.join(sorted(CONFIG_TYPES))}"
            )
        missing = [key for key in ("width", "height", "fps") if getattr(config, key) is None]
        if missing:
            raise CameraSpecError(
                f"camera {name!r}: give {', '.join(missing)} (the dataset declares each image's "
                "shape before the camera opens; a video file's are checked against it)"
            )
    twin_observation_names(twin_cameras, cameras)


def twin_observation_names(twin_cameras: list[str], cameras: dict[str, object]) -> dict[str, str]:
    """Twin camera -> its observation key beside the real ``cameras`` (their depth maps
    ``NAME_depth`` included): ``NAME``, or ``NAME_twin`` where a real camera is ``NAME``."""
    depth = [n + DEPTH_SUFFIX for n, c in cameras.items() if getattr(c, "use_depth", False)]
    return recorded_twin_names(twin_cameras, [*cameras, *depth])
