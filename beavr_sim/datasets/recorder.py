"""Teleop ticks -> LeRobot frames: the recorder listens to the teleop loop.

A LeRobot frame pairs an observation with the action taken from it. The loop reports each tick
after the twin stepped, so the recorder keeps the observation made before the step (measured
joints and camera images) and, at the tick, writes it with the action the twin was actually
given (:attr:`TwinState.action`: the operator's targets after the twin's composition; holds
included). Hand keypoints are the newest frame of each side up to that tick.

Episodes: :meth:`EpisodeRecorder.begin` after the env reset, :meth:`EpisodeRecorder.end` with
keep or drop. A summary line per episode goes to ``meta/beavr_episodes.jsonl`` beside LeRobot's
metadata (seed, success, duration, source): LeRobot has no field for them.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.datasets.features import (
    ACTION,
    ENV_STATE,
    IMAGE_PREFIX,
    KEYPOINTS,
    STATE,
    TRACKED,
    RecordingConfig,
    hand_sides,
)
from beavr_sim.datasets.writer import EpisodeWriter
from beavr_sim.envs.cameras import OffscreenCameras
from beavr_sim.wire.hand import N_JOINTS
from beavr_sim.wire.records import Tick


class CameraSet:
    """The recorded cameras, rendered together at the recording size."""

    def __init__(
        self, model: mujoco.MjModel | None, cameras: tuple[str, ...], height: int, width: int
    ):
        self.cameras = tuple(cameras)
        if self.cameras and model is None:
            raise ValueError(f"cameras {self.cameras} need a model to render")
        self._cameras = OffscreenCameras(model, height, width) if self.cameras else None

    @classmethod
    def of_env(cls, env, cameras: tuple[str, ...], height: int, width: int) -> CameraSet:
        """The cameras of a :class:`~beavr_sim.envs.beavr_env.BeavrEnv`, drawing its render
        model (compiled only if there is a camera)."""
        return cls(env.render_model if cameras else None, cameras, height, width)

    def render(self, data: mujoco.MjData) -> dict[str, np.ndarray]:
        return {c: self._cameras.render(data, c) for c in self.cameras}

    def render_env(self, env) -> dict[str, np.ndarray]:
        """Every camera at ``env``'s current state (its render model's data)."""
        return self.render(env.render_data()) if self.cameras else {}

    def close(self) -> None:
        if self._cameras is not None:
            self._cameras.close()


class EpisodeRecorder:
    """A teleop-loop listener writing the ticks of each episode as LeRobot frames."""

    def __init__(
        self,
        writer: EpisodeWriter,
        env,
        config: RecordingConfig,
        state_source: Callable[[], np.ndarray] | None = None,
    ):
        self.writer = writer
        self.env = env
        self.config = config
        #: Where ``observation.state`` comes from: the twin's joints by default; the measured
        #: hardware joints when mirroring (``HardwareMirror.latest_measured``).
        self.state_source = state_source
        self.task_text = env.task.instruction or env.task.name
        self.sides = hand_sides(env.embodiment)
        self.cameras = CameraSet.of_env(
            env, config.cameras, config.image_height, config.image_width
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
        self._observation = self._observe()
        self.recording = True
        self.frames = 0
        self._started_wall = time.perf_counter()

    def end(self, keep: bool, **info) -> bool:
        """End the episode: write it (``keep``) or drop it. Returns whether it was written."""
        self.recording = False
        written = keep and self.writer.save_episode()
        if not written:
            self.writer.discard_episode()
        record = {
            "episode_index": self.writer.num_episodes - 1 if written else None,
            "kept": bool(written),
            "frames": self.frames,
            "seconds": round(self.frames / self.config.fps, 3),
            "task": self.env.task.name,
            "embodiment": self.env.embodiment.name,
            **info,
        }
        log_path = Path(self.writer.root) / "meta" / "beavr_episodes.jsonl"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with log_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        return bool(written)

    def close(self) -> None:
        if self.recording:
            self.writer.discard_episode()
            self.recording = False
        self.cameras.close()

    # ------------------------------------------------------------------ frames
    def _observe(self) -> dict[str, np.ndarray]:
        state = self.env.agent_pos if self.state_source is None else self.state_source()
        obs = {STATE: np.asarray(state, dtype=np.float32)}
        if self.config.environment_state:
            obs[ENV_STATE] = self.env.environment_state
        for camera, image in self.cameras.render_env(self.env).items():
            obs[IMAGE_PREFIX + camera] = image
        return obs

    def __call__(self, tick: Tick) -> None:
        if not self.recording or self._observation is None:
            return
        for frame in tick.frames:
            i = self.sides.index(frame.side) if frame.side in self.sides else None
            if i is None:
                continue
            self._keypoints[i] = np.where(frame.tracked[:, None], frame.joints, 0.0)
            self._tracked[i] = frame.tracked
        row = dict(self._observation)
        row[ACTION] = np.asarray(tick.state.action, dtype=np.float32)
        if self.config.hand_keypoints:
            row[KEYPOINTS] = self._keypoints.reshape(-1).copy()
            row[TRACKED] = self._tracked.reshape(-1).copy()
        self.writer.add_frame(row, self.task_text)
        self.frames += 1
        self._observation = self._observe()


def run_recorded_episode(
    loop, recorder: EpisodeRecorder, config: RecordingConfig, progress=None, stop_when=None
):
    """Run the loop's current episode while recording, until it ends by itself (success,
    failure, time limit, end of a trace) or ``stop_when()``; ticks on for ``tail_seconds``
    after success so the data shows the outcome settled. Returns the loop's summary."""
    recorder.begin()
    loop.listeners.append(recorder)
    try:
        summary = loop.run(
            max_seconds=config.episode_seconds,
            stop_on_success=True,
            progress=progress,
            stop_when=stop_when,
        )
        if summary.success:
            for _ in range(int(round(config.tail_seconds * config.fps))):
                loop.tick()
    finally:
        loop.listeners.remove(recorder)
    return summary
