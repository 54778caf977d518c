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

from beavr_sim.experts import grasps
from beavr_sim.experts.ik import TwinIK
from beavr_sim.robots.embodiment import EMBODIMENTS
from beavr_sim.robots.robot_file import is_robot_file
from beavr_sim.workcell import TABLE_TOP_Z

#: Hand speed limits of every expert: a calm human reaching speed.
MAX_LINEAR_SPEED = 0.3  # m/s
MAX_ANGULAR_SPEED = 1.5  # rad/s
MAX_FINGER_SPEED = 3.0  # rad/s per joint
#: Joint speed of the opening move to the ready posture (rad/s, the fastest joint).
READY_JOINT_SPEED = 1.0
#: Ready hands stand at least this far apart sideways (m): two hands on close shoulders (a
#: humanoid's) wait spread out, clear of each other and of the other's work.
READY_MIN_SPACING = 0.5


@dataclass
class Move:
    """Move some effectors' hands and/or fingers to new targets over at least ``duration`` s.

    ``poses``: effector name -> T_world_hand target; ``fingers``: effector name -> 16 hand
    joint targets written for a right hand (mirrored for a left one). Effectors not named keep their current targets. ``settle`` seconds of
    holding follow the motion.
    """

    poses: Mapping[str, mink.SE3] = field(default_factory=dict)
    fingers: Mapping[str, np.ndarray] = field(default_factory=dict)
    duration: float = 0.0
    settle: float = 0.0


