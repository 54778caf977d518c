"""What a beavr_sim LeRobot dataset holds: one :class:`RecordingConfig`, one feature dict.

Features (``docs/formats.md`` lists them with shapes):

- ``observation.state``: measured joint positions (rad), per effector arm then hand, as the env's
  ``agent_pos``; names are the joint names;
- ``action``: the joint targets actually commanded to the twin (after clipping), same order;
- ``observation.environment_state`` (only with ``RecordingConfig.environment_state``): the
  task's object and target poses, privileged state for state-based policies; off by default
  because ``lerobot-train`` feeds every ``observation.*`` feature to the policy;
- ``observation.images.<camera>``: the twin's cameras (``front``, ``overhead``, a robot's own,
  or one ``--camera-poses`` places: ``RecordingConfig.placed_cameras``), HxWx3 video; and the
  real cameras (``real_cameras``), their names kept as given (case too; two names differing
  only in case are refused: their folders would collide on a case-insensitive file system);
  a twin camera with a real camera of its name is recorded as ``<camera>_twin``
  (:mod:`beavr_sim.cameras.names`: the real camera keeps the plain name);
  a real camera's depth (``<camera>_depth``, HxWx1 uint16 millimetres) is flagged
  ``info.is_depth_map`` as LeRobot does for one-channel camera features;
- ``observation.images.<camera>_depth`` (only for ``RecordingConfig.depth_cameras``): the twin
  camera's depth, HxWx1 float32 metres, flagged ``info.is_depth_map`` as LeRobot's RealSense
  depth features (``<camera>_depth``, ``(H, W, 1)``), so sim and RGB-D rig datasets match;
- ``hand.keypoints``: the raw tracked hand joints of every side the embodiment uses (26 XR Hands
  joints x 3, metres, right-handed Z-up world frame), and ``hand.tracked`` (1 tracked, 0 not),
  so that retargeting can be redone later. They do not start with ``observation.``, so LeRobot
  policies do not take them as inputs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from beavr_sim.cameras.names import recorded_twin_names
from beavr_sim.envs.scene import ALL_CAMERA_NAMES
from beavr_sim.naming import check_name
from beavr_sim.robots import Embodiment
from beavr_sim.wire.hand import JOINT_NAMES, N_JOINTS

STATE = "observation.state"
ENV_STATE = "observation.environment_state"
ACTION = "action"
IMAGE_PREFIX = "observation.images."
#: LeRobot's suffix for a camera's depth feature (``observation.images.<camera>_depth``).
DEPTH_SUFFIX = "_depth"
KEYPOINTS = "hand.keypoints"
TRACKED = "hand.tracked"


#: The smallest image width and height LeRobot's video encoder (SVT-AV1, as LeRobot configures
#: it) is given here. Measured on 2026-12-05: widths of 24 and below kill the process (SIGFPE,
#: no exception), 25 and up encode; heights of 2 and below raise, 4 encodes. The width keeps a
#: margin above what was seen to work.
MIN_VIDEO_WIDTH = 32
MIN_VIDEO_HEIGHT = 8


def check_video_size(height: int, width: int) -> None:
    """Raise ValueError for an image size the video encoder cannot take (one it would crash
    on, not raise)."""
    if width < MIN_VIDEO_WIDTH or height < MIN_VIDEO_HEIGHT:
        raise ValueError(
            f"image size {height}x{width} (HxW) is too small to record as video: LeRobot's AV1 "
            f"encoder needs a width of at least {MIN_VIDEO_WIDTH} and a height of at least "
            f"{MIN_VIDEO_HEIGHT}; pass a larger --image-size, or --no-videos to store PNG frames"
        )


@dataclass(frozen=True)
class RecordingConfig:
    """How episodes are recorded (one per dataset; validated here)."""

    fps: int = 30
    cameras: tuple[str, ...] = ("front", "overhead")
    #: Twin cameras of other names placed in the scene (``--camera-poses``' tables with a
    #: ``T_world_camera``): recordable in ``cameras`` and ``depth_cameras`` too.
    placed_cameras: tuple[str, ...] = ()
    #: Twin cameras whose depth is recorded too (``--cameras front,front:depth``).
    depth_cameras: tuple[str, ...] = ()
    image_height: int = 480
    image_width: int = 640
    hand_keypoints: bool = True
    #: Seconds after which an episode ends if the task has not succeeded (None: the env's limit).
    episode_seconds: float | None = None
    #: Ticks recorded after success, so the data shows the settled outcome.
    tail_seconds: float = 0.5
    #: Encode images as video (LeRobot's default) or store PNG frames.
    use_videos: bool = True
    #: Also record the task's object and target poses (privileged state).
    environment_state: bool = False

    def __post_init__(self) -> None:
        if not (isinstance(self.fps, int) and self.fps > 0):
            raise ValueError(f"fps must be a positive integer, got {self.fps!r}")
        object.__setattr__(self, "placed_cameras", tuple(self.placed_cameras))
        recordable = tuple(dict.fromkeys(ALL_CAMERA_NAMES + self.placed_cameras))
        object.__setattr__(self, "cameras", tuple(self.cameras))
        for camera in self.cameras:
            check_name("camera", camera, recordable)
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras repeat: {self.cameras}")
        object.__setattr__(self, "depth_cameras", tuple(self.depth_cameras))
        for camera in self.depth_cameras:
            check_name("depth camera", camera, recordable)
        if len(set(self.depth_cameras)) != len(self.depth_cameras):
            raise ValueError(f"depth cameras repeat: {self.depth_cameras}")
        if self.image_height <= 0 or self.image_width <= 0:
            raise ValueError(
                f"image size must be positive, got {self.image_height}x{self.image_width}"
            )
        if self.use_videos and (self.cameras or self.depth_cameras):
            check_video_size(self.image_height, self.image_width)
        if self.episode_seconds is not None and not self.episode_seconds > 0:
            raise ValueError(f"episode_seconds must be positive, got {self.episode_seconds!r}")
        if not self.tail_seconds >= 0:
            raise ValueError(f"tail_seconds must be >= 0, got {self.tail_seconds!r}")


def _check_case_distinct(camera: str, features: Mapping[str, dict]) -> None:
    """A camera's name is recorded as given (``observation.images.Front``), but two image
    features whose names differ only in case would share a folder on a case-insensitive file
    system (macOS, Windows): refused, naming both."""
    for key in features:
        if key.startswith(IMAGE_PREFIX) and key.casefold() == (IMAGE_PREFIX + camera).casefold():
            other = key.removeprefix(IMAGE_PREFIX)
            raise ValueError(
                f"camera {camera!r} and {other!r} differ only in case (their dataset folders "
                "collide on case-insensitive file systems); rename one"
            )


def hand_sides(embodiment: Embodiment) -> tuple[str, ...]:
    """The hand sides an embodiment's operator tracks, in effector order."""
    return tuple(dict.fromkeys(e.side for e in embodiment.effectors))


