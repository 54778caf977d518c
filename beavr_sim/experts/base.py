"""Scripted experts: task-space motion scripts turned into joint targets through the twin's IK.

An expert's :meth:`ScriptedExpert.script` is a generator of :class:`Move` segments. It may
read the simulation (object poses) between segments, like an operator who looks before each
motion, but it acts only through the env's actions. Each segment interpolates the hand poses
(position linearly, rotation along the geodesic, with a smooth-step time law) and finger
targets from where the previous segment left them; its duration is stretched so that no hand
moves faster than the expert's speed limits. The IK then follows under joint speed limits.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import mink
import numpy as np

from beavr_sim.experts.ik import TwinIK

#: Hand speed limits of every expert: a calm human reaching speed.
MAX_LINEAR_SPEED = 0.3  # m/s
MAX_ANGULAR_SPEED = 1.5  # rad/s
MAX_FINGER_SPEED = 3.0  # rad/s per joint


@dataclass
class Move:
    """Move some effectors' hands and/or fingers to new targets over at least ``duration`` s.

    ``poses``: effector name -> T_world_hand target; ``fingers``: effector name -> 16 hand
    joint targets. Effectors not named keep their current targets. ``settle`` seconds of
    holding follow the motion.
    """

    poses: Mapping[str, mink.SE3] = field(default_factory=dict)
    fingers: Mapping[str, np.ndarray] = field(default_factory=dict)
    duration: float = 0.0
    settle: float = 0.0


def smoothstep(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * (3 - 2 * s)


class ScriptedExpert(ABC):
    """Base of the scripted experts: runs a :meth:`script` through the IK, one step per call."""

    def __init__(self, env):
        self.env = env.unwrapped
        self.task = self.env.task
        self.embodiment = self.env.embodiment
        self.dt = 1.0 / self.env.control_hz
        self.ik = TwinIK(self.embodiment, self.dt)
        self._script: Iterator[Move] | None = None

    # ------------------------------------------------------------------ running
    def reset(self) -> None:
        """Call after ``env.reset``: start the script from the measured robot state."""
        q = self.env.agent_pos.astype(np.float64)
        self.ik.reset(q)
        self.pose = {e.name: self.ik.T_world_hand(e.name) for e in self.embodiment.effectors}
        self.fingers = {
            e.name: q[self.env.joints.slices[e.name]][len(e.arm_joints) :].copy()
            for e in self.embodiment.effectors
        }
        self._script = self.script()
        self._timeline: list[tuple[dict, dict]] = []
        self.done = False

    def act(self) -> np.ndarray:
        """The next action (joint targets in the env's order)."""
        if self._script is None:
            raise RuntimeError("call reset() after env.reset() before act()")
        while not self._timeline and not self.done:
            try:
                self._timeline = self._expand(next(self._script))
            except StopIteration:
                self.done = True
        if self._timeline:
            self.pose, self.fingers = self._timeline.pop(0)
        q = self.ik.step(self.pose)
        for e in self.embodiment.effectors:
            sl = self.env.joints.slices[e.name]
            q[sl.start + len(e.arm_joints) : sl.stop] = self.fingers[e.name]
        return np.clip(q, self.env.joints.lower, self.env.joints.upper).astype(np.float32)

    def _expand(self, move: Move) -> list[tuple[dict, dict]]:
        """The per-control-step (pose, fingers) targets of one segment."""
        start_pose, start_fingers = dict(self.pose), dict(self.fingers)
        end_pose = {**start_pose, **move.poses}
        end_fingers = {k: np.asarray(v, float) for k, v in {**start_fingers, **move.fingers}.items()}
        duration = move.duration
        for name, target in move.poses.items():
            delta = (start_pose[name].inverse() @ target).log()
            duration = max(
                duration,
                np.linalg.norm(target.translation() - start_pose[name].translation())
                / MAX_LINEAR_SPEED,
                np.linalg.norm(delta[3:]) / MAX_ANGULAR_SPEED,
            )
        for name, target in move.fingers.items():
            duration = max(
                duration, float(np.max(np.abs(target - start_fingers[name]))) / MAX_FINGER_SPEED
            )
        n = max(1, int(np.ceil(duration / self.dt)))
        steps = []
        for i in range(1, n + 1):
            s = smoothstep(i / n)
            pose = {k: _interpolate(start_pose[k], end_pose[k], s) for k in end_pose}
            fingers = {
                k: (1 - s) * start_fingers[k] + s * end_fingers[k] for k in end_fingers
            }
            steps.append((pose, fingers))
        steps += [steps[-1]] * int(np.ceil(move.settle / self.dt))
        return steps

    # ------------------------------------------------------------ for subclasses
    @abstractmethod
    def script(self) -> Iterator[Move]:
        """Yield the motion segments that solve the task (may read the sim in between)."""

    @property
    def effector_names(self) -> list[str]:
        return [e.name for e in self.embodiment.effectors]


def _interpolate(a: mink.SE3, b: mink.SE3, s: float) -> mink.SE3:
    """Straight-line position, geodesic rotation."""
    if s <= 0:
        return a
    if s >= 1:
        return b
    Ra, Rb = a.rotation(), b.rotation()
    R = Ra @ mink.SO3.exp(s * (Ra.inverse() @ Rb).log())
    p = (1 - s) * a.translation() + s * b.translation()
    return mink.SE3.from_rotation_and_translation(R, p)
