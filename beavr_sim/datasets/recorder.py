"""Teleop ticks -> LeRobot frames: the recorder listens to the teleop loop.

A LeRobot frame pairs an observation with the action taken from it. The loop reports each tick
after the twin stepped, so the recorder keeps the observation made before the step (measured
joints and camera images) and, at the tick, writes it with the action the twin was actually
given (:attr:`TwinState.action`: the operator's targets after the twin's composition; holds
included). Hand keypoints are the newest frame of each side up to that tick.

Episodes: :meth:`EpisodeRecorder.begin` after the env reset, :meth:`EpisodeRecorder.end` with
keep or drop. A summary line per episode goes to ``meta/beavr_episodes.jsonl`` beside LeRobot's
metadata (seed, success, duration, source): LeRobot has no field for them.

Mirrored hardware (``observation.state`` measured by the devices): a :class:`HardwareWatch`
checks every frame that every device is live and that the measured joints follow the command
(within the rig's divergence limits for no longer than its window); the age of the oldest
device reading behind each frame's state is kept (``max_state_age_s``). The first fault is kept in
:attr:`EpisodeRecorder.fault` (the session ends the episode on it) and written as the episode's
``hardware_fault`` in ``meta/beavr_episodes.jsonl``: an episode whose measured state froze or
stayed away from the commands beyond the window is never recorded as if it were live.

Real cameras (:class:`~beavr_sim.cameras.RealCameras`, capturing on LeRobot's read threads):
each observation takes every camera's newest frame as ``observation.images.NAME``; frames older
than 1.5 control periods are counted per camera (``cameras`` in ``meta/beavr_episodes.jsonl``),
and a camera that stops delivering is the episode's hardware fault (its frame is not written).
A twin camera with a real camera of its name is written as ``observation.images.NAME_twin``
(:mod:`beavr_sim.cameras.names`).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.cameras.names import recorded_twin_names
from beavr_sim.datasets.features import (
    ACTION,
    DEPTH_SUFFIX,
    ENV_STATE,
    IMAGE_PREFIX,
    KEYPOINTS,
    STATE,
    TRACKED,
    RecordingConfig,
    hand_sides,
)
from beavr_sim.datasets.writer import EpisodeWriter, append_log_line
from beavr_sim.envs.cameras import OffscreenCameras
from beavr_sim.robots.identity import embodiment_label
from beavr_sim.wire.hand import N_JOINTS, HandFrame
from beavr_sim.wire.records import Tick, TwinState


class CameraSet:
    """The recorded cameras, rendered together at the recording size; ``depth``: cameras
    whose depth (metres, HxWx1 float32) is rendered too."""

    def __init__(
        self,
        model: mujoco.MjModel | None,
        cameras: tuple[str, ...],
        height: int,
        width: int,
        depth: tuple[str, ...] = (),
    ):
        self.cameras = tuple(cameras)
        self.depth = tuple(depth)
        if (self.cameras or self.depth) and model is None:
            raise ValueError(f"cameras {self.cameras + self.depth} need a model to render")
        drawn = self.cameras or self.depth
        self._cameras = OffscreenCameras(model, height, width) if drawn else None

    @classmethod
    def of_env(
        cls, env, cameras: tuple[str, ...], height: int, width: int, depth: tuple[str, ...] = ()
    ) -> CameraSet:
        """The cameras of a :class:`~beavr_sim.envs.beavr_env.BeavrEnv`, drawing its render
        model (compiled only if there is a camera)."""
        return cls(env.render_model if cameras or depth else None, cameras, height, width, depth)

    def render(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        return {c: self._cameras.render(data, c) for c in self.cameras}

    def render_depth(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        return {c: self._cameras.render_depth(data, c) for c in self.depth}

    def render_env(self, env) -> dict[str, np.ndarray]:
        """Every camera at ``env``'s current state (its render model's data)."""
        return self.render(env.render_data()) if self.cameras else {}

    def render_env_depth(self, env) -> dict[str, np.ndarray]:
        """Every depth camera at ``env``'s current state."""
        return self.render_depth(env.render_data()) if self.depth else {}

    def close(self) -> None:
        if self._cameras is not None:
            self._cameras.close()


