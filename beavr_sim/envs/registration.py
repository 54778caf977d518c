"""The one registry of gymnasium ids: ``beavr_sim/<Task>-v0`` for every task.

Entry points are strings, so registering imports neither MuJoCo nor the tasks.
"""

from __future__ import annotations

import gymnasium as gym

from beavr_sim.tasks.registry import TASKS

ENV_NAMESPACE = "beavr_sim"
ENTRY_POINT = "beavr_sim.envs.beavr_env:BeavrEnv"


def env_id(task: str) -> str:
    return f"{ENV_NAMESPACE}/{task}-v0"


def register_envs() -> list[str]:
    """Register every task's env (idempotent); returns the ids."""
    ids = []
    for task in TASKS:
        eid = env_id(task)
        if eid not in gym.registry:
            gym.register(
                id=eid, entry_point=ENTRY_POINT, kwargs={"task": task}, disable_env_checker=False
            )
        ids.append(eid)
    return ids


def registered_env_ids() -> list[str]:
    return [eid for eid in gym.registry if eid.startswith(ENV_NAMESPACE + "/")]