def lerobot_features(
    embodiment: Embodiment,
    config: RecordingConfig,
    environment_state_names: Sequence[str] = (),
    real_cameras: Mapping[str, tuple[int, int, int]] | None = None,
) -> dict[str, dict]:
    """LeRobot feature dict (``LeRobotDataset.create(features=...)``) for this embodiment;
    ``environment_state_names`` (the env's) are needed when the config records that state;
    ``real_cameras``: real cameras' frame shapes by name, recorded next to the twin's renders."""
    joints = list(embodiment.joint_names)
    features: dict[str, dict] = {
        STATE: {"dtype": "float32", "shape": (len(joints),), "names": joints},
        ACTION: {"dtype": "float32", "shape": (len(joints),), "names": joints},
    }
    if config.environment_state:
        if not environment_state_names:
            raise ValueError(
                "environment_state recording needs the env's environment_state_names "
                "(this task has no object state)"
            )
        names = list(environment_state_names)
        features[ENV_STATE] = {"dtype": "float32", "shape": (len(names),), "names": names}
    # A twin camera with a real namesake is recorded as NAME_twin (the real one keeps NAME).
    twin = recorded_twin_names(config.cameras + config.depth_cameras, real_cameras or {})
    for camera in config.cameras:
        features[IMAGE_PREFIX + twin[camera]] = {
            "dtype": "video" if config.use_videos else "image",
            "shape": (config.image_height, config.image_width, 3),
            "names": ["height", "width", "channels"],
        }
    for camera in config.depth_cameras:
        features[IMAGE_PREFIX + twin[camera] + DEPTH_SUFFIX] = {
            "dtype": "video" if config.use_videos else "image",
            "shape": (config.image_height, config.image_width, 1),
            "names": ["height", "width", "channels"],
            "info": {"is_depth_map": True},
        }
    for camera, shape in (real_cameras or {}).items():
        key = IMAGE_PREFIX + camera
        if key in features:
            raise ValueError(
                f"camera {camera!r} is both a twin camera or depth (--cameras) and a real one"
            )
        _check_case_distinct(camera, features)
        features[key] = {
            "dtype": "video" if config.use_videos else "image",
            "shape": tuple(shape),
            "names": ["height", "width", "channels"],
        }
        if len(shape) == 3 and shape[2] == 1:  # LeRobot's rule: one channel is a depth map
            features[key]["info"] = {"is_depth_map": True}
    if config.hand_keypoints:
        sides = hand_sides(embodiment)
        features[KEYPOINTS] = {
            "dtype": "float32",
            "shape": (len(sides) * N_JOINTS * 3,),
            "names": [f"{s}/{j}/{a}" for s in sides for j in JOINT_NAMES for a in "xyz"],
        }
        features[TRACKED] = {
            "dtype": "float32",
            "shape": (len(sides) * N_JOINTS,),
            "names": [f"{s}/{j}" for s in sides for j in JOINT_NAMES],
        }
    return features
