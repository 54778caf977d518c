"""``--teleop.type=beavr_quest``: the Quest hand-tracking pipeline as a LeRobot
``Teleoperator`` (the Quest app's sockets, any WebXR headset's browser, or a VR trace).

The detector (a :class:`~beavr_sim.headset.sources.HandSource`: the Quest app's sockets or a VR
trace, frames validated by :class:`~beavr_sim.headset.validation.StreamValidator`) and the
operator (:class:`~beavr_sim.operator.operator.Operator`: filters, arm IK, LEAP retargeting)
run inside :meth:`BeavrQuestTeleop.get_action`, which returns joint targets (joint name ->
rad) for every joint of the embodiment: the ``action_features`` of ``--robot.type=beavr_sim``
with the same embodiment. The operator starts from the embodiment's home pose (where the
``beavr_sim`` robot starts in ``sim``) and keeps its arms off the task's fixtures.

LeRobot gives a teleoperator no word of what the robot did with its action, so when the
robot's guard refuses a command the operator does not re-anchor at the held pose (as
``python -m beavr_sim.teleop`` does): the robot holds until the hands lead back to safe
targets.
"""

from __future__ import annotations

import logging
import time
from functools import cached_property
from typing import Any

import numpy as np
from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from beavr_sim.envs.beavr_env import BeavrEnv
from beavr_sim.headset.sources import QuestSource, TraceSource, WebXRSource
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.integrations.config_teleoperator import TELEOP_TYPE, BeavrQuestTeleopConfig
from beavr_sim.integrations.joints import action_dict, joint_features
from beavr_sim.integrations.options import DEFAULT_EMBODIMENT, check_embodiment, check_task
from beavr_sim.operator.obstacles import fixture_obstacles
from beavr_sim.traces.format import TraceReader

log = logging.getLogger(__name__)


class BeavrQuestTeleop(Teleoperator):
    config_class = BeavrQuestTeleopConfig
    name = TELEOP_TYPE

    def __init__(self, config: BeavrQuestTeleopConfig):
        super().__init__(config)
        self.config = config
        task, embodiment, seed = config.task, config.embodiment, config.seed
        if config.source == "trace":
            meta = TraceReader(config.trace).metadata
            if meta.task and task is not None and meta.task != task:
                raise ValueError(
                    f"trace {config.trace} was recorded for task {meta.task}, not {task}"
                )
            if meta.embodiment and embodiment is not None and meta.embodiment != embodiment:
                raise ValueError(f"trace {config.trace} drives {meta.embodiment}, not {embodiment}")
            task = task or (check_task(meta.task) if meta.task else None)
            embodiment = embodiment or meta.embodiment or None
            seed = meta.seed if seed is None else seed
        #: The task whose fixtures the IK avoids (None: none), the embodiment driven, the seed.
        self.task: str | None = task
        self.embodiment = check_embodiment(embodiment or DEFAULT_EMBODIMENT)
        self.seed: int = 0 if seed is None else int(seed)
        self.joint_names: tuple[str, ...] = self.embodiment.joint_names
        self.operator = None
        self.source = None
        self._context = None
        self._validator = None
        self._stage = None  # the operator stage, once connected
        self._slices: dict[str, slice] = {}
        self._action: np.ndarray | None = None
        self._ticks = 0
        self._origin = 0.0  # tick clock: the source time the trace (re)started at
        #: Frames taken and rejected (validator), and trace restarts.
        self.frames_received = 0
        self.frames_rejected = 0
        self.restarts = 0

    def __str__(self) -> str:
        ident = f" {self.id}" if self.id else ""
        return f"beavr_quest teleoperator{ident} ({self.config.source}, {self.embodiment.name})"

    # ------------------------------------------------------------------ features
    @cached_property
    def action_features(self) -> dict[str, type]:
        return joint_features(self.joint_names)

    @cached_property
    def feedback_features(self) -> dict:
        return {}

    # ------------------------------------------------------------------ lifecycle
    @property
    def is_connected(self) -> bool:
        return self.operator is not None

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Hand tracking needs no calibration."""

    def configure(self) -> None:
        """Nothing to configure."""

    def connect(self, calibrate: bool = True) -> None:
        """Build the operator (home pose, the task's fixtures) and open the source."""
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        from beavr_sim.operator.operator import Operator  # local: heavy (the pipeline: mink, scipy)
        from beavr_sim.teleop.stages import (
            OperatorStage,  # local: heavy (the pipeline: mink, scipy)
        )

        cfg = self.config
        # The task's scene at the seed's layout: the joints' order and home, and the fixtures.
        env = BeavrEnv(task=self.task or "Playground", embodiment=self.embodiment.name)
        try:
            env.reset(seed=self.seed)
            home = env.joints.home.astype(np.float64).copy()
            self._slices = dict(env.joints.slices)
            obstacles = fixture_obstacles(env.model, env.data)
        finally:
            env.close()
        operator = Operator(self.embodiment, 1.0 / cfg.fps)
        operator.reset(home, self._slices)
        operator.set_obstacles(obstacles)
        self._validator = StreamValidator()
        if cfg.source == "trace":
            self.source = TraceSource(cfg.trace, real_time=cfg.clock == "real")
        elif cfg.source == "webxr":
            self.source = WebXRSource(cfg.webxr_config(), self._validator)
            log.info("%s: open %s in the headset's browser and press Start", self, self.source.url)
        else:
            import zmq

            self._context = zmq.Context()
            try:
                self.source = QuestSource(self._context, cfg.transport(), self._validator)
            except BaseException:
                self._context.destroy(linger=0)
                self._context = None
                raise
        self._action = home
        self._ticks, self._origin = 0, 0.0
        self.operator = operator
        # the runners' operator stage: an operator exception holds (reason "error")
        self._stage = OperatorStage(
            operator,
            cfg.fps,
            hold_positions=lambda name: self._action[self._slices[name]].copy(),
            source_finished=lambda: self.source is not None and self.source.finished,
        )
        log.info("%s connected (%s, %s clock)", self, cfg.source, cfg.clock)

    def disconnect(self) -> None:
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        try:
            if self.source is not None:
                self.source.close()
        finally:
            if self._context is not None:
                self._context.destroy(linger=0)
            self.source = self.operator = self._context = None

    # ------------------------------------------------------------------ I/O
    def _now(self) -> float:
        if self.config.clock == "tick":
            return self._ticks / self.config.fps
        return time.monotonic()

    def get_action(self) -> dict[str, float]:
        """The operator's joint targets for the newest hand frames (holds where none)."""
        if self.operator is None:
            raise DeviceNotConnectedError(f"{self} is not connected: call connect() first")
        operator, source = self.operator, self.source
        now = self._now()
        if source.finished and self.config.loop_trace:
            source.rewind()
            self._validator.reset()
            self._origin = now
            operator.reset(self._action, self._slices)  # re-anchor: nothing jumps
            self.restarts += 1
        frames = source.poll(now - self._origin if self.config.clock == "tick" else now)
        used = []
        for frame in frames:
            self.frames_received += 1
            if source.validates or self._validator.check(frame) is None:
                used.append(frame)
            else:
                self.frames_rejected += 1
        stage = self._stage
        for name, command in stage.command(now, stage.observe(used)).items():
            self._action[self._slices[name]] = command.positions
        self._ticks += 1
        return action_dict(self._action, self.joint_names)

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        """No feedback to the headset through LeRobot (the twin's view goes over
        ``python -m beavr_sim.teleop``)."""
