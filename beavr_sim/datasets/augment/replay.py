"""A source episode replayed on the twin from its seed: what augmentation needs of it.

The recorded actions are what the twin was given, so stepping the env from the episode's
seed with them reproduces the episode (the twin is deterministic). Per frame, after the step:
the effector's hand pose in the world (the body the operator's IK drives), every thing's pose
(free objects and fixtures), which objects the robot touches, and the objects' speeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np

from beavr_sim.datasets.augment.frames import body_yaw_symmetry, yaw_of
from beavr_sim.datasets.augment.source import SourceEpisode

SINGLE_ARM = ("xarm7_leap_right", "xarm7_leap_left")


def make_env(task: str, embodiment: str):
    """The task's env (unwrapped) for a single-arm embodiment; bimanual comes later."""
    if embodiment not in SINGLE_ARM:
        raise ValueError(
            f"augmentation supports single-arm embodiments for now ({', '.join(SINGLE_ARM)}), "
            f"not {embodiment!r}"
        )
    return gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped


@dataclass(frozen=True)
class Things:
    """The task's free objects and fixtures, bound to an env: poses and symmetries."""

    objects: tuple[str, ...]
    fixtures: tuple[str, ...]
    symmetry: dict[str, float]

    @classmethod
    def of(cls, env) -> Things:
        task = env.task
        objects = tuple(getattr(task, "objects", {}))
        fixtures = tuple(getattr(task, "fixtures", {}))
        sym = {n: body_yaw_symmetry(env.model, task.objects[n].geom_ids) for n in objects}
        sym |= {n: body_yaw_symmetry(env.model, task.fixtures[n].geom_ids) for n in fixtures}
        return cls(objects, fixtures, sym)

    @property
    def names(self) -> tuple[str, ...]:
        return self.objects + self.fixtures

    def pose(self, env, name: str) -> tuple[np.ndarray, float]:
        """Position and yaw of ``name`` now."""
        task, data = env.task, env.data
        if name in task.objects:
            obj = task.objects[name]
            return obj.pos(data), yaw_of(obj.R_world_body(data))
        fixture = task.fixtures[name]
        return fixture.pos(data), fixture.yaw(data)


def hand_body(env) -> int:
    effector = env.embodiment.effectors[0]
    return env.model.body(f"{effector.name}/hand").id


def hand_pose(env, body: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = env.data.xmat[body].reshape(3, 3)
    T[:3, 3] = env.data.xpos[body]
    return T


@dataclass(frozen=True)
class Trajectory:
    """A replayed source episode, one row per frame (after that frame's step)."""

    episode: SourceEpisode
    things: Things
    palm: np.ndarray  # (T, 4, 4) hand body pose, world
    pos: dict[str, np.ndarray]  # thing -> (T, 3)
    yaw: dict[str, np.ndarray]  # thing -> (T,)
    touch: dict[str, np.ndarray]  # object -> (T,) bool: the robot touches it
    speed: dict[str, np.ndarray]  # object -> (T,) linear speed, m/s
    start_pos: dict[str, np.ndarray]  # thing -> (3,) at the reset
    start_yaw: dict[str, float]
    success: bool
    hand: slice  # the hand joints within the action

    @property
    def frames(self) -> int:
        return len(self.palm)


def replay(episode: SourceEpisode) -> Trajectory:
    """Step the env from ``episode.seed`` through its actions, recording the trajectory."""
    env = make_env(episode.task, episode.embodiment)
    try:
        env.reset(seed=episode.seed)
        things = Things.of(env)
        body = hand_body(env)
        start = {n: things.pose(env, n) for n in things.names}
        n = len(episode.actions)
        palm = np.zeros((n, 4, 4))
        pos = {t: np.zeros((n, 3)) for t in things.names}
        yaw = {t: np.zeros(n) for t in things.names}
        touch = {o: np.zeros(n, bool) for o in things.objects}
        speed = {o: np.zeros(n) for o in things.objects}
        success = False
        for i, action in enumerate(episode.actions):
            _, _, info = env.advance(action)
            mujoco.mj_kinematics(env.model, env.data)
            palm[i] = hand_pose(env, body)
            for t in things.names:
                pos[t][i], yaw[t][i] = things.pose(env, t)
            for o in things.objects:
                touch[o][i] = env.task.touched_by_robot(env.model, env.data, o)
                speed[o][i] = env.task.objects[o].linear_speed(env.data)
            success |= bool(info["is_success"])
        effector = env.embodiment.effectors[0]
        sl = env.joints.slices[effector.name]
        hand = slice(sl.start + len(effector.arm_joints), sl.stop)
    finally:
        env.close()
    return Trajectory(
        episode, things, palm, pos, yaw, touch, speed,
        {t: p for t, (p, _) in start.items()}, {t: y for t, (_, y) in start.items()},
        success, hand,
    )  # fmt: skip
