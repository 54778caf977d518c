"""Playground: the bare scene with no objects and no success criterion."""

from __future__ import annotations

import mujoco

from beavr_sim.tasks.base import Task, TaskStatus


class Playground(Task):
    name = "Playground"
    instruction = "Move freely."
    max_episode_seconds = 60.0

    def evaluate(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        return TaskStatus(success=False, failure=False)
