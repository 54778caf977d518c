"""The operator's arm IK: one QP step per tick on a one-effector copy of the twin.

Each effector gets its own robot-only model (its arm and hand at their base pose, or on the
body that carries it holding its pose, and the table), so effectors solve independently. One call to :meth:`ArmIK.step` moves the arm one
control period towards the target hand pose: a damped Gauss-Newton step on the arm joints
only (the quantities of ``mink.FrameTask`` and ``mink.PostureTask``: position and orientation
error of the ``hand`` body, weighted by their costs, plus a small pull to the posture), under

- joint position limits (``mink.ConfigurationLimit``'s, gain 0.95) and arm joint velocity
  limits (``ArmIKConfig.max_joint_speed``), both as simple bounds on the step;
- collision avoidance (:class:`~beavr_sim.operator.collision.CollisionLimit`, mink's rows): hand
  and forearm against the table, palm against the upper arm and the base (self-collision), palm
  and forearm against the body (a humanoid's torso and head), every pair of arm links the twin's
  guard checks against each other (MuJoCo's collision filter: not welded together, not parent
  and child, not excluded by the MJCF; less pairs within the margin at home), and the arm's
  moving links against the back face of the guard's workspace box, as a velocity damper: one
  step closes at most ``collision_gain`` of the gap above the margin. Without the arm-link
  pairs and the wall, the IK could step into a pose the guard refuses (forearm on the
  shoulder, elbow behind the box) and, resynced to the held action, take the same step again
  every tick.

The QP is assembled here and solved with DAQP directly: ``mink.solve_ik`` builds the same
problem over all 23 joints through generic task and limit objects, which took most of the
operator's tick. The finger joints are not solved here; the caller sets them (the retargeted
values) so the collision geometry of the fingers is where the fingers are, and the QP cannot
satisfy a collision constraint by moving fingers the hand will not move.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import mink
import mujoco
import numpy as np

from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.operator import kernels
from beavr_sim.operator.collision import CollisionLimit
from beavr_sim.operator.obstacles import (
    Obstacle,
    add_obstacles,
    obstacle_geoms,
    place_obstacles,
)
from beavr_sim.operator.qp import StepQP
from beavr_sim.robots.embodiment import BODY_PREFIX, Embodiment, JointIndex
from beavr_sim.robots.parts import LEAP_HAND
from beavr_sim.workcell import TABLE_WORKSPACE_BOX

#: Hand bodies whose geoms are checked: the hand's ``collision_bodies``, the palm and the
#: fingertip links (the parts that reach furthest; fewer pairs keep the IK well under a
#: millisecond). The LEAP hand's:
HAND_BODIES = LEAP_HAND.collision_bodies

#: Name of the IK scene's wall on the back face of the twin guard's workspace box.
BACK_WALL = "ik_back_wall"
#: Half thickness (m) of that wall.
_WALL_HALF = 0.05


@dataclass(frozen=True)
class ArmIKConfig:
    """Costs, limits and solver settings of the operator's arm IK.

    Costs weigh the hand's position error (per metre), orientation error (per radian) and the
    pull of every arm joint to the posture (per radian), as mink's task costs do (squared in
    the objective). ``lm_damping`` adds ``lm_damping * |weighted error|^2`` and ``damping`` a
    constant to the Hessian's diagonal. ``collision_gain``: fraction of the gap above
    ``collision_margin`` one step may close, once closer than ``collision_detection``.
    """

    position_cost: float = 1.0
    orientation_cost: float = 0.5
    posture_cost: float = 1e-2
    lm_damping: float = 1e-3
    damping: float = 1e-4
    max_joint_speed: float = 2.0  # rad/s, under the xArm7's 180 deg/s
    collision_margin: float = 0.002  # m kept between the checked geoms
    collision_detection: float = 0.03  # m at which avoidance starts acting
    collision_gain: float = 0.85
    collision_avoidance: bool = True
    iterations: int = 1

    def __post_init__(self) -> None:
        for name in ("position_cost", "orientation_cost", "max_joint_speed", "collision_detection"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("posture_cost", "lm_damping", "damping", "collision_margin"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0 < self.collision_gain <= 1:
            raise ValueError(f"collision_gain must be in (0, 1], got {self.collision_gain!r}")
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")


#: mink.ConfigurationLimit's default gain: a step goes at most this fraction of the way to a
#: joint limit.
JOINT_LIMIT_GAIN = 0.95


def _only(joints: JointIndex, effector: str) -> JointIndex:
    """The part of ``joints`` that is ``effector``'s (arm then hand)."""
    sl = joints.slices[effector]
    return JointIndex(
        names=joints.names[sl],
        qpos_adr=joints.qpos_adr[sl],
        qvel_adr=joints.qvel_adr[sl],
        actuator_ids=joints.actuator_ids[sl],
        lower=joints.lower[sl],
        upper=joints.upper[sl],
        home=joints.home[sl],
        slices={effector: slice(0, sl.stop - sl.start)},
    )


