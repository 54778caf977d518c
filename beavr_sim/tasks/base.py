"""The task base: scene objects, a reset distribution and a success checker.

A task receives the embodiment; it never subclasses it. Success and failure are explicit
hooks evaluated on the simulation state only (never on actions or on an expert).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import mujoco
import numpy as np

from beavr_sim.robots import Embodiment


@dataclass(frozen=True)
class TaskStatus:
    """What a checker says about the current state."""

    success: bool = False
    failure: bool = False
    details: dict[str, Any] = field(default_factory=dict)


class Task(ABC):
    """One benchmark task. Subclasses add objects and a checker; the base does the rest."""

    name: ClassVar[str]
    instruction: ClassVar[str] = ""
    max_episode_seconds: ClassVar[float] = 30.0
    #: Embodiment names this task supports; ``None`` means every embodiment.
    embodiments: ClassVar[tuple[str, ...] | None] = None

    def __init__(self, embodiment: Embodiment):
        self.embodiment = embodiment

    def build(self, scene: mujoco.MjSpec) -> None:
        """Add the task's objects to the scene spec (before compilation)."""

    def bind(self, model: mujoco.MjModel) -> None:
        """Resolve ids of the task's objects in the compiled model."""

    def initialize_episode(
        self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator
    ) -> None:
        """Place objects for a new episode, drawing from ``rng`` only; reset any latches."""

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the entries of :meth:`state` (empty: the task has no state of its own)."""
        return ()

    def state(self, data: mujoco.MjData) -> np.ndarray:
        """The task's own state (object and target poses): the env's ``environment_state``,
        privileged information a state-based policy may take in place of images."""
        return np.zeros(0)

    @abstractmethod
    def evaluate(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        """Success / failure of the current state (may update documented latches)."""