@dataclass(frozen=True)
class FollowLimits:
    """How far a mirrored rig's measured joints may be from the command, per joint (action
    order; ``inf`` for a joint no device measures), and for how long (the rig's
    ``MirrorConfig.divergence_window_s``) before the frame is untrue. ``lag_s``: a device
    trails its commands (``MirrorConfig.device_lag_s``); a measured joint is judged against
    the commands of that last stretch (between the lowest and highest of them), as the
    mirror judges a device against the targets it sent."""

    limit_rad: np.ndarray
    window_s: float
    joint_names: tuple[str, ...]
    lag_s: float = 0.0

    def __post_init__(self) -> None:
        if len(self.joint_names) != len(self.limit_rad):
            raise ValueError(
                f"{len(self.limit_rad)} limits for {len(self.joint_names)} joints: one per joint"
            )
        if not (np.all(self.limit_rad > 0) and self.window_s >= 0 and self.lag_s >= 0):
            raise ValueError("divergence limits must be positive, the window and lag >= 0")


def _live_or_waiting(device) -> bool:
    """Following, catching up, or holding for want of a fresh command."""
    state, reason = device.state.name, getattr(device.reason, "name", device.reason)
    return state in ("FOLLOWING", "CATCHING_UP") or (state == "HOLDING" and reason == "TIMEOUT")


def _not_live(devices: Sequence) -> str:
    """The devices of a health snapshot that are not following, as one line."""
    parts = []
    for device in devices:
        kind = device.state.name
        if kind not in ("FOLLOWING", "CATCHING_UP"):
            detail = device.detail
            parts.append(f"{device.name} {kind.lower()}" + (f" ({detail})" if detail else ""))
    return "; ".join(parts) or "a device was not live"


class HardwareWatch:
    """Per recorded frame: is the measured state true? (See the module docstring.)

    ``reading``: the devices' measured joints and when the oldest of them was read
    (``HardwareMirror.latest_reading``: ``.q``, ``.t_oldest``, ``.oldest``); :meth:`observe`
    takes one as a frame's ``observation.state`` and keeps the oldest reading's age over the
    episode (:attr:`max_reading_age_s`: reported, not judged; a device in a command-timeout
    hold is not read, so a loaded machine's stalls age its reading while it stands still).

    ``health``: the mirror's cheap snapshot (``HardwareMirror.health``: ``.live``,
    ``.devices``: each ``.name``, ``.state`` (an enum: ``FOLLOWING``, ``CATCHING_UP``, ...),
    ``.detail``; ``.episode_faults``). The measured state of a frame
    (read before the tick) is compared with the commands in force when it was read (the
    previous frames' actions within the lag; the first frame's own)."""

    def __init__(
        self,
        reading: Callable[[], object],
        health: Callable[[], object],
        limits: FollowLimits,
        fps: float,
    ):
        self.reading = reading
        self.health = health
        self.limits = limits
        self.fps = float(fps)
        self.fault = ""
        self.max_gap_rad = 0.0
        #: The oldest reading's age (s) behind the episode's frames so far.
        self.max_reading_age_s = 0.0
        self._recent: deque[np.ndarray] = deque(maxlen=max(1, math.ceil(limits.lag_s * fps)))
        self._diverged_frames = 0

    def observe(self, now: float | None = None) -> np.ndarray:
        """The measured joints for a frame's ``observation.state`` (their reading's age
        kept)."""
        reading = self.reading()
        now = time.monotonic() if now is None else now
        self.max_reading_age_s = max(self.max_reading_age_s, float(reading.age_s(now)))
        return np.asarray(reading.q, dtype=np.float64)

    def begin(self) -> None:
        self.fault = ""
        self.max_gap_rad = 0.0
        self.max_reading_age_s = 0.0
        self._recent.clear()
        self._diverged_frames = 0

    def health_fault(self, *, waiting_for_commands: bool = False) -> str:
        """The rig's fault now, as one line ("" while every device is live and this
        episode has no fault): the first of its episode's faults, else the devices not live.

        ``waiting_for_commands``: a device holding for want of a fresh command (a
        command-timeout hold: the caller sent none for a while, e.g. LeRobot saving an
        episode) counts as live: it stands where it was held, its last reading."""
        health = self.health()
        faults = tuple(getattr(health, "episode_faults", ()))
        if faults:
            return faults[0]
        if health.live or (
            waiting_for_commands and all(_live_or_waiting(d) for d in health.devices)
        ):
            return ""
        return _not_live(health.devices)

    def check(self, state: np.ndarray, action: np.ndarray) -> str:
        """The frame's fault ("" when it is true); the first one is kept in :attr:`fault`."""
        fault = self.health_fault()
        if self._recent:
            asked = np.stack(self._recent)
            low, high = asked.min(axis=0), asked.max(axis=0)
        else:
            low = high = np.asarray(action, dtype=np.float64)
        self._recent.append(np.array(action, dtype=np.float64))
        measured = np.asarray(state, dtype=np.float64)
        gap = np.maximum(np.maximum(low - measured, measured - high), 0.0)
        over = gap > self.limits.limit_rad
        finite = np.isfinite(self.limits.limit_rad)
        if finite.any():
            self.max_gap_rad = max(self.max_gap_rad, float(np.max(gap[finite])))
        self._diverged_frames = self._diverged_frames + 1 if over.any() else 0
        if not fault and self._diverged_frames / self.fps > self.limits.window_s:
            j = int(np.argmax(np.where(over, gap - self.limits.limit_rad, -np.inf)))
            fault = (
                f"measured {self.limits.joint_names[j]} {gap[j]:.3f} rad from the commands for "
                f"{self._diverged_frames / self.fps:.2f} s (limit {self.limits.limit_rad[j]:g} "
                "rad)"
            )
        if fault and not self.fault:
            self.fault = fault
        return fault