def _body_geoms(model: mujoco.MjModel, body: str) -> list[int]:
    return [g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body(body).id]


def _colliding_geoms(model: mujoco.MjModel, body: int) -> list[int]:
    return [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] == body and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]


def _in_subtree(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


def checked_link_pairs(model: mujoco.MjModel, root: str, hand: str) -> list[tuple[int, int]]:
    """Pairs of arm links (bodies from ``root`` down to, not including, ``hand``'s subtree)
    that MuJoCo's collision filter lets collide, as the twin's guard checks them: bodies not
    welded together, not a weld parent and child (unless the model turns that filter off) and
    not excluded by the MJCF. Only bodies with colliding geoms are listed."""
    r, h = model.body(root).id, model.body(hand).id
    links = [
        b
        for b in range(model.nbody)
        if _in_subtree(model, b, r) and not _in_subtree(model, b, h) and _colliding_geoms(model, b)
    ]
    excluded = {int(s) for s in model.exclude_signature}
    filter_parent = not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    weld, parent = model.body_weldid, model.body_parentid
    pairs = []
    for i, b1 in enumerate(links):
        for b2 in links[i + 1 :]:
            w1, w2 = int(weld[b1]), int(weld[b2])
            if w1 == w2 or ((min(b1, b2) << 16) + max(b1, b2)) in excluded:
                continue
            if filter_parent and w1 and w2 and (w1 == weld[parent[w2]] or w2 == weld[parent[w1]]):
                continue
            pairs.append((b1, b2))
    return pairs


class ArmIK:
    """Arm joint targets for one effector's hand pose target."""

    #: Whether the last :meth:`step` made no progress: no iteration's QP had a solution (e.g.
    #: the hand already closer to the table than the margin), so the arm holds this period.
    infeasible: bool = False
    #: QP iterations without a solution since construction (a partial step counts too).
    infeasible_iterations: int = 0
    #: DAQP's exit flag of the latest iteration without a solution (None before any).
    last_exitflag: int | None = None

    def __init__(
        self, embodiment: Embodiment, effector: str, dt: float, config: ArmIKConfig | None = None
    ):
        self.config = config or ArmIKConfig()
        self.dt = float(dt)
        name = embodiment.effector(effector).name  # raises with the valid names
        spec_e = next(e for e in embodiment.spec.effectors if e.name == name)
        self.single = Embodiment(
            dataclasses.replace(
                embodiment.spec, name=f"{embodiment.name}:{effector}", effectors=(spec_e,)
            )
        )
        self.effector = self.single.effectors[0]
        lower, upper = embodiment.spec.guard_box or TABLE_WORKSPACE_BOX
        #: The guard's workspace box (its default for this embodiment): the arm's moving links
        #: keep in front of its back face, a wall in the IK's scene.
        self.guard_box = (tuple(map(float, lower)), tuple(map(float, upper)))
        #: The task's fixtures the hand and forearm keep off (see :meth:`set_obstacles`).
        self.obstacles: tuple[Obstacle, ...] = ()
        self.model = self._scene_spec().compile()
        if self.model.nq != self.model.nv:
            raise ValueError("ArmIK expects a robot-only model (hinge and slide joints)")
        every = self.single.bind(self.model)
        #: This effector's joints (arm then hand); the body, if any, holds its home pose.
        self.joints = _only(every, name)
        self.n_arm = len(self.effector.arm_joints)
        self._configuration = mink.Configuration(self.model)
        q = self._configuration.q.copy()
        q[every.qpos_adr[every.body]] = every.home[every.body]
        self._configuration.update(q)
        self._stale = False  # qpos changed since the last kinematics update
        self._hand_body = self.model.body(f"{self.effector.name}/hand").id
        self._arm_qpos = self.joints.qpos_adr[: self.n_arm].astype(np.int64)
        self._arm_dofs = self.joints.qvel_adr[: self.n_arm].astype(np.int64)
        self._hand_qpos = self.joints.qpos_adr[self.n_arm :]
        self._arm_lower = self.joints.lower[: self.n_arm]
        self._arm_upper = self.joints.upper[: self.n_arm]
        self._jac = np.zeros((6, self.model.nv))  # translation rows, then rotation rows
        self._weights = np.repeat([self.config.position_cost, self.config.orientation_cost], 3)
        self._no_rows = (np.zeros((0, self.n_arm)), np.zeros(0))
        self._qp = StepQP(self.n_arm)
        self._posture = self._configuration.q[self._arm_qpos].copy()
        #: Geom pairs of this arm's links that the twin's guard checks against each other and
        #: the IK keeps apart (:func:`checked_link_pairs`, less those within the margin at home).
        #: And the arm's moving link geoms against the back wall of the guard's box.
        self.self_collision_pairs, self.wall_pairs = self._arm_pairs()
        self.collision: CollisionLimit | None = None
        if self.config.collision_avoidance:
            self.collision = self._collision_limit()
        self.reset(self.joints.home)

    def _scene_spec(self) -> mujoco.MjSpec:
        """A fresh spec of the IK's scene: this effector's robot, the table, the obstacles."""
        spec = build_scene_spec(self.single, 64, 64)
        (x0, y0, z0), (_, y1, z1) = self.guard_box
        spec.worldbody.add_geom(
            name=BACK_WALL,
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[_WALL_HALF, (y1 - y0) / 2, (z1 - z0) / 2],
            pos=[x0 - _WALL_HALF, (y0 + y1) / 2, (z0 + z1) / 2],
            group=5,
            rgba=[0, 0, 0, 0],
        )
        add_obstacles(spec, self.obstacles)
        return spec

    def _arm_pairs(self) -> tuple[tuple[tuple[int, int], ...], tuple[tuple[int, int], ...]]:
        """The arm's link pairs the guard would refuse contact between, and its moving links
        against the back wall, geom by geom, without the geom pairs that touch or lie within
        the margin at the home pose (by design, e.g. overlapping shells of neighbouring links:
        the IK could not keep them apart)."""
        model, p = self.model, self.effector.name + "/"
        arm = self.single.spec.effectors[0].arm
        data = mujoco.MjData(model)
        data.qpos[:] = self._configuration.q
        data.qpos[self.joints.qpos_adr] = self.joints.home
        mujoco.mj_kinematics(model, data)
        clear = self.config.collision_margin

        def apart(g1: int, g2: int) -> bool:
            return mujoco.mj_geomDistance(model, data, g1, g2, 1.0, None) > clear

        links = checked_link_pairs(model, p + arm.root_body, p + "hand")
        pairs = [
            (g1, g2)
            for b1, b2 in links
            for g1 in _colliding_geoms(model, b1)
            for g2 in _colliding_geoms(model, b2)
            if apart(g1, g2)
        ]
        root = model.body(p + arm.root_body).id
        fixed = model.body_weldid[root]  # links that do not move with the arm's joints
        moving = {b for pair in links for b in pair if model.body_weldid[b] != fixed}
        wall = model.geom(BACK_WALL).id
        walls = [
            (g, wall) for b in sorted(moving) for g in _colliding_geoms(model, b) if apart(g, wall)
        ]
        return tuple(pairs), tuple(walls)

    def _collision_limit(self) -> CollisionLimit:
        """The watched pairs: hand and forearm against the table and the task's fixtures, palm
        against the upper arm and the body, forearm against the body, the arm's links against
        each other and against the back wall (:meth:`_arm_pairs`)."""
        model, p = self.model, self.effector.name + "/"
        arm = self.single.spec.effectors[0].arm
        hand_model = self.single.spec.effectors[0].hand
        hand = [g for b in hand_model.collision_bodies for g in _body_geoms(model, p + b)]
        palm = _body_geoms(model, p + hand_model.palm_body)
        forearm = [g for link in arm.forearm_links for g in _body_geoms(model, p + link)]
        upper = [g for link in arm.upper_arm_links for g in _body_geoms(model, p + link)]
        body = [
            g
            for g in range(model.ngeom)
            if model.body(model.geom_bodyid[g]).name.startswith(BODY_PREFIX)
            and (model.geom_contype[g] or model.geom_conaffinity[g])
        ]
        static = [model.geom("table_top").id, *obstacle_geoms(model, self.obstacles)]
        return CollisionLimit(
            model,
            geom_pairs=[
                (hand + forearm, static),
                (palm, upper + body),
                (forearm, body),
                *(([a], [b]) for a, b in self.self_collision_pairs + self.wall_pairs),
            ],
            spec=self._scene_spec(),
            minimum_distance_from_collisions=self.config.collision_margin,
            collision_detection_distance=self.config.collision_detection,
            gain=self.config.collision_gain,
        )

    def set_obstacles(self, obstacles: Sequence[Obstacle]) -> None:
        """The task's fixtures (:func:`~beavr_sim.operator.obstacles.fixture_obstacles` of the
        env after each reset): the hand and forearm keep off them as off the table (fingertips
        included: the twin's guard lets fingers only ``finger_tolerance`` into a fixture).

        The IK's model is robot-only, so fixtures of other shapes than the last (another task)
        build it again, with them as mocap bodies (tens of milliseconds); the same shapes are
        only moved. The joints and the posture are kept."""
        obstacles = tuple(obstacles)
        rebuild = [o.shape for o in obstacles] != [o.shape for o in self.obstacles]
        self.obstacles = obstacles
        if not self.config.collision_avoidance:
            return
        if rebuild:
            qpos = self._configuration.data.qpos.copy()
            self.model = self._scene_spec().compile()
            if self.model.body(f"{self.effector.name}/hand").id != self._hand_body:
                raise RuntimeError("obstacles changed the robot's body ids")  # appended last
            self._configuration = mink.Configuration(self.model)
            self._configuration.data.qpos[:] = qpos
            self.collision = self._collision_limit()
        place_obstacles(self.model, self._configuration.data, obstacles)
        self._stale = True  # kinematics (obstacle poses) updated when next needed

    def reset(self, q_effector: np.ndarray, posture: np.ndarray | None = None) -> None:
        """Start from this effector's joint positions (arm then hand, action order)."""
        q = self._configuration.q.copy()
        q[self.joints.qpos_adr] = q_effector
        self._configuration.update(q)
        self._stale = False
        target = q_effector if posture is None else posture
        self._posture = np.asarray(target, dtype=np.float64)[: self.n_arm].copy()

    @property
    def posture(self) -> np.ndarray:
        """The arm posture the IK regularises towards."""
        return self._posture.copy()

    def set_fingers(self, q_hand: np.ndarray) -> None:
        """Put the finger joints where the hand command puts them (collision geometry)."""
        self._configuration.data.qpos[self._hand_qpos] = q_hand
        self._stale = True  # kinematics updated when next needed (the step's start)

    @property
    def configuration(self) -> mink.Configuration:
        """The IK configuration, its kinematics up to date with its joints."""
        self._forward()
        return self._configuration

    def _forward(self) -> None:
        """Kinematics for the current joints, if they changed since the last update: one
        update per tick (fingers set, then the step) rather than one per change."""
        if self._stale:
            self._configuration.update()
            self._stale = False

    @property
    def q(self) -> np.ndarray:
        """This effector's joint positions (arm then hand) in the IK configuration."""
        return self._configuration.data.qpos[self.joints.qpos_adr]  # fancy index: a copy

    def T_world_hand(self) -> np.ndarray:
        data = self.configuration.data
        T = np.eye(4)
        T[:3, :3] = data.xmat[self._hand_body].reshape(3, 3)
        T[:3, 3] = data.xpos[self._hand_body]
        return T

    def step(self, T_world_target: np.ndarray, dt: float | None = None) -> np.ndarray:
        """One control period (or ``dt`` s: a command per hand frame) towards
        ``T_world_target``; returns the arm joint positions.

        An iteration whose QP has no solution leaves the joints as they are; :attr:`infeasible`
        says whether every iteration of this step failed (the arm did not move), and
        :attr:`infeasible_iterations` counts them, so the caller can report the hold."""
        T_world_target = np.asarray(T_world_target, dtype=np.float64)
        if T_world_target.shape != (4, 4) or not np.isfinite(T_world_target).all():
            raise ValueError(f"step needs a finite 4x4 pose, got shape {T_world_target.shape}")
        failed = 0
        period = self.dt if dt is None else float(dt)
        for _ in range(self.config.iterations):
            if not self._step(T_world_target, period / self.config.iterations):
                failed += 1
                self.last_exitflag = getattr(self._qp, "last_exitflag", None)
        self.infeasible = failed == self.config.iterations
        self.infeasible_iterations += failed
        return self._configuration.data.qpos[self._arm_qpos]  # fancy index: a copy

    def _step(self, T_world_target: np.ndarray, dt: float) -> bool:
        """One QP iteration; returns whether it had a solution (else the joints stay)."""
        cfg, model = self.configuration, self.model
        data, body = cfg.data, self._hand_body
        # Hand pose error in the world frame (position, and the rotation vector that takes the
        # current orientation to the target's), weighted; Jacobian of the hand body.
        mujoco.mj_jacBody(model, data, self._jac[:3], self._jac[3:], body)
        config = self.config
        qp = self._qp
        kernels.arm_qp(
            self._jac, self._arm_dofs, self._weights, T_world_target,
            data.xpos[body], data.xmat[body].reshape(3, 3), data.qpos, self._arm_qpos,
            self._posture, config.posture_cost**2, config.damping, config.lm_damping,
            config.max_joint_speed * dt, self._arm_lower, self._arm_upper, JOINT_LIMIT_GAIN,
            qp.H, qp.c, qp.lower, qp.upper,
        )  # fmt: skip
        A, h = self._no_rows
        if self.collision is not None:
            # dt = 1: the bound is on the step itself (a velocity damper per tick).
            _, rows, h = self.collision.active_rows(cfg, 1.0)
            A = rows.take(self._arm_dofs, axis=1)  # a C-contiguous copy
        dq = qp.solve(A, h)
        if dq is None:  # infeasible (e.g. already in collision): hold, reported by step
            return False
        data.qpos[self._arm_qpos] += dq
        self._stale = True
        return True
