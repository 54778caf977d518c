"""A two-arm source episode mirrored left <-> right: what the right arm did, done by the left in
the scene reflected across the robot's plane of symmetry (world ``y = 0``), and the other way.

Two arms handle the objects on their own side, so a source in which the right arm always took
the large block cannot make a new scene with the large block on the left: the right arm would
reach across the table (the guard holds it). Its mirror image covers that scene. A
:class:`Mirror` exists only for an embodiment whose two arms are each other's reflection:
effectors ``left`` and ``right`` whose hand bodies, at home, are reflections of each other
(checked on the model).

Reflection ``M = diag(1, -1, 1)``. A thing's position ``p`` becomes ``M p`` and its yaw
``-yaw``; a hand pose ``T`` of one arm becomes ``M T M`` for the other, times a fixed
translation in the hand's frame (:attr:`Mirror.offset`), measured on the model: the left LEAP
hand's geometry is not placed exactly where the right one's reflection would be (about 3 cm
apart); the offset puts the fingers where the reflected fingers were (to a few mm). Finger
joints carry over, but the LEAP hand's side-to-side joints and the thumb's first two turn the
other way (:data:`LEAP_FLIPPED`; the thumb's ranges are each other's negation in the model),
then are clipped to the receiving hand's ranges.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import mujoco
import numpy as np

from beavr_sim.datasets.augment.replay import Trajectory, hand_body

M = np.diag([1.0, -1.0, 1.0])
M4 = np.diag([1.0, -1.0, 1.0, 1.0])
SWAP = {"left": "right", "right": "left"}
#: Hand joints (in hand order) that turn the other way in the other hand: the LEAP hand's
#: side-to-side joints of index, middle and ring, and the thumb's first two.
LEAP_FLIPPED = (0, 4, 8, 12, 13)
LIMIT_MARGIN = 1e-3  # rad: mirrored finger targets stay this far inside the joint limits


@dataclass(frozen=True)
class Mirror:
    """The reflection between the two arms of one embodiment (see the module docstring)."""

    offset: dict[str, np.ndarray]  # arm -> 4x4: M T_other M @ offset is this arm's pose
    finger_signs: np.ndarray  # per hand joint: +1, or -1 where it turns the other way
    finger_range: dict[str, tuple[np.ndarray, np.ndarray]]  # arm -> its hand joints' limits

    @classmethod
    def of(cls, env) -> Mirror | None:
        """The mirror of ``env``'s two arms (set to home), or None when they are not mirrors."""
        arms = {e.name for e in env.embodiment.effectors}
        if arms != set(SWAP) or any(e.hand.source for e in env.embodiment.spec.effectors):
            return None  # not two arms, or a robot file's hand: which joints flip is unknown
        model, data = env.model, env.data
        data.qpos[env.joints.qpos_adr] = env.joints.home
        mujoco.mj_kinematics(model, data)
        pose = {a: _pose(data, hand_body(env, a)) for a in SWAP}
        for a, b in SWAP.items():
            if not np.allclose(pose[a], M4 @ pose[b] @ M4, atol=1e-6):
                return None
        geoms = _paired_hand_geoms(env)
        if not len(geoms["left"]):
            return None
        offset = {}
        for a, b in SWAP.items():
            inv_a = np.linalg.inv(pose[a])  # = inv(M T_b M) at home
            own = (inv_a[:3, :3] @ data.geom_xpos[geoms[a]].T).T + inv_a[:3, 3]
            seen = (inv_a[:3, :3] @ (M @ data.geom_xpos[geoms[b]].T)).T + inv_a[:3, 3]
            T = np.eye(4)
            T[:3, 3] = -(own - seen).mean(axis=0)
            offset[a] = T
        n = len(env.embodiment.effectors[0].hand_joints)
        signs = np.ones(n)
        signs[[i for i in LEAP_FLIPPED if i < n]] = -1.0
        limits = {}
        for effector in env.embodiment.effectors:
            sl = env.joints.slices[effector.name]
            hand = slice(sl.start + len(effector.arm_joints), sl.stop)
            limits[effector.name] = (env.joints.lower[hand].copy(), env.joints.upper[hand].copy())
        return cls(offset, signs, limits)

    def trajectory(self, traj: Trajectory) -> Trajectory:
        """``traj`` reflected: each arm does what the other did, in the reflected scene."""
        actions = traj.episode.actions.copy()
        for a, b in SWAP.items():
            low, high = self.finger_range[a]
            fingers = traj.episode.actions[:, traj.hand[b]] * self.finger_signs
            actions[:, traj.hand[a]] = np.clip(fingers, low + LIMIT_MARGIN, high - LIMIT_MARGIN)
        palm = {a: M4 @ traj.palm[SWAP[a]] @ M4 @ self.offset[a] for a in traj.arms}
        return replace(
            traj,
            episode=replace(traj.episode, actions=actions),
            palm=palm,
            pos={t: p @ M for t, p in traj.pos.items()},
            yaw={t: -y for t, y in traj.yaw.items()},
            touch={a: traj.touch[SWAP[a]] for a in traj.arms},
            start_pos={t: M @ p for t, p in traj.start_pos.items()},
            start_yaw={t: -y for t, y in traj.start_yaw.items()},
        )


def reflect(positions: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Positions reflected across ``y = 0``."""
    return {k: M @ np.asarray(p, float) for k, p in positions.items()}


def _pose(data: mujoco.MjData, body: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = data.xmat[body].reshape(3, 3)
    T[:3, 3] = data.xpos[body]
    return T


def _paired_hand_geoms(env) -> dict[str, np.ndarray]:
    """Per arm, the geoms of its hand (bodies below its hand body) that the other hand has
    too (same body name, same place among the body's geoms), in the same order."""
    model = env.model
    found: dict[str, dict[tuple[str, int], int]] = {}
    for arm in SWAP:
        root = hand_body(env, arm)
        found[arm] = {}
        for g in range(model.ngeom):
            b = k = int(model.geom_bodyid[g])
            while k > 0 and k != root:
                k = int(model.body_parentid[k])
            if k != root or b == root:
                continue
            name = model.body(b).name.split("/", 1)[1]
            n = sum(1 for key in found[arm] if key[0] == name)
            found[arm][name, n] = g
    keys = sorted(set(found["left"]) & set(found["right"]))
    return {arm: np.array([found[arm][k] for k in keys], int) for arm in SWAP}