def smoothstep(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * (3 - 2 * s)


def check_expert_embodiment(embodiment: str) -> None:
    """Refuse a robot file in one line naming the built-in embodiments: the experts' grasp
    headings (:attr:`~beavr_sim.robots.parts.ArmModel.pinch_heading_deg_by_side`) and reaches
    are tuned on the built-in arms, and a robot file's arm states none. Other names are left to
    the embodiment check."""
    if is_robot_file(embodiment):
        raise ValueError(
            f"the scripted experts run on the built-in embodiments ({', '.join(EMBODIMENTS)}), "
            f"not on the robot file {embodiment}: their grasp headings are tuned for those arms"
        )


class ScriptedExpert(ABC):
    """Base of the scripted experts: runs a :meth:`script` through the IK, one step per call."""

    def __init__(self, env):
        self.env = env.unwrapped
        self.task = self.env.task
        self.embodiment = self.env.embodiment
        check_expert_embodiment(self.embodiment.name)
        self.dt = 1.0 / self.env.control_hz
        self.ik = TwinIK(self.embodiment, self.dt)
        self.ready_q = self.ik.converge(self.ready_poses())
        self._script: Iterator[Move] | None = None

    # ------------------------------------------------------------------ running
    def reset(self) -> None:
        """Call after ``env.reset``: start from the measured robot state.

        The arms first move in joint space to the ready posture (as an operator raises the
        hands before starting), then the script runs in task space from there.
        """
        q = self.env.agent_pos.astype(np.float64)
        self.ik.reset(q, posture=self.ready_q)
        self.fingers = {
            e.name: q[self.env.joints.slices[e.name]][len(e.arm_joints) :].copy()
            for e in self.embodiment.effectors
        }
        span = float(np.max(np.abs(self.ready_q - q)))
        n = max(1, int(np.ceil(span / READY_JOINT_SPEED / self.dt)))
        self._joint_path = [q + smoothstep(i / n) * (self.ready_q - q) for i in range(1, n + 1)]
        self.pose = {e.name: self.ik.T_world_hand(e.name) for e in self.embodiment.effectors}
        self._script = self.script()
        self._timeline: list[tuple[dict, dict]] = []
        self.done = False

    def act(self) -> np.ndarray:
        """The next action (joint targets in the env's order)."""
        if self._script is None:
            raise RuntimeError("call reset() after env.reset() before act()")
        if self._joint_path:
            q = self._joint_path.pop(0)
            self.ik.reset(q, posture=self.ready_q)
            self.pose = {e.name: self.ik.T_world_hand(e.name) for e in self.embodiment.effectors}
            return self._with_fingers(q)
        while not self._timeline and not self.done:
            try:
                self._timeline = self._expand(next(self._script))
            except StopIteration:
                self.done = True
        if self._timeline:
            self.pose, self.fingers = self._timeline.pop(0)
        return self._with_fingers(self.ik.step(self.pose))

    def _sided(self, fingers: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Finger shapes written for a right hand, mirrored for each effector's side."""
        return {
            name: e.hand.mirrored(np.asarray(shape, float), e.side)
            for name, shape in fingers.items()
            for e in self.embodiment.spec.effectors
            if e.name == name
        }

    def _with_fingers(self, q: np.ndarray) -> np.ndarray:
        """Arm joints from ``q``, hand joints from the current finger targets."""
        q = q.copy()
        for e in self.embodiment.effectors:
            sl = self.env.joints.slices[e.name]
            q[sl.start + len(e.arm_joints) : sl.stop] = self.fingers[e.name]
        return np.clip(q, self.env.joints.lower, self.env.joints.upper).astype(np.float32)

    def _expand(self, move: Move) -> list[tuple[dict, dict]]:
        """The per-control-step (pose, fingers) targets of one segment."""
        start_pose, start_fingers = dict(self.pose), dict(self.fingers)
        end_pose = {**start_pose, **move.poses}
        end_fingers = {**start_fingers, **self._sided(move.fingers)}
        duration = move.duration
        for name, target in move.poses.items():
            delta = (start_pose[name].inverse() @ target).log()
            duration = max(
                duration,
                np.linalg.norm(target.translation() - start_pose[name].translation())
                / MAX_LINEAR_SPEED,
                np.linalg.norm(delta[3:]) / MAX_ANGULAR_SPEED,
            )
        for name, target in self._sided(move.fingers).items():
            duration = max(
                duration, float(np.max(np.abs(target - start_fingers[name]))) / MAX_FINGER_SPEED
            )
        n = max(1, int(np.ceil(duration / self.dt)))
        steps = []
        for i in range(1, n + 1):
            s = smoothstep(i / n)
            pose = {k: _interpolate(start_pose[k], end_pose[k], s) for k in end_pose}
            fingers = {k: (1 - s) * start_fingers[k] + s * end_fingers[k] for k in end_fingers}
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

    def effector_spec(self, effector: str):
        return next(e for e in self.embodiment.spec.effectors if e.name == effector)

    def pinch_heading(self, effector: str) -> float:
        """The palm-down hand heading (rad, world) ``effector``'s arm reaches the table with
        most freely (:attr:`ArmModel.pinch_heading_deg_by_side`, turned with the base)."""
        e = self.effector_spec(effector)
        return e.arm.pinch_heading(e.side) + float(np.deg2rad(e.base_yaw_deg))

    def ready_poses(self) -> dict[str, mink.SE3]:
        """Each hand palm down at its arm's pinch heading (fingers forward on an xArm), 20 cm
        above the workspace in front of its arm (spread to READY_MIN_SPACING apart when the
        arms stand closer): the posture the IK's redundancy resolves towards (keeps the elbow
        and wrist in one consistent configuration across episodes)."""
        ws = self.task.workspace
        specs = self.embodiment.spec.effectors
        ys = np.array([e.base_pos[1] for e in specs], float)
        if np.ptp(ys) > 0 and np.ptp(ys) < READY_MIN_SPACING:
            ys = ys.mean() + (ys - ys.mean()) * READY_MIN_SPACING / np.ptp(ys)
        return {
            e.name: grasps.T_world_hand_pinching(
                (np.mean(ws.x), y, TABLE_TOP_Z + 0.2),
                grasps.R_world_palm_down(self.pinch_heading(e.name)),
            )
            for e, y in zip(specs, ys, strict=True)
        }

    def reaches(self, effector: str, targets) -> bool:
        """Whether ``effector``'s hand can get to the poses ``targets`` in turn from where
        the IK is now (a trial: the IK state is left as it was)."""
        return self.ik.reaches(*({effector: T} for T in targets))

    # ------------------------------------------------------- motion primitives
    def pick_poses(self, obj: str, heading: float, lift: float = 0.12) -> tuple[mink.SE3, ...]:
        """The hand poses of :meth:`pick`: over object ``obj`` (its pose now), and at it."""
        centre = self.task.objects[obj].pos(self.env.data)
        centre[2] = max(centre[2], TABLE_TOP_Z + grasps.MIN_PINCH_HEIGHT)
        R = grasps.R_world_palm_down(heading)
        return (
            grasps.T_world_hand_pinching(centre + [0, 0, lift], R),
            grasps.T_world_hand_pinching(centre, R),
        )

    def pick(
        self,
        effector: str,
        obj: str,
        heading: float,
        lift: float = 0.12,
        also: Mapping[str, mink.SE3] | None = None,
    ) -> Iterator[Move]:
        """Front-pinch object ``obj`` (read its pose now) with the hand heading ``heading``,
        then lift it ``lift`` metres. ``also``: other hands' poses to move to meanwhile, on
        the way over the object."""
        above, at = self.pick_poses(obj, heading, lift)
        yield Move(
            poses={**(also or {}), effector: above},
            fingers={effector: grasps.PINCH_OPEN},
            settle=0.2,
        )
        yield Move(poses={effector: at}, settle=0.2)
        yield Move(fingers={effector: grasps.PINCH_CLOSED}, duration=0.6, settle=0.3)
        yield Move(poses={effector: above}, settle=0.2)

    def place(
        self,
        effector: str,
        centre_world,
        held: str | None = None,
        clearance: float = 0.12,
        drop: float = 0.005,
    ) -> Iterator[Move]:
        """Carry the pinched object over ``centre_world`` (where its centre should end up),
        lower it to ``drop`` metres above that, open the hand and withdraw upwards.

        With ``held`` (the object's name), the expert first looks where the object really
        sits in the hand (it may have slipped in the pinch) and aims with that, as an
        operator corrects by eye.
        """
        pose = self.pose[effector]
        R = pose.rotation().as_matrix()
        centre = np.asarray(centre_world, float)
        in_hand = self.object_in_hand(effector, held) if held is not None else None

        def at(height: float) -> mink.SE3:
            return grasps.T_world_hand_pinching(centre + [0, 0, height], R, in_hand)

        yield Move(poses={effector: at(clearance)}, settle=0.2)
        yield Move(poses={effector: at(drop)}, settle=0.2)
        yield Move(fingers={effector: grasps.RELEASE}, duration=0.4, settle=0.2)
        yield Move(poses={effector: at(clearance)}, settle=0.2)

    def object_in_hand(self, effector: str, obj: str) -> np.ndarray:
        """Where object ``obj``'s centre is in ``effector``'s hand frame, measured now."""
        hand = self.env.data.body(f"{effector}/hand")
        R_world_hand = hand.xmat.reshape(3, 3)
        return R_world_hand.T @ (self.task.objects[obj].pos(self.env.data) - hand.xpos)

    def retreat(self, effector: str) -> Iterator[Move]:
        """Take the hand back to its ready pose, out of the way of the cameras and objects."""
        yield Move(poses=self.ready_poses_of(effector))

    def ready_poses_of(self, *effectors: str) -> dict[str, mink.SE3]:
        """The ready poses of ``effectors`` (effector name -> pose)."""
        ready = self.ready_poses()
        return {name: ready[name] for name in effectors}


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
