"""A source episode replayed on the twin from its seed: what augmentation needs of it.

The recorded actions are what the twin was given, so stepping the env from the episode's
seed with them reproduces the episode (the twin is deterministic). Per frame, after the step:
each effector's hand pose in the world (the body the operator's IK drives), every thing's pose
(free objects and fixtures), which objects each effector touches, and the objects' speeds.
Any embodiment: one arm, two (``xarm7_leap_bimanual``) or the RX-1 humanoid (its body joints
are replayed as recorded; augmentation holds them).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np

from beavr_sim.datasets.augment.frames import body_yaw_symmetry, yaw_of
from beavr_sim.datasets.augment.source import SourceEpisode
from beavr_sim.tasks.checks import in_contact


def make_env(task: str, embodiment: str):
    """The task's env (unwrapped) on ``embodiment``."""
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


def hand_body(env, effector: str) -> int:
    return env.model.body(f"{effector}/hand").id


def effector_geoms(env, effector: str) -> np.ndarray:
    """The robot geoms of ``effector`` (its arm and hand), of the task's robot geoms."""
    model = env.model
    prefix = f"{effector}/"
    return np.array(
        [
            g
            for g in env.task.robot_geoms
            if model.body(model.geom_bodyid[g]).name.startswith(prefix)
        ],
        dtype=int,
    )


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
    palm: dict[str, np.ndarray]  # effector -> (T, 4, 4) hand body pose, world
    pos: dict[str, np.ndarray]  # thing -> (T, 3)
    yaw: dict[str, np.ndarray]  # thing -> (T,)
    touch: dict[str, dict[str, np.ndarray]]  # effector -> object -> (T,) bool: it touches it
    speed: dict[str, np.ndarray]  # object -> (T,) linear speed, m/s
    start_pos: dict[str, np.ndarray]  # thing -> (3,) at the reset
    start_yaw: dict[str, float]
    success: bool
    hand: dict[str, slice]  # effector -> its hand joints within the action

    @property
    def arms(self) -> tuple[str, ...]:
        return tuple(self.palm)

    @property
    def frames(self) -> int:
        return len(self.episode.actions)


def replay(episode: SourceEpisode) -> Trajectory:
    """Step the env from ``episode.seed`` through its actions, recording the trajectory."""
    env = make_env(episode.task, episode.embodiment)
    try:
        env.reset(seed=episode.seed)
        things = Things.of(env)
        arms = [e.name for e in env.embodiment.effectors]
        bodies = {a: hand_body(env, a) for a in arms}
        geoms = {a: effector_geoms(env, a) for a in arms}
        start = {n: things.pose(env, n) for n in things.names}
        n = len(episode.actions)
        palm = {a: np.zeros((n, 4, 4)) for a in arms}
        pos = {t: np.zeros((n, 3)) for t in things.names}
        yaw = {t: np.zeros(n) for t in things.names}
        touch = {a: {o: np.zeros(n, bool) for o in things.objects} for a in arms}
        speed = {o: np.zeros(n) for o in things.objects}
        success = False
        for i, action in enumerate(episode.actions):
            _, _, info = env.advance(action)
            mujoco.mj_kinematics(env.model, env.data)
            for a in arms:
                palm[a][i] = hand_pose(env, bodies[a])
            for t in things.names:
                pos[t][i], yaw[t][i] = things.pose(env, t)
            for o in things.objects:
                obj_geoms = env.task.objects[o].geom_ids
                for a in arms:
                    touch[a][o][i] = in_contact(env.model, env.data, obj_geoms, geoms[a])
                speed[o][i] = env.task.objects[o].linear_speed(env.data)
            success |= bool(info["is_success"])
        hand = {}
        for effector in env.embodiment.effectors:
            sl = env.joints.slices[effector.name]
            hand[effector.name] = slice(sl.start + len(effector.arm_joints), sl.stop)
    finally:
        env.close()
    return Trajectory(
        episode, things, palm, pos, yaw, touch, speed,
        {t: p for t, (p, _) in start.items()}, {t: y for t, (_, y) in start.items()},
        success, hand,
    )  # fmt: skip
