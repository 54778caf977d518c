"""Retargeting for a hand from a model file (:mod:`beavr_sim.robots.hand_file`).

Human keypoints (the 26 canonical joints in the palm frame, :mod:`beavr_sim.wire.hand`) map to
one fingertip target per hand finger in the hand's root frame:

    target_f = R_palm_root @ (scale_f * human_tip_h)

where ``h`` is the human finger the file maps to ``f`` and ``scale_f`` is derived, as LEAP's
are in :mod:`beavr_sim.operator.retarget`: the hand finger's reach at home (root origin ->
fingertip) over the human template's wrist -> tip length for ``h``. Each tick a few damped
least-squares steps on the fingertip positions move the joints toward the targets; the step
is clipped to the joint limits and to ``max_velocity_deg_s * dt``. The per-tick call never
raises: a non-finite or missing keypoint set holds the last command (counted in ``holds``).
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

    def __init__(self, hand: ModelHand, side: str, config: ModelRetargetConfig | None = None):
        self.hand, self.config = hand, config or ModelRetargetConfig()
        self.scales = finger_scales(hand, side)
        human = dict(hand.spec.human_fingers)
        self._tip_rows = np.array([JOINT_INDEX[f"{human[f]}_tip"] for f, _, _ in hand.tips])
        self._scale = np.array([self.scales[f] for f, _, _ in hand.tips])
        self._weight = np.array(
            [self.config.thumb_weight if f == hand.spec.thumb else 1.0 for f, _, _ in hand.tips]
        )
        self._data = mujoco.MjData(hand.model)
        self.q = hand.home.copy()
        self.holds = 0
        self._jac = np.zeros((3, hand.model.nv))

    def targets(self, keypoints: np.ndarray) -> np.ndarray:
        """The fingertip targets (n_fingers x 3, root frame) of palm-frame ``keypoints``."""
        tips = keypoints[self._tip_rows] * self._scale[:, None]
        return tips @ self.hand.R_palm_root.T

    def tips(self, q: np.ndarray) -> np.ndarray:
        """The fingertips (root frame) at joints ``q``."""
        self._data.qpos[self.hand.qpos_ids] = q
        mujoco.mj_kinematics(self.hand.model, self._data)
        return tip_points(self.hand, self._data)

    def step(self, keypoints: np.ndarray | None, dt: float) -> np.ndarray:
        """Joint targets after one tick of ``dt`` seconds; holds on bad input, never raises."""
        try:
            ok = (keypoints is not None and np.shape(keypoints) == (N_JOINTS, 3)
                  and bool(np.isfinite(keypoints).all()) and np.isfinite(dt) and dt > 0)  # fmt: skip
        except TypeError:
            ok = False
        if not ok:
            self.holds += 1
            return self.q.copy()
        hand, model, data = self.hand, self.hand.model, self._data
        goal = self.targets(np.asarray(keypoints, dtype=float))
        cap = np.radians(hand.spec.max_velocity_deg_s) * dt
        q = self.q.copy()
        for _ in range(self.config.iterations):
            data.qpos[hand.qpos_ids] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            R = data.xmat[hand.root_id].reshape(3, 3)
            rows, errors = [], []
            for (_, kind, i), target, p, w in zip(
                hand.tips, goal, tip_points(hand, data), self._weight, strict=True
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
        q = self.q + np.clip(q - self.q, -cap, cap)
        if not np.isfinite(q).all():
            self.holds += 1
            return self.q.copy()
        self.q = np.clip(q, hand.lower, hand.upper)
        return self.q.copy()
