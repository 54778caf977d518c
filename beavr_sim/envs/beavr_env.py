"""The one gymnasium env of beavr_sim, parameterised by task and embodiment.

Observations follow LeRobot's gym-env convention: ``agent_pos`` (measured joint positions,
per effector arm then hand, float32), ``environment_state`` (the task's object and target
poses, float32: privileged state, names in ``env.environment_state_names``) and, when cameras
are on, ``pixels`` (camera name -> HxWx3 uint8). Actions are joint position targets in the same order. ``terminated`` means
task success or failure, ``truncated`` the time limit; ``info["is_success"]`` is always set.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from beavr_sim.envs.camera_pose import PlacedCamera
from beavr_sim.envs.cameras import OffscreenCameras
from beavr_sim.envs.drive import InterpolatedServo
from beavr_sim.envs.scene import (
    DEFAULT_CONTACT,
    DEFAULT_HAND_VARIANT,
    ContactSettings,
    build_scene_spec,
    camera_names,
    check_hand_variant,
)
from beavr_sim.naming import check_name
from beavr_sim.robots import Embodiment, make_embodiment
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT, embodiment_layout
from beavr_sim.tasks.base import Task, TaskStatus
from beavr_sim.tasks.registry import task_class

#: Largest physics step; the env picks the largest step <= this that divides the control period.
MAX_PHYSICS_DT = 0.002
RENDER_MODES = ("rgb_array",)


#: The env's control rate (Hz) unless one is given: the runners' operator commands at it.
DEFAULT_CONTROL_HZ = 30.0


class BeavrEnv(gym.Env):
    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 30}

    def __init__(
        self,
        task: str = "Playground",
        embodiment: str = DEFAULT_EMBODIMENT,
        render_mode: str | None = None,
        cameras: Sequence[str] | None = None,
        control_hz: float = DEFAULT_CONTROL_HZ,
        max_episode_seconds: float | None = None,
        camera_height: int = 480,
        camera_width: int = 640,
        hand_variant: str = DEFAULT_HAND_VARIANT,
        contact: ContactSettings | None = None,
        placed_cameras: Sequence[PlacedCamera] = (),
    ):
        """``hand_variant``: the hands' hardware variant (LEAP: ``"full"`` or ``"lite"``); it
        sets their finger joints' torque cap (docs/models.md, "LEAP servos"). ``contact``: the
        scene's contact options (friction cone, impratio; default :data:`DEFAULT_CONTACT`).
        ``placed_cameras``: twin cameras at real cameras' poses (a rig file's
        ``[cameras.NAME]`` poses; :mod:`beavr_sim.envs.camera_pose`): a fixed camera of the
        same name moves there, other names are added to the scene's cameras."""
        super().__init__()
        if render_mode is not None:
            check_name("render_mode", render_mode, RENDER_MODES)
        self.render_mode = render_mode
        self.embodiment: Embodiment = make_embodiment(embodiment)
        self.hand_variant = check_hand_variant(self.embodiment, hand_variant)
        self.placed_cameras = tuple(placed_cameras)
        placed_names = [c.name for c in self.placed_cameras]
        if len(set(placed_names)) != len(placed_names):
            raise ValueError(f"placed cameras repeat a name: {placed_names}")
        valid_cameras = tuple(dict.fromkeys(camera_names(self.embodiment) + tuple(placed_names)))
        self.cameras = tuple(
            check_name("camera", c, valid_cameras, f"for embodiment {embodiment}")
            for c in (cameras or ())
        )
        if not (math.isfinite(control_hz) and control_hz > 0):
            raise ValueError(f"control_hz must be a positive number, got {control_hz!r}")
        if camera_height <= 0 or camera_width <= 0:
            raise ValueError(f"camera size must be positive, got {camera_height}x{camera_width}")
        self.camera_height, self.camera_width = int(camera_height), int(camera_width)

        self.task: Task = task_class(task)(self.embodiment)
        if self.task.embodiments is not None:
            # A robot file's robot runs the tasks of the built-in with its effectors.
            layout = embodiment_layout(self.embodiment.spec) or embodiment
            check_name("embodiment", layout, self.task.embodiments, f"for task {task}")
        self.max_episode_seconds = float(
            self.task.max_episode_seconds if max_episode_seconds is None else max_episode_seconds
        )
        if not self.max_episode_seconds > 0:
            raise ValueError(f"max_episode_seconds must be positive, got {max_episode_seconds!r}")

        self._contact = DEFAULT_CONTACT if contact is None else contact
        spec = self._scene_spec(visuals=False)
        self.control_hz = float(control_hz)
        self.n_substeps = max(1, math.ceil(1.0 / (self.control_hz * MAX_PHYSICS_DT)))
        #: Called (no arguments) after each physics substep of :meth:`step`, or None: the
        #: event-driven twin takes the commands that arrive meanwhile there, so a control
        #: period of physics never holds a command up by more than a substep. It must not
        #: change the env's state (it may read it).
        self.between_substeps: Callable[[], None] | None = None
        spec.option.timestep = 1.0 / (self.control_hz * self.n_substeps)
        #: The physics model: collision geometry only. The robots' visual geometry lives in
        #: :attr:`render_model` (same bodies, joints and state layout): visual geoms never
        #: collide, but in the model that steps they still cost MuJoCo's collision phase about
        #: a fifth of a physics step.
        self.model: mujoco.MjModel = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._render_model: mujoco.MjModel | None = None
        self._render_data: mujoco.MjData | None = None
        self.joints = self.embodiment.bind(self.model)
        self.task.bind(self.model)
        # The arm joints that follow targets as a servo-mode arm does (envs/drive.py); the
        # other joints get each target straight on their position actuators.
        servo_index, v_max, a_max = self.embodiment.servo_joints()
        self._servo_index = servo_index
        self._servo: InterpolatedServo | None = None
        if len(servo_index):
            self._servo = InterpolatedServo(
                self.model,
                self.joints.actuator_ids[servo_index],
                self.joints.qvel_adr[servo_index],
                v_max,
                a_max,
                period=1.0 / self.control_hz,
                n_substeps=self.n_substeps,
            )
        self.metadata = {**self.metadata, "render_fps": self.control_hz}

        n = self.joints.size
        self.action_space = spaces.Box(
            low=self.joints.lower.astype(np.float32),
            high=self.joints.upper.astype(np.float32),
            dtype=np.float32,
        )
        obs_spaces: dict[str, spaces.Space] = {
            "agent_pos": spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32)
        }
        self.environment_state_names = self.task.state_names
        if self.environment_state_names:
            obs_spaces["environment_state"] = spaces.Box(
                -np.inf, np.inf, shape=(len(self.environment_state_names),), dtype=np.float32
            )
        if self.cameras:
            obs_spaces["pixels"] = spaces.Dict(
                {
                    c: spaces.Box(
                        0, 255, shape=(self.camera_height, self.camera_width, 3), dtype=np.uint8
                    )
                    for c in self.cameras
                }
            )
        self.observation_space = spaces.Dict(obs_spaces)
        self._renderer: OffscreenCameras | None = None
        self._elapsed_steps = 0
        self._status = TaskStatus()
        self.target = self.joints.home.astype(np.float64).copy()

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        start = self.joints.home
        if options and options.get("robot_qpos") is not None:
            # Start where a mirrored robot stands (teleop --mirror-hardware), not at home.
            start = np.asarray(options["robot_qpos"], dtype=np.float64)
            if start.shape != (self.joints.size,) or not np.isfinite(start).all():
                raise ValueError(
                    f"options['robot_qpos'] needs {self.joints.size} finite joint positions "
                    f"(agent_pos order), got shape {start.shape}"
                )
            start = np.clip(start, self.joints.lower, self.joints.upper)
        self.data.qpos[self.joints.qpos_adr] = start
        self.data.ctrl[self.joints.actuator_ids] = start
        #: The joint targets of the last step, clipped to the joint ranges (action order).
        self.target = np.array(start, dtype=np.float64)
        if self._servo is not None:
            self._servo.reset(start[self._servo_index])
        self.task.initialize_episode(self.model, self.data, self.np_random)
        mujoco.mj_forward(self.model, self.data)
        self._elapsed_steps = 0
        self._status = self.task.evaluate(self.model, self.data)
        return self._observation(), self._info(clipped=())

    def step(self, action):
        terminated, truncated, info = self.advance(action)
        return self._observation(), 0.0 + float(self._status.success), terminated, truncated, info

    def advance(self, action) -> tuple[bool, bool, dict[str, Any]]:
        """:meth:`step` without building the observation: ``(terminated, truncated, info)``.

        For callers that read the state themselves (the twin): the observation's task state
        and camera images are work they would throw away."""
        target = self._validate_action(action)
        clipped_target = np.clip(target, self.joints.lower, self.joints.upper)
        clipped = tuple(self.joints.names[i] for i in np.flatnonzero(clipped_target != target))
        self.data.ctrl[self.joints.actuator_ids] = clipped_target
        self.target = clipped_target
        servo = self._servo
        if servo is not None:
            servo.begin_period(clipped_target[self._servo_index])
        hook = self.between_substeps
        if hook is None and (servo is None or servo.at_rest):
            mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
        elif servo is None or servo.at_rest:
            for _ in range(self.n_substeps):
                mujoco.mj_step(self.model, self.data)
                hook()
        else:
            ctrl, ids = self.data.ctrl, servo.actuator_ids
            for row in servo.period_controls():
                ctrl[ids] = row
                mujoco.mj_step(self.model, self.data)
                if hook is not None:
                    hook()
        self._elapsed_steps += 1
        self._status = self.task.evaluate(self.model, self.data)
        terminated = bool(self._status.success or self._status.failure)
        truncated = bool(self.elapsed_seconds >= self.max_episode_seconds - 1e-9) and not terminated
        return terminated, truncated, self._info(clipped)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self.render_camera(self.cameras[0] if self.cameras else "front")

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ helpers
    @property
    def elapsed_seconds(self) -> float:
        return self._elapsed_steps / self.control_hz

    @property
    def agent_pos(self) -> np.ndarray:
        return self.data.qpos[self.joints.qpos_adr].astype(np.float32)

    @property
    def environment_state(self) -> np.ndarray:
        """The task's object and target poses (names in ``environment_state_names``)."""
        return self.task.state(self.data).astype(np.float32)

    def render_camera(self, camera: str) -> np.ndarray:
        """One HxWx3 uint8 frame from a named camera (shadows and reflections off)."""
        if self._renderer is None:
            self._renderer = OffscreenCameras(
                self.render_model, self.camera_height, self.camera_width
            )
        return self._renderer.render(self.render_data(), camera)

    @property
    def render_model(self) -> mujoco.MjModel:
        """The twin as it is drawn: :attr:`model` plus the robots' visual geometry (group 2;
        collision geometry in group 3), compiled on first use. Its bodies, joints, mocap
        bodies and cameras are :attr:`model`'s, index for index, so body poses and ``qpos``
        carry over; its geom ids do not. Draw with it, never step it."""
        if self._render_model is None:
            spec = self._scene_spec(visuals=True)
            spec.option.timestep = self.model.opt.timestep
            model = spec.compile()
            for size in ("nbody", "nq", "nv", "nmocap", "ncam", "njnt"):
                if getattr(model, size) != getattr(self.model, size):
                    raise RuntimeError(
                        f"the render model's {size} ({getattr(model, size)}) differs from the "
                        f"physics model's ({getattr(self.model, size)}): visuals must add geoms "
                        "and meshes only"
                    )
            self._render_model, self._render_data = model, mujoco.MjData(model)
        return self._render_model

    def render_data(self, data: mujoco.MjData | None = None) -> mujoco.MjData:
        """:attr:`render_model`'s data at the state of ``data`` (default: :attr:`data`):
        positions and mocap poses copied, kinematics, cameras and lights recomputed (no
        collision, no dynamics). One shared instance: call from one thread."""
        model = self.render_model
        out, src = self._render_data, self.data if data is None else data
        out.time = src.time
        out.qpos[:] = src.qpos
        out.mocap_pos[:] = src.mocap_pos
        out.mocap_quat[:] = src.mocap_quat
        mujoco.mj_kinematics(model, out)
        mujoco.mj_comPos(model, out)
        mujoco.mj_camlight(model, out)
        return out

    def _scene_spec(self, visuals: bool) -> mujoco.MjSpec:
        spec = build_scene_spec(
            self.embodiment,
            self.camera_height,
            self.camera_width,
            self.hand_variant,
            self._contact,
            visuals=visuals,
            placed_cameras=self.placed_cameras,
        )
        self.task.build(spec)
        return spec

    def _validate_action(self, action) -> np.ndarray:
        expected = self.action_space.shape
        try:
            target = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"action must be a numeric array of shape {expected}, got {type(action).__name__}"
            ) from exc
        if target.shape != expected:
            raise ValueError(
                f"action has shape {target.shape}, expected {expected}: joint targets for "
                f"{', '.join(e.name + ' (' + str(len(e.joints)) + ')' for e in self.embodiment.effectors)}"
            )
        if not np.all(np.isfinite(target)):
            bad = [self.joints.names[i] for i in np.flatnonzero(~np.isfinite(target))]
            raise ValueError(f"action of shape {expected} has NaN/inf targets for joints {bad}")
        return target

    def _observation(self) -> dict[str, Any]:
        obs: dict[str, Any] = {"agent_pos": self.agent_pos}
        if self.environment_state_names:
            obs["environment_state"] = self.environment_state
        if self.cameras:
            obs["pixels"] = {c: self.render_camera(c) for c in self.cameras}
        return obs

    def _info(self, clipped: tuple[str, ...]) -> dict[str, Any]:
        return {
            "is_success": bool(self._status.success),
            "is_failure": bool(self._status.failure),
            "task": self.task.name,
            "embodiment": self.embodiment.name,
            "elapsed_seconds": self.elapsed_seconds,
            "action_clipped": bool(clipped),
            "clipped_joints": clipped,
            **{f"task/{k}": v for k, v in self._status.details.items()},
        }