class EpisodeRecorder:
    """A teleop-loop listener writing the ticks of each episode as LeRobot frames."""

    def __init__(
        self,
        writer: EpisodeWriter,
        env,
        config: RecordingConfig,
        watch: HardwareWatch | None = None,
        real_cameras=None,
    ):
        self.writer = writer
        self.env = env
        self.config = config
        #: Mirrored hardware: ``observation.state`` is the devices' measured joints
        #: (:meth:`HardwareWatch.observe`) and every frame is checked true; without it, the
        #: twin's joints.
        self.watch = watch
        #: Real cameras (:class:`~beavr_sim.cameras.RealCameras`), already connected, or None.
        self.real_cameras = real_cameras
        self._camera_fault = ""
        self.task_text = env.task.instruction or env.task.name
        self.sides = hand_sides(env.embodiment)
        self.cameras = CameraSet.of_env(
            env, config.cameras, config.image_height, config.image_width, config.depth_cameras
        )
        #: Twin camera -> its feature name (``NAME_twin`` beside a real ``NAME``; as
        #: ``lerobot_features`` declares it).
        self._twin_names = recorded_twin_names(
            config.cameras + config.depth_cameras, real_cameras.names if real_cameras else ()
        )
        self.recording = False
        self._observation: dict[str, np.ndarray] | None = None
        self._keypoints = np.zeros((len(self.sides), N_JOINTS, 3), dtype=np.float32)
        self._tracked = np.zeros((len(self.sides), N_JOINTS), dtype=np.float32)
        self._started_wall = 0.0
        self.frames = 0

    # ------------------------------------------------------------------ episodes
    def begin(self) -> None:
        """Start an episode at the env's current state (call after the reset)."""
        self.writer.discard_episode()
        self._keypoints[:] = 0.0
        self._tracked[:] = 0.0
        self._camera_fault = ""
        if self.real_cameras is not None:
            self.real_cameras.start_episode()
        self._observation = self._observe()
        self.recording = True
        self.frames = 0
        self._started_wall = time.perf_counter()
        if self.watch is not None:
            self.watch.begin()

    @property
    def fault(self) -> str:
        """The episode's first hardware fault ("" when none, or no hardware): a device's,
        or a real camera that stopped delivering."""
        watched = self.watch.fault if self.watch is not None else ""
        return watched or self._camera_fault

    def end(self, keep: bool, **info) -> bool:
        """End the episode: write it (``keep``) or drop it. Returns whether it was written."""
        self.recording = False
        record = {
            "episode_index": None,
            "kept": bool(keep),
            "frames": self.frames,
            "seconds": round(self.frames / self.config.fps, 3),
            "task": self.env.task.name,
            "embodiment": embodiment_label(self.env.embodiment.name),
            **info,
        }
        if self.watch is not None:
            record["hardware_fault"] = self.watch.fault or None
            record["max_state_gap_rad"] = round(self.watch.max_gap_rad, 4)
            age = self.watch.max_reading_age_s
            record["max_state_age_s"] = round(age, 3) if math.isfinite(age) else None
        if self.real_cameras is not None:
            record["hardware_fault"] = self.fault or None
            record["cameras"] = self.real_cameras.summary()
        # A kept episode's line is written in its save's transaction: both or neither.
        written = keep and self.writer.save_episode(log_record=record)
        if not written:
            self.writer.discard_episode()
            append_log_line(self.writer.root, {**record, "kept": False})
        return bool(written)

    def close(self) -> None:
        if self.recording:
            self.writer.discard_episode()
            self.recording = False
        self.cameras.close()

    # ------------------------------------------------------------------ frames
    def _observe(self) -> dict[str, np.ndarray]:
        state = self.env.agent_pos if self.watch is None else self.watch.observe()
        obs = {STATE: np.asarray(state, dtype=np.float32)}
        if self.config.environment_state:
            obs[ENV_STATE] = self.env.environment_state
        twin = self._twin_names
        for camera, image in self.cameras.render_env(self.env).items():
            obs[IMAGE_PREFIX + twin[camera]] = image
        for camera, depth in self.cameras.render_env_depth(self.env).items():
            obs[IMAGE_PREFIX + twin[camera] + DEPTH_SUFFIX] = depth
        if self.real_cameras is not None:
            grab = self.real_cameras.grab()
            if grab.dead and not self._camera_fault:
                self._camera_fault = f"camera {', '.join(grab.dead)} stopped delivering frames"
            for camera, image in grab.frames.items():
                obs[IMAGE_PREFIX + camera] = image
        return obs

    def __call__(self, tick: Tick) -> None:
        """The single-process loop's tick: :meth:`record` of its state and frames."""
        self.record(tick.state, tick.frames)

    def record(self, state: TwinState, frames: Iterable[HandFrame] = ()) -> None:
        """One frame: the observation made before the twin's step, the action it took
        (``state.action``), and the hands' keypoints: ``frames`` (the hand frames that
        reached the operator since the last frame, oldest first; the newest of each side is
        kept). Both layouts call this: the single-process loop's tick and the twin process's
        ``after_step`` hook, with the operator's keypoints of the same tick."""
        if not self.recording or self._observation is None or self._camera_fault:
            return  # a dead camera's frame is never written (the episode ends on the fault)
        for frame in frames:
            i = self.sides.index(frame.side) if frame.side in self.sides else None
            if i is None:
                continue
            self._keypoints[i] = np.where(frame.tracked[:, None], frame.joints, 0.0)
            self._tracked[i] = frame.tracked
        row = dict(self._observation)
        row[ACTION] = np.asarray(state.action, dtype=np.float32)
        if self.watch is not None:
            self.watch.check(row[STATE], state.action)
        if self.config.hand_keypoints:
            row[KEYPOINTS] = self._keypoints.reshape(-1).copy()
            row[TRACKED] = self._tracked.reshape(-1).copy()
        self.writer.add_frame(row, self.task_text)
        self.frames += 1
        self._observation = self._observe()


def run_recorded_episode(
    loop,
    recorder: EpisodeRecorder,
    config: RecordingConfig,
    progress=None,
    stop_when=None,
    max_seconds: float | None = None,
):
    """Run the loop's current episode while recording, until it ends by itself (success,
    failure, time limit, end of a trace), ``max_seconds`` (the session's time left; the
    episode's own limit is ``config.episode_seconds``), ``stop_when()`` or a hardware fault
    (:attr:`EpisodeRecorder.fault`); ticks on for ``tail_seconds`` after success so the data
    shows the outcome settled. Returns the loop's summary."""

    def stop() -> bool:
        return bool(recorder.fault) or (stop_when is not None and stop_when())

    recorder.begin()
    loop.listeners.append(recorder)
    try:
        summary = loop.run(
            max_seconds=min(
                (s for s in (config.episode_seconds, max_seconds) if s is not None), default=None
            ),
            stop_on_success=True,
            progress=progress,
            stop_when=stop,
        )
        if summary.success:
            for _ in range(int(round(config.tail_seconds * config.fps))):
                if recorder.fault:
                    break
                tick = loop.tick()
                if progress is not None:
                    progress(tick)
    finally:
        loop.listeners.remove(recorder)
    return summary
