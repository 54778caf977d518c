"""The twin as safety guard: a command that is unsafe on the twin's model is refused before it
is applied (and, when mirroring, before it reaches any hardware); that effector holds its last
safe command.

Rules, per effector, cheapest first (a command fails on the first rule it breaks):

1. ``non-finite``: a NaN or inf target.
2. ``joint limit``: a target outside the model's range shrunk by ``limit_margin``.
3. ``velocity`` / ``acceleration``: against the last accepted command, one control period
   ago (only when the guard knows it: streaming, not a configuration checked alone). The
   velocity rule refuses a joint that the speed caps' rate limit
   (:class:`~beavr_sim.twin.rate_limit.JointRateLimit`, :attr:`CollisionGuard.rate_limit`)
   would shorten over that period. The twin clamps every joint's step with the same limit
   before its guard checks, so there the velocity rule is a second line; other callers (the
   mirror's catch-up, the hardware guard CLI) meet it first.
4. ``workspace``: a moving robot geom leaves its effector's box (default: the volume over the
   table). The table top is the box's floor, checked on each geom's exact world bounding box:
   unlike a contact depth, it does not depend on how far a link has passed into a thin table.
5. ``contact``: a robot geom penetrates the static scene or another robot geom (another
   link, the other arm) by more than its tolerance. The static scene is what the robot cannot
   push: the table, anything welded to the world, the task's fixtures (mocap bodies, e.g. the
   box tape and lantern go onto, and bodies welded to them; posed as the twin has them) and a
   humanoid's body. Finger links get ``finger_tolerance`` against all of it: a task may need
   the fingers on a fixture. Contacts with the task's free objects are the point of
   manipulation and never block.

Rules 4 and 5 hold along the whole path from the last accepted command, not only at its end:
the path is sampled so that no robot geom moves more than ``path_resolution`` between two
samples, so a link cannot step over the table top or through another link between ticks.

The check is kinematic, on a private copy of the twin's model in which only robot-static and
robot-robot pairs can collide (objects as the twin has them now). The operator's IK already
keeps within these limits, so in normal operation the guard never fires; it is the last line
against what the IK cannot see (a stale command, a bad retarget, the other arm, a corrupted
message).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import mujoco
import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.robots.embodiment import BODY_PREFIX, Embodiment, JointIndex
from beavr_sim.twin import kernels
from beavr_sim.twin.extents import GeomExtents
from beavr_sim.twin.rate_limit import JointRateLimit
from beavr_sim.workcell import TABLE_WORKSPACE_BOX

_ROBOT, _STATIC = 1, 2  # contype / conaffinity bits of the guard's private model
RULES = ("non-finite", "joint limit", "velocity", "acceleration", "workspace", "contact")


@dataclass(frozen=True)
class Workspace:
    """An axis-aligned box in the world frame (m) that an effector's links stay inside."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lower, float), np.asarray(self.upper, float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and (lo < hi).all()):
            raise ValueError(
                f"workspace needs finite lower < upper, 3 values each, got {self.lower}, {self.upper}"
            )


#: The volume over the table (:data:`beavr_sim.workcell.TABLE_WORKSPACE_BOX`).
TABLE_WORKSPACE = Workspace(*TABLE_WORKSPACE_BOX)


