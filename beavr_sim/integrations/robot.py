"""``--robot.type=beavr_sim``: the xArm7 + LEAP rig or the RX-1 as a LeRobot ``Robot``.

The twin is always there, as the teleop runners' twin stage
(:class:`beavr_sim.teleop.stages.TwinStage` over a ``BeavrEnv``): every action passes its
guard (joint limits, speed and acceleration, workspace, contacts along the path) and its step
limit, and :meth:`BeavrSimRobot.send_action` returns the targets that were actually sent: an
effector whose command the guard refused keeps its last safe target, so what comes back
differs from what went in. Each ``send_action`` is one command to the stage and one step of
one control period (1/fps). With hardware (``emulated`` or a rig file) the
:class:`beavr_sim.hardware.mirror.HardwareMirror` follows the stage through its hooks
(:class:`beavr_sim.teleop.mirroring.MirrorFollower`, the runners' own wiring), so the same
guarded targets go to the devices, and the observation is the devices' measured joints; in
``sim`` it is the twin's. At connect and at each :meth:`BeavrSimRobot.reset_scene` the mirror
is told the episode's start and fixtures (``begin_episode``): its own guard checks every
catch-up against this layout's fixtures, never a previous one's.

Camera images are the twin's renders (``camera_names``; ``camera_poses`` stands them at a
rig file's ``T_world_camera`` poses, as teleop's ``--camera-poses``) and the real cameras'
newest frames (``cameras`` and a rig file's: LeRobot cameras opened at connect through
:class:`beavr_sim.cameras.real.RealCameras`, read on their own threads). A twin camera with a
real camera of its name is observed as ``NAME_twin``; the real one keeps ``NAME``
(:mod:`beavr_sim.cameras.names`, as teleop records them). A real camera that
stops delivering (its newest frame older than ``camera_max_age_s``, or its read thread ended)
makes :meth:`BeavrSimRobot.get_observation` raise one line: a frozen frame is never handed to
the recorder as a live one.

The measured joints are judged as the teleop recorder judges them
(:class:`beavr_sim.datasets.recorder.HardwareWatch`, the rig's own limits): ``get_observation``
raises :class:`~beavr_sim.hardware.device.MeasuredStateError` when a device is not live or the
episode has a fault, and ``send_action`` raises it (after sending: the guarded command is safe)
when the observation it acted on had been away from the commands beyond the rig's window.
``lerobot-record`` then saves none of the frame: the episode in progress is dropped, the ones
saved before it are kept. A frozen or stale measured state is never recorded as live.

Joints the embodiment's effectors do not own (the RX-1's torso and head) hold their pose: their
values in an action are ignored, and the returned action shows the held ones.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from functools import cached_property
from typing import Any

import numpy as np
from lerobot.robots.robot import Robot
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from beavr_sim.cameras.errors import CameraStoppedError
from beavr_sim.cameras.real import DEPTH_SUFFIX, RealCameras
from beavr_sim.datasets.recorder import HardwareWatch
from beavr_sim.envs.beavr_env import BeavrEnv
from beavr_sim.hardware.device import MeasuredStateError
from beavr_sim.integrations.config_robot import (
    ROBOT_TYPE,
    BeavrSimRobotConfig,
    twin_observation_names,
)
from beavr_sim.integrations.joints import action_dict, action_vector, joint_features
from beavr_sim.integrations.options import check_embodiment
from beavr_sim.teleop.mirroring import MirrorFollower, RigChoice, connect_mirror, hardware_watch
from beavr_sim.wire.records import JointCommand

log = logging.getLogger(__name__)

#: The twin's episode length as a robot: it never times out.
_FOREVER_S = 1e9


class BeavrSimRobot(Robot):
    config_class = BeavrSimRobotConfig
    name = ROBOT_TYPE

    def __init__(self, config: BeavrSimRobotConfig):
        super().__init__(config)
        self.config = config
        self.embodiment = check_embodiment(config.embodiment)
        self.joint_names: tuple[str, ...] = self.embodiment.joint_names
        #: The real cameras' LeRobot configs (``cameras`` and a rig file's).
        self.real_camera_configs = config.real_camera_configs()
        #: The twin cameras ``camera_poses`` stands at real cameras' poses (none: ()).
        self.placed_cameras = config.placed_cameras()
        #: Twin camera -> its observation key: ``NAME``, or ``NAME_twin`` beside a real
        #: camera ``NAME`` (``beavr_sim.cameras.names``).
        self.twin_names = twin_observation_names(config.camera_names, self.real_camera_configs)
        #: Observation key -> (height, width), the twin's then the real ones
        #: (``lerobot-record`` counts them).
        self.cameras: dict[str, tuple[int, int]] = {
            **{
                self.twin_names[c]: (config.image_height, config.image_width)
                for c in config.camera_names
            },
            **{n: (int(c.height), int(c.width)) for n, c in self.real_camera_configs.items()},
        }
        #: The real cameras while connected (None without any).
        self.real_cameras: RealCameras | None = None
        self.twin = None
        #: The twin stage every action goes through (None while not connected).
        self.stage = None
        self.mirror = None
        #: The per-frame judge of the measured joints (with hardware; None in sim).
        self.watch: HardwareWatch | None = None
        #: The measured joints the last ``get_observation`` returned (with hardware).
        self._observed: np.ndarray | None = None
        #: The last ``send_action``'s guard outcome (accepted and refused effectors).
        self.last_outcome = None
        self._closers: list[Callable[[], None]] = []
        #: Actions sent since connect, and those with an effector the guard refused.
        self.actions_sent = 0
        self.actions_refused = 0

    def __str__(self) -> str:
        ident = f" {self.id}" if self.id else ""
        return f"beavr_sim robot{ident} ({self.config.embodiment}, {self.config.hardware})"

    # ------------------------------------------------------------------ features
    @cached_property
    def observation_features(self) -> dict[str, Any]:
        cams = {c: (h, w, 3) for c, (h, w) in self.cameras.items()}
        # A depth camera's depth map, its own feature (LeRobot's robots: ``NAME_depth``, HxWx1).
        depth = {
            name + DEPTH_SUFFIX: (int(c.height), int(c.width), 1)
            for name, c in self.real_camera_configs.items()
            if getattr(c, "use_depth", False)
        }
        return {**joint_features(self.joint_names), **cams, **depth}

    @cached_property
    def action_features(self) -> dict[str, type]:
        return joint_features(self.joint_names)

    # ------------------------------------------------------------------ lifecycle
    @property
    def is_connected(self) -> bool:
        return self.twin is not None

    @property
    def is_calibrated(self) -> bool:
        return True  # the drivers carry their calibration (docs/hardware.md)

    def calibrate(self) -> None:
        """Nothing to calibrate here: the drivers convert units in one tested place."""

    def configure(self) -> None:
        """Nothing to configure: the drivers set their modes at connect."""

    def connect(self, calibrate: bool = True) -> None:
        """Open the real cameras (first: one that does not open fails here, naming it, before
        anything else starts), build the twin; with hardware, connect the rig and start the
        twin at the measured pose (nothing moves at connect)."""
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        from beavr_sim.teleop.stages import TwinStage  # local: heavy (the operator: mink)
        from beavr_sim.twin.twin import TwinInterface  # local: heavy (the guard: mink, scipy)

        cfg = self.config
        hand_variant = self._hand_variant()
        self._closers = []
        try:
            if self.real_camera_configs:
                cameras = RealCameras(
                    self.real_camera_configs,
                    control_period_s=1.0 / cfg.fps,
                    dead_after_s=cfg.camera_max_age_s,
                )
                self._closers.append(cameras.close)
                cameras.connect()
                self.real_cameras = cameras
            env = BeavrEnv(
                task=cfg.task,
                embodiment=cfg.embodiment,
                cameras=cfg.camera_names,
                control_hz=float(cfg.fps),
                max_episode_seconds=_FOREVER_S,
                camera_height=cfg.image_height,
                camera_width=cfg.image_width,
                hand_variant=hand_variant,
                placed_cameras=self.placed_cameras,
            )
            self._closers.append(env.close)
            twin = TwinInterface(env, use_guard=cfg.use_guard)
            stage = TwinStage(twin)
            q_measured = None
            if cfg.mirrors_hardware:
                choice = RigChoice(cfg.hardware, cfg.dry_run, cfg.emulate_faults)
                self.mirror, q_measured = connect_mirror(choice, env, self._closers)
                twin.follow_speed_caps(self.mirror.speed_caps)
            stage.reset(cfg.seed, robot_qpos=q_measured)
            if self.mirror is not None:
                self.mirror.start(twin.action)
                MirrorFollower(stage, self.mirror)
                self.watch = hardware_watch(self.mirror, env, cfg.fps)
                self._begin_episode(stage)
        except BaseException:
            self._close_all()
            raise
        self.twin, self.stage = twin, stage
        self.actions_sent = self.actions_refused = 0
        log.info("%s connected (%s, task %s)", self, cfg.hardware, cfg.task)

    def _hand_variant(self) -> str:
        cfg = self.config
        if cfg.mirrors_hardware and cfg.hardware != "emulated":
            from beavr_sim.hardware.rig import RigConfig  # local: heavy (mujoco)

            rig = RigConfig.from_toml(cfg.hardware).leap_variant()
            if rig is not None and cfg.hand_variant not in (None, rig):
                raise ValueError(
                    f"hand_variant {cfg.hand_variant!r} but the rig's LEAP hands are {rig!r}: "
                    "the twin simulates the rig's hands; leave hand_variant out"
                )
            if rig is not None:
                return rig
        return cfg.hand_variant or "full"

    def disconnect(self) -> None:
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        log.info(
            "%s: %d actions sent, %d with a command the guard refused",
            self,
            self.actions_sent,
            self.actions_refused,
        )
        if self.real_cameras is not None:
            for name, stats in self.real_cameras.summary().items():
                log.info("%s: camera %s since connect: %s", self, name, stats)
        self._close_all()

    def _close_all(self) -> None:
        closers, self._closers = self._closers, []
        for close in reversed(closers):
            try:
                close()
            except Exception as exc:  # release everything we can
                log.warning("closing %s: %r", self, exc)
        self.twin = self.stage = self.mirror = self.real_cameras = self.watch = None
        self._observed = None

    # ------------------------------------------------------------------ I/O
    def _require(self):
        if self.twin is None:
            raise DeviceNotConnectedError(f"{self} is not connected: call connect() first")
        return self.twin

    def _begin_episode(self, stage) -> None:
        """Tell the mirror the episode's start (the twin's action after its reset) and its
        fixtures: the devices catch up with the twin there, their path checked against
        this layout."""
        from beavr_sim.hardware.mirror import Fixtures  # local: heavy (the guard: mink, scipy)

        self.mirror.begin_episode(stage.action.copy(), fixtures=Fixtures.of(stage.twin.env.data))
        self.watch.begin()
        self._observed = None

    def measured_positions(self) -> np.ndarray:
        """Measured joints in action order: the devices' with hardware, else the twin's."""
        twin = self._require()
        if self.mirror is not None:
            return self.mirror.latest_measured()
        return twin.env.agent_pos.astype(np.float64)

    def get_observation(self) -> dict[str, Any]:
        """The measured joints (the twin's in sim) and the cameras' images; with hardware,
        raises :class:`MeasuredStateError` (one line) when a device is not live."""
        twin = self._require()
        if self.watch is not None:
            q = self._observe_live(self.watch)
        else:
            q = self.measured_positions()
        obs: dict[str, Any] = action_dict(q, self.joint_names)
        for camera in self.config.camera_names:
            obs[self.twin_names[camera]] = twin.env.render_camera(camera)
        if self.real_cameras is not None:
            obs.update(self._real_frames(self.real_cameras))
        return obs

    def _observe_live(self, watch: HardwareWatch) -> np.ndarray:
        # Before this frame's command: a device holding since the last one (LeRobot saving
        # an episode sends none for a while) stands where it was held, its last reading.
        fault = watch.health_fault(waiting_for_commands=True)
        if fault:
            raise MeasuredStateError(
                f"hardware not live: {fault}; no observation with a frozen measured state is "
                "recorded: check the rig and record again"
            )
        self._observed = watch.observe()
        return self._observed

    def _real_frames(self, cameras: RealCameras) -> dict[str, np.ndarray]:
        """The real cameras' newest frames; raises one line for a camera that stopped."""
        grab = cameras.grab()
        if grab.dead:
            name = grab.dead[0]
            why = (
                "its read thread ended: the camera failed or its video file ended"
                if name in cameras.failed_for_good()
                else f"no frame for over {self.config.camera_max_age_s:g} s"
            )
            raise CameraStoppedError(
                f"camera {name!r} stopped delivering frames ({why}); "
                "no observation with a frozen frame is recorded: check the camera and record again"
            )
        return grab.frames

    def send_action(self, action: dict[str, Any]) -> dict[str, float]:
        """Guard ``action`` (joint name -> target, rad) and send it: one command to the twin
        stage (the guarded targets go to the hardware at once, through its hooks), then one
        step of one period; returns the targets actually sent."""
        twin = self._require()
        target = action_vector(action, self.joint_names)
        nan = math.nan
        commands = {
            e.name: JointCommand(e.name, target[twin.slices[e.name]].copy(), nan, nan)
            for e in self.embodiment.effectors
        }
        outcome = self.stage.command(commands, latency=False)
        sent = twin.action.copy()
        self.stage.step()
        self.last_outcome = outcome
        self.actions_sent += 1
        if outcome.blocked:
            self.actions_refused += 1
            log.warning(
                "guard refused %s: %s",
                ", ".join(outcome.blocked),
                twin.last_refusal.reason() if twin.last_refusal else "",
            )
        self._judge(sent)
        return action_dict(sent, self.joint_names)

    def _judge(self, sent: np.ndarray) -> None:
        """The rig's rule on the observation this action was taken from (the teleop
        recorder's: measured away from the commands in force beyond the window)."""
        if self.watch is None or self._observed is None:
            return
        observed, self._observed = self._observed, None
        fault = self.watch.check(observed, sent)
        if fault:
            raise MeasuredStateError(
                f"measured state untrue: {fault}; this frame is not recorded (the guarded "
                "command was sent): check the rig and record again"
            )

    # ------------------------------------------------------------------ extras
    def reset_scene(self, seed: int | None = None) -> None:
        """A new layout of the task's objects (the robot stays where it is); with hardware,
        the mirror is told this episode's start and fixtures."""
        self._require()
        q = self.measured_positions()
        self.stage.reset(seed, robot_qpos=q)
        if self.mirror is not None:
            self._begin_episode(self.stage)

    def estop(self, reason: str = "emergency stop") -> None:
        """Latch the hardware's emergency stop (every device holds until released)."""
        if self.mirror is not None:
            self.mirror.estop(reason)
