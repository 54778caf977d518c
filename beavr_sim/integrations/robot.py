"""``--robot.type=beavr_sim``: the xArm7 + LEAP rig or the RX-1 as a LeRobot ``Robot``.

The twin (:class:`beavr_sim.twin.twin.TwinInterface` over a ``BeavrEnv``) is always there:
every action passes its guard (joint limits, speed and acceleration, workspace, contacts
along the path) and its step limit, and :meth:`BeavrSimRobot.send_action` returns the
targets that were actually sent: an effector whose command the guard refused keeps its last
safe target, so what comes back differs from what went in. Each ``send_action`` then steps the
twin one control period (1/fps). With hardware (``emulated`` or a rig file) the same guarded
targets go to the devices through :class:`beavr_sim.hardware.mirror.HardwareMirror` (as
``teleop --mirror-hardware`` does) and the observation is the devices' measured joints; in
``sim`` it is the twin's. Camera images are the twin's renders.

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

from beavr_sim.envs.beavr_env import BeavrEnv
from beavr_sim.integrations.config_robot import ROBOT_TYPE, BeavrSimRobotConfig
from beavr_sim.integrations.joints import action_dict, action_vector, joint_features
from beavr_sim.integrations.options import check_embodiment
from beavr_sim.teleop.mirroring import RigChoice, connect_mirror
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
        #: Camera name -> (height, width) (``lerobot-record`` counts them).
        self.cameras: dict[str, tuple[int, int]] = {
            c: (config.image_height, config.image_width) for c in config.camera_names
        }
        self.twin = None
        self.mirror = None
        #: The last ``send_action``'s guard outcome (accepted and refused effectors).
        self.last_outcome = None
        self._closers: list[Callable[[], None]] = []
        self._positions: np.ndarray | None = None  # the twin's joints after its last step
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
        return {**joint_features(self.joint_names), **cams}

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
        """Build the twin; with hardware, connect the rig and start the twin at the measured
        pose (nothing moves at connect)."""
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        from beavr_sim.twin.twin import TwinInterface  # local: heavy (the pipeline: mink, scipy)

        cfg = self.config
        env = BeavrEnv(
            task=cfg.task,
            embodiment=cfg.embodiment,
            cameras=cfg.camera_names,
            control_hz=float(cfg.fps),
            max_episode_seconds=_FOREVER_S,
            camera_height=cfg.image_height,
            camera_width=cfg.image_width,
            hand_variant=self._hand_variant(),
        )
        self._closers = [env.close]
        try:
            twin = TwinInterface(env, use_guard=cfg.use_guard)
            q_measured = None
            if cfg.mirrors_hardware:
                choice = RigChoice(cfg.hardware, cfg.dry_run)
                self.mirror, q_measured = connect_mirror(choice, env, self._closers)
                twin.follow_speed_caps(self.mirror.speed_caps)
            twin.reset(cfg.seed, robot_qpos=q_measured)
            if self.mirror is not None:
                self.mirror.start(twin.action)
        except BaseException:
            self._close_all()
            raise
        self.twin = twin
        self.actions_sent = self.actions_refused = 0
        self._positions = env.agent_pos.astype(np.float64)
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
        self._close_all()

    def _close_all(self) -> None:
        closers, self._closers = self._closers, []
        for close in reversed(closers):
            try:
                close()
            except Exception as exc:  # release everything we can
                log.warning("closing %s: %r", self, exc)
        self.twin = self.mirror = None

    # ------------------------------------------------------------------ I/O
    def _require(self):
        if self.twin is None:
            raise DeviceNotConnectedError(f"{self} is not connected: call connect() first")
        return self.twin

    def measured_positions(self) -> np.ndarray:
        """Measured joints in action order: the devices' with hardware, else the twin's."""
        twin = self._require()
        if self.mirror is not None:
            return self.mirror.latest_measured()
        return twin.env.agent_pos.astype(np.float64)

    def get_observation(self) -> dict[str, Any]:
        twin = self._require()
        obs: dict[str, Any] = action_dict(self.measured_positions(), self.joint_names)
        for camera in self.cameras:
            obs[camera] = twin.env.render_camera(camera)
        return obs

    def send_action(self, action: dict[str, Any]) -> dict[str, float]:
        """Guard ``action`` (joint name -> target, rad), send it (twin, and hardware), step
        the twin one period; returns the targets actually sent."""
        twin = self._require()
        target = action_vector(action, self.joint_names)
        nan = math.nan
        commands = {
            e.name: JointCommand(e.name, target[twin.slices[e.name]].copy(), nan, nan)
            for e in self.embodiment.effectors
        }
        outcome = twin.command(commands)
        sent = twin.action.copy()
        if self.mirror is not None:
            self.mirror.submit(sent, self._positions, outcome.blocked)
        state = twin.step()
        self._positions = state.positions
        self.last_outcome = outcome
        self.actions_sent += 1
        if outcome.blocked:
            self.actions_refused += 1
            log.warning(
                "guard refused %s: %s",
                ", ".join(outcome.blocked),
                twin.last_refusal.reason() if twin.last_refusal else "",
            )
        return action_dict(sent, self.joint_names)

    # ------------------------------------------------------------------ extras
    def reset_scene(self, seed: int | None = None) -> None:
        """A new layout of the task's objects (the robot stays where it is)."""
        twin = self._require()
        q = self.measured_positions()
        twin.reset(seed, robot_qpos=q)
        self._positions = twin.env.agent_pos.astype(np.float64)

    def estop(self, reason: str = "emergency stop") -> None:
        """Latch the hardware's emergency stop (every device holds until released)."""
        if self.mirror is not None:
            self.mirror.estop(reason)
