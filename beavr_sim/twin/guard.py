"""The twin as collision guard: a command that would put the robot into itself or the table
is refused before it is applied (and, when mirroring, before it reaches any hardware).

The check is kinematic: the commanded joint positions are put into a private copy of the
twin's model (objects where the twin has them now), and MuJoCo's collision detection lists
the contacts. A command is refused when one of its effector's geoms would penetrate the
static scene (table, fixtures on the world body) or another robot geom (another link of the
same robot, or the other arm) by more than ``tolerance``. Contacts with the task's objects are
the point of manipulation and never block.

The operator's IK already keeps the arm off the table and the fingers apart with velocity
limits, so in normal operation the guard never fires; it is the last line against what the
IK cannot see (a stale command, a bad retarget, the other arm).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.robots.embodiment import Embodiment, JointIndex

_ROBOT, _STATIC = 1, 2  # contype / conaffinity bits of the guard's private model


@dataclass(frozen=True)
class GuardConfig:
    #: Penetration (m) a commanded configuration may have before it is refused. Position
    #: targets of a grasp sit slightly inside what they grasp; against the table or the robot
    #: itself a few millimetres are allowed for the difference between target and reached pose.
    tolerance: float = 0.005
    #: The same for finger links: a grasp near the table commands the fingertips a little into
    #: it (the bundled traces go to ~8 mm) and the hand's position control then presses with a
    #: small force; that is wanted, a finger driven centimetres into the table is not.
    finger_tolerance: float = 0.02

    def __post_init__(self) -> None:
        for name in ("tolerance", "finger_tolerance"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class GuardVerdict:
    """Which effectors' commands are refused, and the contacts that refused them."""

    blocked: tuple[str, ...]
    #: (geom 1, geom 2, penetration depth in m) per offending contact; an unnamed geom is
    #: called ``{body}/geom{id}``.
    contacts: tuple[tuple[str, str, float], ...] = ()

    @property
    def ok(self) -> bool:
        return not self.blocked


class CollisionGuard:
    """Checks full commanded actions (action order) against the twin's model."""

    def __init__(
        self,
        model: mujoco.MjModel,
        embodiment: Embodiment,
        joints: JointIndex,
        config: GuardConfig | None = None,
    ):
        self.config = config or GuardConfig()
        self.joints = joints
        # Owner of each geom: the effector whose subtree it is in; "static" for bodies welded
        # to the world (table, fixtures); None for objects (bodies that move freely, never
        # guarded).
        names = [e.name for e in embodiment.effectors]
        self._owner: list[str | None] = []
        self._geom_names: list[str] = []
        finger_bodies = {
            int(model.jnt_bodyid[model.joint(j).id])
            for e in embodiment.effectors
            for j in e.hand_joints
        }
        for b in range(model.nbody):  # bodies below a finger joint are finger links too
            parent = int(model.body_parentid[b])
            if parent in finger_bodies:
                finger_bodies.add(b)
        self._tolerance = np.full(model.ngeom, self.config.tolerance)
        for g in range(model.ngeom):
            body = int(model.geom_bodyid[g])
            body_name = model.body(body).name
            owner = next((e for e in names if body_name.startswith(e + "/")), None)
            if owner is None and int(model.body_weldid[body]) == 0:
                owner = "static"
            self._owner.append(owner)
            if body in finger_bodies:
                self._tolerance[g] = self.config.finger_tolerance
            elif owner == "static":
                self._tolerance[g] = np.inf  # the robot geom's tolerance decides
            self._geom_names.append(model.geom(g).name or f"{body_name or 'world'}/geom{g}")
        # A private copy of the model in which only robot-static and robot-robot pairs can
        # collide (contype / conaffinity bits): objects, and the scene with itself, are never
        # checked, so the cost does not grow with the task's objects (e.g. pour's particles).
        self.model = copy.deepcopy(model)
        for g, owner in enumerate(self._owner):
            if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
                continue  # visual only
            if owner is None:
                self.model.geom_contype[g] = self.model.geom_conaffinity[g] = 0
            elif owner == "static":
                self.model.geom_contype[g], self.model.geom_conaffinity[g] = _STATIC, 0
            else:
                self.model.geom_contype[g], self.model.geom_conaffinity[g] = (
                    _ROBOT,
                    _ROBOT | _STATIC,
                )
        self.data = mujoco.MjData(self.model)
        self.checks = 0
        self.refusals = 0

    def check(self, action: np.ndarray, qpos_now: np.ndarray) -> GuardVerdict:
        """Would ``action`` (joint targets, action order) collide, objects as in ``qpos_now``?"""
        m, d = self.model, self.data
        d.qpos[:] = qpos_now
        d.qpos[self.joints.qpos_adr] = action
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        self.checks += 1
        blocked: set[str] = set()
        offending = []
        n = d.ncon
        if n:
            contacts = d.contact
            g1, g2, dist = contacts.geom1[:n], contacts.geom2[:n], contacts.dist[:n]
            deep = dist < -np.minimum(self._tolerance[g1], self._tolerance[g2])
            for i in np.flatnonzero(deep):
                a, b = self._owner[g1[i]], self._owner[g2[i]]
                blocked |= {a, b} - {"static"}
                offending.append(
                    (self._geom_names[g1[i]], self._geom_names[g2[i]], float(-dist[i]))
                )
        if blocked:
            self.refusals += 1
        return GuardVerdict(tuple(sorted(blocked)), tuple(offending))

    def filter(
        self,
        action: np.ndarray,
        previous: np.ndarray,
        qpos_now: np.ndarray,
        slices: Mapping[str, slice],
    ) -> tuple[np.ndarray, GuardVerdict]:
        """``action`` with every refused effector's slice set back to ``previous``.

        The held action is checked again: if the robot is already in collision (e.g. placed
        there by a reset) holding is still the safest thing, so it is returned as is.
        """
        verdict = self.check(action, qpos_now)
        if verdict.ok:
            return action, verdict
        safe = np.array(action, dtype=np.float64, copy=True)
        for name in verdict.blocked:
            safe[slices[name]] = previous[slices[name]]
        return safe, verdict
