"""A hand from a model file: the hand a robot file's ``[hands.NAME]`` table loads.

The table (parsed by :func:`beavr_sim.robots.robot_file.read_hand_table` into a
:class:`~beavr_sim.robots.robot_file.HandFile`) names an MJCF model (path relative to the robot
file or ``pkg://package/path``), its root body (the palm: its frame is the hand's palm frame),
the axes of that frame in the human palm frame's terms (``palm_axes``, e.g. ``["y", "-x",
"z"]``: the root's x is the human +y, ...), per finger a fingertip site or body
(``[hands.NAME.fingers]``: finger = "site:NAME" or "body:NAME"), which finger is the thumb,
which human finger drives each hand finger (``human_fingers``, default the same name), the
joint order (default: the model's hinge joints on the bodies below the root), home (default 0
clipped into the limits), a speed cap and the twin's servo gains. Joint limits are read from
the model. Every error is one line naming the file, the key and the valid choices.
:func:`load_hand` turns the table into a :class:`ModelHand`: the compiled model with the ids
the retargeter (:mod:`beavr_sim.operator.retarget_model`) needs, and the per-finger reach at
home (root origin -> fingertip) from which finger scales are derived.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.robots.robot_file import (
    FINGER_NAMES,
    TIP_KINDS,
    HandFile,
    _Reader,
    read_hand_table,
)
from beavr_sim.robots.robot_file import palm_rotation as _palm_rotation

__all__ = [
    "FINGER_NAMES",
    "TIP_KINDS",
    "HandFile",
    "ModelHand",
    "load_hand",
    "palm_rotation",
    "read_hand_table",
    "tip_points",
]


@dataclass(frozen=True)
class ModelHand:
    """A hand loaded from its model: ids into ``model``, limits, home and derived reach."""

    spec: HandFile
    model: mujoco.MjModel
    root_id: int
    R_palm_root: np.ndarray  # human palm frame -> root frame rotation (3x3)
    joint_names: tuple[str, ...]
    qpos_ids: np.ndarray
    dof_ids: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    home: np.ndarray
    tips: tuple[tuple[str, str, int], ...]  # (finger, kind, id)
    reach: dict[str, float]  # finger -> |root origin -> tip| at home (m)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)


def palm_rotation(axes: tuple[str, ...]) -> np.ndarray:
    """Rows: the root frame's x, y, z as signed human-palm axes; raises on a non-rotation."""
    return np.array(_palm_rotation(axes))


def _below(model: mujoco.MjModel, body: int, root: int) -> bool:
    """Whether ``body`` lies strictly below ``root`` in the kinematic tree."""
    while body > 0:
        body = int(model.body_parentid[body])
        if body == root:
            return True
    return False


def load_hand(spec: HandFile, where: Path | None = None) -> ModelHand:
    """Compile ``spec.model`` and resolve every name; errors list the model's valid names."""
    r = _Reader(Path(where) if where is not None else spec.model)
    key = f"hands.{spec.name}"
    try:
        model = mujoco.MjModel.from_xml_path(str(spec.model))
    except ValueError as e:
        raise r.fail(f"{key}.model", f"MuJoCo cannot load {spec.model}: {e}") from None
    bodies = [model.body(i).name for i in range(model.nbody)]
    try:
        root = bodies.index(check_name("root body", spec.root, bodies))
    except ValueError as e:
        raise r.fail(f"{key}.root", str(e)) from None
    hinges = [
        model.joint(j).name
        for j in range(model.njnt)
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
        and _below(model, int(model.jnt_bodyid[j]), root)
    ]
    joint_names = spec.joints if spec.joints is not None else tuple(hinges)
    for joint in joint_names:
        try:
            check_name("hand joint (hinges below the root)", joint, hinges)
        except ValueError as e:
            raise r.fail(f"{key}.joints", str(e)) from None
    if not joint_names:
        raise r.fail(f"{key}.root", f"no hinge joint below body {spec.root!r}")
    ids = [model.joint(j).id for j in joint_names]
    if not all(model.jnt_limited[j] for j in ids):
        free = [n for n, j in zip(joint_names, ids, strict=True) if not model.jnt_limited[j]]
        raise r.fail(f"{key}.joints", f"joints without limits in the model: {', '.join(free)}")
    lower, upper = model.jnt_range[ids, 0].copy(), model.jnt_range[ids, 1].copy()
    home = np.radians(spec.home_deg) if spec.home_deg is not None else np.zeros(len(ids))
    home = np.clip(home, lower, upper)
    tips = []
    for finger, kind, target in spec.fingers:
        obj = mujoco.mjtObj.mjOBJ_SITE if kind == "site" else mujoco.mjtObj.mjOBJ_BODY
        tid = mujoco.mj_name2id(model, obj, target)
        count = model.nsite if kind == "site" else model.nbody
        valid = [mujoco.mj_id2name(model, obj, i) or "" for i in range(count)]
        if tid < 0:
            raise r.fail(f"{key}.fingers.{finger}",
                         f"no {kind} {target!r} in the model; valid {kind}s: "
                         f"{', '.join(v for v in valid if v)}")  # fmt: skip
        owner = int(model.site_bodyid[tid]) if kind == "site" else tid
        if not _below(model, owner, root):
            raise r.fail(f"{key}.fingers.{finger}", f"{kind} {target!r} is not below {spec.root!r}")
        tips.append((finger, kind, tid))
    hand = ModelHand(
        spec=spec, model=model, root_id=root,
        R_palm_root=palm_rotation(spec.palm_axes),
        joint_names=tuple(joint_names),
        qpos_ids=model.jnt_qposadr[ids].copy(), dof_ids=model.jnt_dofadr[ids].copy(),
        lower=lower, upper=upper, home=home, tips=tuple(tips), reach={},
    )  # fmt: skip
    data = mujoco.MjData(model)
    data.qpos[hand.qpos_ids] = home
    mujoco.mj_kinematics(model, data)
    points = tip_points(hand, data)
    hand.reach.update(
        {f: float(np.linalg.norm(p)) for (f, _, _), p in zip(tips, points, strict=True)}
    )
    if not all(math.isfinite(v) and v > 0 for v in hand.reach.values()):
        raise r.fail(f"{key}.fingers", f"a fingertip sits on the root's origin: {hand.reach}")
    return hand


def tip_points(hand: ModelHand, data: mujoco.MjData) -> np.ndarray:
    """The fingertips (n_fingers x 3) in the root frame, after kinematics ran on ``data``."""
    R, o = data.xmat[hand.root_id].reshape(3, 3), data.xpos[hand.root_id]
    world = np.array([
        data.site_xpos[i] if kind == "site" else data.xpos[i] for _, kind, i in hand.tips
    ])  # fmt: skip
    return (world - o) @ R
