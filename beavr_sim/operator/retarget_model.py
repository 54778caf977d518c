"""Retargeting for a hand from a model file (:mod:`beavr_sim.robots.hand_file`).

Human keypoints (the 26 canonical joints in the palm frame, :mod:`beavr_sim.wire.hand`) map to
one fingertip target per hand finger in the hand's root frame:

    target_f = R_palm_root @ (scale_f * human_tip_h)

where ``h`` is the human finger the file maps to ``f`` and ``scale_f`` is derived, as LEAP's
are in :mod:`beavr_sim.operator.retarget`: the hand finger's reach at home (root origin ->
fingertip) over the human template's wrist -> tip length for ``h``. Each tick a few damped
least-squares steps on the fingertip positions move the joints toward the targets; the step
is clipped to the joint limits, to ``speed_fraction * max_velocity_deg_s * dt`` and to a
change of speed of at most ``max_acceleration * dt`` from the previous step (under the twin guard's hand
acceleration cap). The per-tick call never raises: a non-finite or missing keypoint set holds
the last command (counted in ``holds``); a finger whose human tip is untracked holds.

:meth:`ModelHandRetargeter.retarget` and :meth:`~ModelHandRetargeter.reset` are the
operator's interface (:class:`~beavr_sim.operator.operator.EffectorOperator` uses them as it
uses :class:`~beavr_sim.operator.retarget.LeapRetargeter`'s), with :attr:`~ModelHandRetargeter.map`
for the views.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.operator.retarget import human_template
from beavr_sim.robots.hand_file import ModelHand, tip_points
from beavr_sim.wire.hand import JOINT_INDEX, N_JOINTS


@dataclass(frozen=True)
class ModelRetargetConfig:
    """Solver settings of :class:`ModelHandRetargeter`."""

    damping: float = 0.02  # m: the DLS damping (units of fingertip error)
    iterations: int = 4  # DLS steps per tick
    thumb_weight: float = 2.0  # the thumb's tip error weight (pinches need it)
    #: rad/s^2: how much a joint's speed may change from one step to the next (the twin
    #: guard refuses hand joints above 250: a reversal at full speed would pass it at 30 Hz
    #: only for caps under 3.75 rad/s).
    max_acceleration: float = 200.0
    #: The share of the hand's speed cap (``max_velocity_deg_s``, the twin's and the guard's)
    #: the retargeter moves at, as the arm IK's 2 rad/s sits under the xArm's pi: commands
    #: that come per hand frame add up within one control period, and the twin shortens a
    #: joint's steps beyond its cap from the last physics step.
    speed_fraction: float = 2 / 3


class ModelHandMap:
    """The human palm frame -> hand frame map of a model-file hand, for views: the hand part's
    ``hand`` frame is the human palm frame's convention, so a point maps by its finger's
    scale alone."""

    def __init__(self, hand: ModelHand, scales: dict[str, float]):
        human = dict(hand.spec.human_fingers)
        self.scales = scales
        middle = scales.get("middle", float(np.mean(list(scales.values()))))
        #: Scale of each of the 26 canonical joints (its finger's; the middle finger's else).
        self.joint_scales = np.full(N_JOINTS, middle)
        for finger, scale in scales.items():
            for name, i in JOINT_INDEX.items():
                if name.startswith(f"{human[finger]}_") and not name.endswith("metacarpal"):
                    self.joint_scales[i] = scale

    def skeleton(self, keypoints_palm: np.ndarray) -> np.ndarray:
        """All 26 joints mapped to the hand frame (each with its finger's scale)."""
        return self.joint_scales[:, None] * keypoints_palm


def finger_scales(hand: ModelHand, side: str) -> dict[str, float]:
    """Per hand finger: its reach at home over the template's wrist -> tip length of the human
    finger the file maps to it."""
    template = human_template(side)
    human = dict(hand.spec.human_fingers)
    return {
        f: hand.reach[f] / float(np.linalg.norm(template[JOINT_INDEX[f"{human[f]}_tip"]]))
        for f, _, _ in hand.tips
    }


class ModelHandRetargeter:
    """Human palm-frame keypoints -> joint targets of a model-file hand, one call per tick."""

    #: The operator's interface: a damped least-squares step always has a solution.
    infeasible: bool = False
    last_exitflag: int | None = None

    def __init__(
        self,
        hand: ModelHand,
        side: str,
        config: ModelRetargetConfig | None = None,
        dt: float = 1 / 30,
    ):
        self.hand, self.config = hand, config or ModelRetargetConfig()
        #: The period :meth:`retarget` steps over (the operator's control period).
        self.dt = float(dt)
        self.scales = finger_scales(hand, side)
        self.map = ModelHandMap(hand, self.scales)
        human = dict(hand.spec.human_fingers)
        self._tip_rows = np.array([JOINT_INDEX[f"{human[f]}_tip"] for f, _, _ in hand.tips])
        self._scale = np.array([self.scales[f] for f, _, _ in hand.tips])
        self._weight = np.array(
            [self.config.thumb_weight if f == hand.spec.thumb else 1.0 for f, _, _ in hand.tips]
        )
        self._data = mujoco.MjData(hand.model)
        self.q = hand.home.copy()
        self._v = np.zeros(hand.n_joints)  # rad/s of the last step
        self.holds = 0
        self._jac = np.zeros((3, hand.model.nv))
        self._finger_dofs = [_finger_dofs(hand, kind, i) for _, kind, i in hand.tips]

    def reset(self, q: np.ndarray | None = None) -> None:
        """Restart from joints ``q`` (the hand's joint order; default its home), at rest."""
        q = self.hand.home if q is None else np.asarray(q, dtype=float)
        if q.shape != (self.hand.n_joints,) or not np.isfinite(q).all():
            raise ValueError(
                f"reset needs {self.hand.n_joints} finite joint values, got shape {q.shape}"
            )
        self.q = np.clip(q, self.hand.lower, self.hand.upper)
        self._v[:] = 0.0

    def retarget(
        self,
        keypoints_palm: np.ndarray,
        tracked: np.ndarray | None = None,
        dt: float | None = None,
    ) -> np.ndarray:
        """Joint targets for one hand frame (palm-frame keypoints, per-joint tracked flags),
        one step of ``dt`` (default :attr:`dt`): the operator's call."""
        return self.step(keypoints_palm, self.dt if dt is None else dt, tracked)

    def root_targets(self, keypoints: np.ndarray) -> np.ndarray:
        """The fingertip targets (n_fingers x 3, root frame) of palm-frame ``keypoints``."""
        return self.targets(keypoints) @ self.hand.R_palm_root.T

    def targets(self, keypoints: np.ndarray) -> np.ndarray:
        """The fingertip targets (n_fingers x 3) of palm-frame ``keypoints`` in the hand
        part's ``hand`` frame (the palm frame's convention, at the root's origin)."""
        return keypoints[self._tip_rows] * self._scale[:, None]

    def tips(self, q: np.ndarray) -> np.ndarray:
        """The fingertips (root frame) at joints ``q``."""
        self._data.qpos[self.hand.qpos_ids] = q
        mujoco.mj_kinematics(self.hand.model, self._data)
        return tip_points(self.hand, self._data)

    def step(
        self, keypoints: np.ndarray | None, dt: float, tracked: np.ndarray | None = None
    ) -> np.ndarray:
        """Joint targets after one tick of ``dt`` seconds; holds on bad input, never raises.
        ``tracked``: per-joint flags (None: all); a finger whose human tip is untracked (its
        position then need not be finite) holds its joints."""
        try:
            held = np.zeros(len(self.hand.tips), dtype=bool)
            if tracked is not None:
                flags = np.asarray(tracked, dtype=bool)
                held = ~flags[self._tip_rows] if flags.shape == (N_JOINTS,) else ~held
            ok = (keypoints is not None and np.shape(keypoints) == (N_JOINTS, 3)
                  and not held.all() and np.isfinite(dt) and dt > 0
                  and bool(np.isfinite(np.asarray(keypoints, dtype=float)[
                      self._tip_rows[~held]]).all()))  # fmt: skip
        except (TypeError, ValueError, IndexError):
            ok = False
        if not ok:
            self.holds += 1
            self._v[:] = 0.0
            return self.q.copy()
        hand, model, data = self.hand, self.hand.model, self._data
        goal = self.root_targets(np.nan_to_num(np.asarray(keypoints, dtype=float)))
        weight = np.where(held, 0.0, self._weight)
        cap = self.config.speed_fraction * np.radians(hand.spec.max_velocity_deg_s) * dt
        q = self.q.copy()
        for _ in range(self.config.iterations):
            data.qpos[hand.qpos_ids] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            R = data.xmat[hand.root_id].reshape(3, 3)
            rows, errors = [], []
            for (_, kind, i), target, p, w in zip(
                hand.tips, goal, tip_points(hand, data), weight, strict=True
            ):
                if kind == "site":
                    mujoco.mj_jacSite(model, data, self._jac, None, i)
                else:
                    mujoco.mj_jacBody(model, data, self._jac, None, i)
                rows.append(w * (R.T @ self._jac[:, hand.dof_ids]))
                errors.append(w * (target - p))
            J, e = np.vstack(rows), np.concatenate(errors)
            lam2 = self.config.damping**2
            dq = J.T @ np.linalg.solve(J @ J.T + lam2 * np.eye(len(e)), e)
            q = np.clip(q + dq, hand.lower, hand.upper)
        for finger in np.flatnonzero(held):
            q[self._finger_dofs[finger]] = self.q[self._finger_dofs[finger]]
        dv = self.config.max_acceleration * dt * dt  # the change of step one tick allows
        v_step = self._v * dt
        step = np.clip(q - self.q, v_step - dv, v_step + dv)
        q = self.q + np.clip(step, -cap, cap)
        if not np.isfinite(q).all():
            self.holds += 1
            self._v[:] = 0.0
            return self.q.copy()
        q = np.clip(q, hand.lower, hand.upper)
        self._v = (q - self.q) / dt
        self.q = q
        return self.q.copy()


def _finger_dofs(hand: ModelHand, kind: str, tip: int) -> np.ndarray:
    """Indices (into the hand's joints) of the joints that move fingertip ``tip`` (a site or
    body id, ``kind``): the joints on the path from the root to it."""
    model = hand.model
    body = int(model.site_bodyid[tip]) if kind == "site" else tip
    chain = set()
    while body > 0 and body != hand.root_id:
        chain.add(body)
        body = int(model.body_parentid[body])
    ids = [model.joint(n).id for n in hand.joint_names]
    return np.array([k for k, j in enumerate(ids) if int(model.jnt_bodyid[j]) in chain], dtype=int)