@dataclass(frozen=True)
class GuardConfig:
    #: Penetration (m) a commanded configuration may have against the table or the robot
    #: itself: a few millimetres for the difference between target and reached pose.
    tolerance: float = 0.005
    #: The same for finger links: a grasp near the table commands the fingertips a little into
    #: it and the hand's position control presses with a small force; that is wanted, a finger
    #: driven centimetres into the table is not.
    finger_tolerance: float = 0.02
    #: How far (m) a link may leave its workspace box (below the table top, for the floor).
    workspace_tolerance: float = 0.005
    #: The same for finger links: the bundled demonstrations press fingertips up to 9.2 mm
    #: below the table top (exact geom boxes); 12 mm keeps them and refuses a hand driven
    #: into the table.
    finger_workspace_tolerance: float = 0.012
    #: Targets must lie this far (rad) inside the model's joint range.
    limit_margin: float = 0.0
    #: Joint speed caps (rad/s): the xArm7's own cap (pi; the operator's IK uses 2) and the
    #: LEAP hand's (its retargeting steps at most 3).
    arm_max_velocity: float = math.pi
    hand_max_velocity: float = 8.0
    #: Joint acceleration caps (rad/s^2), between consecutive accepted commands. The operator
    #: starts and stops a joint within one tick (up to 109 arm / 128 hand measured on the
    #: bundled traces), so these sit above that and below what the speed caps allow.
    arm_max_acceleration: float = 150.0
    hand_max_acceleration: float = 250.0
    #: Workspace box per effector name; effectors not listed get the embodiment's
    #: ``guard_box``, or :data:`TABLE_WORKSPACE`.
    workspaces: Mapping[str, Workspace] = field(default_factory=dict)
    #: Path sampling: no robot geom moves more than this (m) between two checked samples ...
    path_resolution: float = 0.01
    #: ... with at most this many samples per command (a larger step is refused by the
    #: velocity rule first).
    max_path_samples: int = 12

    def __post_init__(self) -> None:
        for name in (
            "tolerance",
            "finger_tolerance",
            "workspace_tolerance",
            "finger_workspace_tolerance",
            "limit_margin",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for name in (
            "arm_max_velocity",
            "hand_max_velocity",
            "arm_max_acceleration",
            "hand_max_acceleration",
            "path_resolution",
        ):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not (isinstance(self.max_path_samples, int) and self.max_path_samples >= 1):
            raise ValueError(
                f"max_path_samples must be an integer >= 1, got {self.max_path_samples!r}"
            )
        for name, box in self.workspaces.items():
            if not isinstance(box, Workspace):
                raise ValueError(f"workspaces[{name!r}] must be a Workspace, got {box!r}")


def hand_joints(embodiment: Embodiment, joints: JointIndex) -> np.ndarray:
    """Per action index: whether it is a hand joint (else an arm joint, or the body's)."""
    hand = np.zeros(joints.size, dtype=bool)
    for e in embodiment.effectors:
        sl = joints.slices[e.name]
        hand[sl.start + len(e.arm_joints) : sl.stop] = True
    return hand


def max_velocity(embodiment: Embodiment, joints: JointIndex, config: GuardConfig) -> np.ndarray:
    """Per action index: the joint's speed cap (rad/s), the hand's or the arm's: the
    :class:`~beavr_sim.twin.rate_limit.JointRateLimit` of the guard's velocity rule and of the
    twin's per-tick step limit (with the guard off as well). An arm whose servo has a lower
    speed cap than ``config.arm_max_velocity`` (:class:`~beavr_sim.robots.parts.ArmServo`, a
    robot file's ``max_velocity_deg_s``) keeps its own, and so does a hand with a lower cap
    (``HandModel.max_velocity``: a robot file's hand from a model file)."""
    hand = hand_joints(embodiment, joints)
    caps = np.where(hand, config.hand_max_velocity, config.arm_max_velocity)
    index, v_max, _ = embodiment.servo_joints()
    caps[index] = np.minimum(caps[index], v_max)
    for e, spec in zip(embodiment.effectors, embodiment.spec.effectors, strict=True):
        if spec.hand.max_velocity is not None:
            sl = joints.slices[e.name]
            fingers = slice(sl.start + len(e.arm_joints), sl.stop)
            caps[fingers] = np.minimum(caps[fingers], spec.hand.max_velocity)
    return caps


@dataclass(frozen=True)
class GuardVerdict:
    """Which effectors' commands are refused, why, and the contacts that refused them."""

    blocked: tuple[str, ...]
    #: (geom 1, geom 2, penetration depth in m) per offending contact; an unnamed geom is
    #: called ``{body}/geom{id}``.
    contacts: tuple[tuple[str, str, float], ...] = ()
    #: Per blocked effector: the rule it broke and the joints or geoms, e.g.
    #: ``"workspace: right/index_distal 13.0 mm below the box (z)"``.
    reasons: Mapping[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.blocked

    def reason(self) -> str:
        return "; ".join(f"{e}: {r}" for e, r in sorted(self.reasons.items()))


class CollisionGuard:
    """Checks full commanded actions (action order) against the twin's model.

    ``dt``: the control period (s) the velocity and acceleration rules use; ``None`` turns them
    off (each command is then only checked as a configuration and along its path).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        embodiment: Embodiment,
        joints: JointIndex,
        config: GuardConfig | None = None,
        dt: float | None = None,
    ):
        self.config = config = config or GuardConfig()
        self.joints = joints
        self.dt = dt
        names = [e.name for e in embodiment.effectors]
        for name in config.workspaces:
            check_name("effector", name, names)
        self.slices = dict(joints.slices)
        # Per action index: effector, joint name, limits, speed and acceleration caps.
        self._effector_of = np.empty(joints.size, dtype=object)
        for e in embodiment.effectors:
            self._effector_of[self.slices[e.name]] = e.name
        #: Per action index: a hand joint (else an arm joint).
        self.hand_joints = hand = hand_joints(embodiment, joints)
        self._lower = joints.lower + config.limit_margin
        self._upper = joints.upper - config.limit_margin
        #: Per action index: the speed (rad/s) and acceleration (rad/s^2) caps.
        self.max_velocity = max_velocity(embodiment, joints, config)
        #: The velocity rule refuses a joint this limit would shorten in one period.
        self.rate_limit = JointRateLimit.of(self.max_velocity)
        self.max_acceleration = np.where(
            hand, config.hand_max_acceleration, config.arm_max_acceleration
        )

        # Owner of each geom: the effector whose subtree it is in; "static" for bodies welded
        # to the world (table), the fixtures (mocap bodies and bodies welded to them: static
        # within an episode) and the robot's body; None for objects (free bodies, never
        # guarded).
        self._owner: list[str | None] = []
        self._geom_names: list[str] = []
        finger_bodies = {
            int(model.jnt_bodyid[model.joint(j).id])
            for e in embodiment.effectors
            for j in e.hand_joints
        }
        for b in range(model.nbody):  # bodies below a finger joint are finger links too
            if int(model.body_parentid[b]) in finger_bodies:
                finger_bodies.add(b)
        self._tolerance = np.full(model.ngeom, config.tolerance)
        moving, finger_moving = [], []
        for g in range(model.ngeom):
            body = int(model.geom_bodyid[g])
            body_name = model.body(body).name
            owner = next((e for e in names if body_name.startswith(e + "/")), None)
            weld = int(model.body_weldid[body])
            if owner is None and (
                weld == 0 or model.body_mocapid[weld] >= 0 or body_name.startswith(BODY_PREFIX)
            ):
                # Welded to the world or to a fixture, or the robot's body (torso, head), which
                # holds its pose: an obstacle for every arm (the body placed where the
                # commanded action puts it).
                owner = "static"
            self._owner.append(owner)
            if body in finger_bodies:
                self._tolerance[g] = config.finger_tolerance
            elif owner == "static":
                self._tolerance[g] = np.inf  # the robot geom's tolerance decides
            self._geom_names.append(model.geom(g).name or f"{body_name or 'world'}/geom{g}")
            collides = model.geom_contype[g] != 0 or model.geom_conaffinity[g] != 0
            if owner not in (None, "static") and collides and int(model.body_weldid[body]) != 0:
                moving.append(g)
                finger_moving.append(body in finger_bodies)
        # Workspace rule: the moving robot geoms, their effector's box and tolerance.
        self._moving = np.array(moving, dtype=int)
        self._extents = GeomExtents(model, self._moving)
        owners = [self._owner[g] for g in moving]
        default_box = TABLE_WORKSPACE
        if embodiment.spec.guard_box is not None:
            default_box = Workspace(*embodiment.spec.guard_box)
        boxes = [config.workspaces.get(o, default_box) for o in owners]
        slack = np.where(
            finger_moving, config.finger_workspace_tolerance, config.workspace_tolerance
        )[:, None]
        self._slack = slack[:, 0]
        self._box_lower = np.array([b.lower for b in boxes]).reshape(-1, 3) - slack
        self._box_upper = np.array([b.upper for b in boxes]).reshape(-1, 3) + slack
        self._moving_owner = np.array(owners, dtype=object)
        self._outside = np.zeros(len(moving), dtype=np.bool_)
        self._codes = np.zeros(joints.size, dtype=np.int64)
        self._not_fast = np.zeros(joints.size, dtype=np.bool_)
        self.joint_names = joints.names
        kernels.warm_up()
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
        #: Refusals per rule (every rule listed, zeros included).
        self.refusals_by_rule = dict.fromkeys(RULES, 0)
        self._velocity = np.zeros(joints.size)  # of the last accepted command
        # Preallocated for the per-tick path: the moving geoms' centres at the path's ends
        # (the end of one check is the start of the next when accepted), samples, scratch.
        n_moving = len(self._moving)
        self._start, self._end = np.zeros((n_moving, 3)), np.zeros((n_moving, 3))
        self._scratch = np.zeros((n_moving, 3))
        self._sample = np.zeros(joints.size)
        self._cached_at = np.zeros(joints.size)  # the action ``_start`` belongs to
        self._cached = False
        self._qpos_adr = np.asarray(joints.qpos_adr, dtype=np.int64)
        self._qpos = self.data.qpos  # views into the private MjData
        self._geom_xpos = self.data.geom_xpos

    # ------------------------------------------------------------------ rules
    def reset(self) -> None:
        """Forget the motion history (after an env reset: the robot stands still)."""
        self._velocity[:] = 0.0
        self._cached = False

    def set_fixtures(self, mocap_pos: np.ndarray, mocap_quat: np.ndarray) -> None:
        """Where the fixtures (the twin's mocap bodies) stand: a reset places them anew."""
        if self.model.nmocap:
            self.data.mocap_pos[:] = mocap_pos
            self.data.mocap_quat[:] = mocap_quat

    def still(self) -> None:
        """No new command this tick: the robot holds (its commanded velocity is zero)."""
        self._velocity[:] = 0.0

    def _joint_rules(
        self, action: np.ndarray, previous: np.ndarray | None, reasons: dict[str, str]
    ) -> None:
        codes = self._codes
        has_previous = previous is not None and self.dt is not None
        if has_previous:
            fast = self.rate_limit.exceeds(action - previous, self.dt)
        else:
            previous, fast = action, self._not_fast
        if not kernels.joint_rules(
            action,
            previous,
            has_previous,
            fast,
            self._velocity,
            self._lower,
            self._upper,
            self.max_acceleration,
            self.dt or 0.0,
            codes,
        ):
            return
        names = self.joint_names
        for i in np.flatnonzero(codes):
            effector, code, q = self._effector_of[i], codes[i], action[i]
            if effector in reasons:
                continue
            if code == kernels.NON_FINITE:
                reasons[effector] = f"non-finite: {names[i]} = {q}"
            elif code == kernels.LIMIT:
                below = q < self._lower[i]
                limit = self._lower[i] if below else self._upper[i]
                reasons[effector] = (
                    f"joint limit: {names[i]} = {q:.4f} {'<' if below else '>'} {limit:.4f} rad"
                )
            elif code == kernels.VELOCITY:
                speed = abs(q - previous[i]) / self.dt
                reasons[effector] = (
                    f"velocity: {names[i]} {speed:.3g} > {self.max_velocity[i]:.3g} rad/s"
                )
            else:
                accel = abs((q - previous[i]) / self.dt - self._velocity[i]) / self.dt
                reasons[effector] = (
                    f"acceleration: {names[i]} {accel:.3g} > {self.max_acceleration[i]:.3g} rad/s^2"
                )

    def _pose(self, action: np.ndarray, qpos_now: np.ndarray, out: np.ndarray) -> None:
        """Kinematics of ``action`` (objects from ``qpos_now``); the moving geoms' centres
        into ``out``."""
        kernels.set_robot_qpos(self._qpos, qpos_now, self._qpos_adr, action)
        mujoco.mj_kinematics(self.model, self.data)
        kernels.gather_rows(self._geom_xpos, self._moving, out)

    def _workspace_reasons(
        self, centre: np.ndarray, half: np.ndarray, reasons: dict[str, str], where: str
    ) -> None:
        low, high = centre - half, centre + half
        out_low, out_high = low < self._box_lower, high > self._box_upper
        for k in np.flatnonzero(self._outside):
            owner = self._moving_owner[k]
            if owner in reasons:
                continue
            axis = int(np.argmax(out_low[k] | out_high[k]))
            slack = self._slack[k]
            if out_low[k, axis]:
                depth, side = self._box_lower[k, axis] + slack - low[k, axis], "below"
            else:
                depth, side = high[k, axis] - self._box_upper[k, axis] + slack, "above"
            reasons[owner] = (
                f"workspace: {self._geom_names[self._moving[k]]} {1e3 * depth:.1f} mm {side} "
                f"the box ({'xyz'[axis]}; tolerance {1e3 * slack:.0f} mm){where}"
            )

    def _geometry_rules(self, reasons: dict[str, str], offending: list, where: str) -> None:
        """Workspace and contact rules at the pose last computed by :meth:`_pose`."""
        m, d = self.model, self.data
        centre, half = self._extents.compute(d)
        if kernels.outside(centre, half, self._box_lower, self._box_upper, self._outside):
            self._workspace_reasons(centre, half, reasons, where)
        mujoco.mj_collision(m, d)
        n = d.ncon
        if not n:
            return
        contacts = d.contact
        g1, g2, dist = contacts.geom1[:n], contacts.geom2[:n], contacts.dist[:n]
        deep = dist < -np.minimum(self._tolerance[g1], self._tolerance[g2])
        for i in np.flatnonzero(deep):
            a, b = self._geom_names[g1[i]], self._geom_names[g2[i]]
            offending.append((a, b, float(-dist[i])))
            for owner in {self._owner[g1[i]], self._owner[g2[i]]} - {"static", None}:
                reasons.setdefault(owner, f"contact: {a} - {b} {1e3 * -dist[i]:.1f} mm deep{where}")

    def check(
        self,
        action: np.ndarray,
        qpos_now: np.ndarray,
        previous: np.ndarray | None = None,
        reference: np.ndarray | None = None,
    ) -> GuardVerdict:
        """Would ``action`` (joint targets, action order) be unsafe, objects as in ``qpos_now``?

        With ``previous`` (the last accepted action) the velocity and acceleration rules apply
        and the geometric rules hold along the path from it. ``reference``: where the velocity
        and acceleration rules measure from, one control period before ``action`` takes
        effect (default ``previous``; the event-driven twin passes the target its physics
        last stepped to, while ``previous`` is the newest accepted command, the path the
        hardware travels). Effectors that break a joint rule are checked geometrically at
        ``previous`` (they would hold there); without ``previous`` at their (unsafe) targets,
        clipped to finite.
        """
        action = np.asarray(action, dtype=np.float64)
        self.checks += 1
        reasons: dict[str, str] = {}
        self._joint_rules(action, previous if reference is None else reference, reasons)
        target = action
        if reasons:
            target = action.copy()
            for name in reasons:
                sl = self.slices[name]
                target[sl] = previous[sl] if previous is not None else self.joints.home[sl]
        offending: list[tuple[str, str, float]] = []
        end = self._end
        self._pose(target, qpos_now, end)
        self._geometry_rules(reasons, offending, "")
        if previous is not None:
            start = self._start
            if not (self._cached and kernels.same(self._cached_at, previous)):
                self._pose(previous, qpos_now, start)
            step = kernels.largest_move(end, start)
            n = min(self.config.max_path_samples, math.ceil(step / self.config.path_resolution))
            sample = self._sample
            for k in range(1, n):
                s = k / n
                kernels.lerp(previous, target, s, sample)
                self._pose(sample, qpos_now, self._scratch)
                self._geometry_rules(reasons, offending, f" at {100 * s:.0f} % of the path")
        # The next command's path starts at this one's end when it is accepted as it is.
        self._start, self._end = self._end, self._start
        self._cached_at[:] = target
        self._cached = True
        blocked = tuple(sorted(reasons))
        if blocked:
            self.refusals += 1
            for reason in reasons.values():
                self.refusals_by_rule[reason.split(":", 1)[0]] += 1
        return GuardVerdict(blocked, tuple(offending), dict(sorted(reasons.items())))

    def filter(
        self,
        action: np.ndarray,
        previous: np.ndarray,
        qpos_now: np.ndarray,
        slices: Mapping[str, slice] | None = None,
        reference: np.ndarray | None = None,
        commit: bool = True,
    ) -> tuple[np.ndarray, GuardVerdict]:
        """``action`` with every refused effector's slice set back to ``previous`` (the last
        accepted action), and the verdict; ``reference`` as in :meth:`check`.

        ``commit``: the result takes effect one control period after ``reference`` (it becomes
        the motion the acceleration rule compares the next command's with; see
        :meth:`commit`). The event-driven twin checks several commands per period and
        commits once, when its physics steps.

        The held action is not checked again: if the robot is already unsafe (e.g. placed
        there by a reset) holding is still the safest thing.
        """
        slices = self.slices if slices is None else slices
        verdict = self.check(action, qpos_now, previous, reference)
        safe = np.array(action, dtype=np.float64, copy=True)
        for name in verdict.blocked:
            safe[slices[name]] = previous[slices[name]]
        if commit:
            self.commit(safe, previous if reference is None else reference)
        return safe, verdict

    def commit(self, action: np.ndarray, reference: np.ndarray) -> None:
        """``action`` took effect one control period after ``reference``: its velocity is
        what the next command's acceleration is measured against."""
        if self.dt is not None:
            self._velocity = (np.asarray(action, dtype=np.float64) - reference) / self.dt
