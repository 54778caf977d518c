"""LEAP hand retargeting: human hand keypoints (palm frame) -> 16 LEAP joint targets, and back.

The human hand arrives as the 26 canonical joints in the palm frame
(:func:`beavr_sim.operator.palm.keypoints_in_palm`: origin at the wrist, +z along the fingers,
+x out of the palm), whose axes are those of the LEAP ``hand`` frame (the mount frame, whose
origin is LEAP's wrist). A human point of finger ``f`` maps to the LEAP hand frame by

    p_hand = origin_offset + scale_f * p_palm

By default ``origin_offset`` is 0 (the human wrist on LEAP's wrist) and ``scale_f`` is the
ratio of LEAP's reach to the human's for that finger: the length of LEAP's wrist -> fingertip
(pad site) at its home pose (open hand) over that of the same finger of
:data:`HUMAN_TEMPLATE_RIGHT` (a typical adult hand, relaxed): 1.18 for the thumb, 1.35 index,
1.27 middle, 1.40 ring. So the template's open hand maps onto LEAP's open hand, the targets
lie where LEAP's fingers can reach, and a fingertip on its target points from the wrist where
the human's does. (An earlier map scaled the human hand 1.8x about its middle knuckle, put on
LEAP's: that put the human wrist 6 cm behind LEAP's and most fingertip targets out of reach,
and the fingers pointed up to 15 degrees away from the human's; docs/benchmarks.md.)

:class:`LeapRetargeter` solves, with mink on a hand-only copy of the LEAP MJCF, for joints that
put each LEAP finger's fingertip-pad site and distal-joint point (origin of ``<finger>_distal``)
on the mapped human tip and distal (DIP, thumb IP) joints, and with a smaller weight its
intermediate point (origin of ``<finger>_middle``) on the human PIP (thumb MCP), under joint
limits and finger-finger collision avoidance (a pair that ends up inside the kept gap is
pushed back out, :attr:`RetargetConfig.collision_recovery`), warm-started from the previous
solution. LEAP has no little finger: the human little finger is ignored.
:func:`human_keypoints_for` is the inverse, for synthetic traces.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mink
import mujoco
import numpy as np

from beavr_sim.assets import mjcf_path
from beavr_sim.naming import check_name
from beavr_sim.operator import kernels
from beavr_sim.operator.collision import CollisionLimit
from beavr_sim.operator.jacobians import PointJacobians
from beavr_sim.operator.qp import StepQP
from beavr_sim.robots.parts import LEAP_HAND
from beavr_sim.wire.hand import JOINT_INDEX, N_JOINTS, SIDES

#: LEAP fingers, in the order of their motor ids' blocks below.
LEAP_FINGERS = ("thumb", "index", "middle", "ring")
#: Motor ids (indices of the 16-vector) that move each LEAP finger.
FINGER_MOTORS: dict[str, tuple[int, ...]] = {
    "index": (0, 1, 2, 3),
    "middle": (4, 5, 6, 7),
    "ring": (8, 9, 10, 11),
    "thumb": (12, 13, 14, 15),
}
#: The retargeting targets: (name, human joint suffix, LEAP frame type, LEAP frame suffix).
#: The intermediate point (PIP joint; the thumb's MCP, human ``thumb_proximal``) conditions
#: nearly straight fingers, whose tip and distal points barely move with the middle joints.
TARGET_POINTS = (
    ("tip", "tip", "site", "tip"),
    ("distal", "distal", "body", "distal"),
    ("intermediate", "intermediate", "body", "middle"),
)
#: Human joint suffix per finger where it differs from the target's (the thumb has no
#: intermediate phalanx: its MCP joint is XR Hands' ``thumb_proximal``).
HUMAN_SUFFIX = {("thumb", "intermediate"): "proximal"}
#: Link pairs of different fingers that cannot come within 9 mm of each other anywhere in the
#: joint range (sampled: 15,000 configurations per hand, a third of them at the range's
#: corners; ``tests/test_retarget.py`` re-checks them against 2 x ``min_finger_distance``).
#: They are left out of the finger-finger collision check, which otherwise spends time on
#: neighbouring knuckles that always lie within the detection distance of each other.
NEVER_CLOSE_LINKS: frozenset[frozenset[str]] = frozenset(
    frozenset(pair)
    for pair in (
        ("middle_base", "ring_base"),
        ("index_base", "middle_base"),
        ("index_proximal", "thumb_proximal"),
        ("index_base", "thumb_proximal"),
        ("ring_middle", "thumb_base"),
        ("middle_base", "thumb_proximal"),
        ("middle_proximal", "thumb_proximal"),
        ("index_base", "thumb_base"),
        ("index_proximal", "thumb_base"),
        ("middle_base", "thumb_base"),
        ("middle_proximal", "thumb_base"),
        ("index_proximal", "ring_proximal"),
        ("ring_proximal", "thumb_proximal"),
        ("ring_base", "thumb_proximal"),
        ("ring_proximal", "thumb_base"),
        ("index_proximal", "ring_base"),
        ("index_base", "ring_proximal"),
        ("ring_base", "thumb_base"),
        ("index_base", "ring_base"),
    )
)


#: A typical adult right hand in its palm frame (metres, wrist at the origin). The wrist and
#: the index, middle and little knuckles make :func:`keypoints_in_palm` the identity; the
#: finger links are a relaxed, slightly curled pose. The left hand is its mirror (y -> -y).
HUMAN_TEMPLATE_RIGHT: dict[str, tuple[float, float, float]] = {
    "wrist": (0.0, 0.0, 0.0),
    "thumb_metacarpal": (0.010, 0.031, 0.020),
    "thumb_proximal": (0.008, 0.055, 0.042),
    "thumb_distal": (-0.002, 0.078, 0.065),
    "thumb_tip": (-0.015, 0.095, 0.086),
    "index_proximal": (0.004, 0.025, 0.087),
    "index_intermediate": (0.010, 0.031, 0.124),
    "index_distal": (0.020, 0.035, 0.146),
    "index_tip": (0.032, 0.037, 0.165),
    "middle_proximal": (0.0, 0.0, 0.092),
    "middle_intermediate": (0.010, 0.0, 0.134),
    "middle_distal": (0.022, 0.0, 0.158),
    "middle_tip": (0.036, 0.001, 0.178),
    "ring_proximal": (0.002, -0.020, 0.086),
    "ring_intermediate": (0.012, -0.024, 0.124),
    "ring_distal": (0.023, -0.026, 0.146),
    "ring_tip": (0.036, -0.026, 0.164),
    "little_proximal": (0.004, -0.038, 0.074),
    "little_intermediate": (0.013, -0.046, 0.103),
    "little_distal": (0.021, -0.051, 0.120),
    "little_tip": (0.031, -0.054, 0.136),
}


def human_template(side: str) -> np.ndarray:
    """The 26 joints of :data:`HUMAN_TEMPLATE_RIGHT` for ``side`` in its palm frame
    (metacarpals a quarter of the way to the knuckles)."""
    joints = np.zeros((N_JOINTS, 3))
    for name, p in HUMAN_TEMPLATE_RIGHT.items():
        joints[JOINT_INDEX[name]] = p
    for finger in ("index", "middle", "ring", "little"):
        joints[JOINT_INDEX[f"{finger}_metacarpal"]] = (
            0.25 * joints[JOINT_INDEX[f"{finger}_proximal"]]
        )
    joints[JOINT_INDEX["palm"]] = 0.5 * joints[JOINT_INDEX["middle_proximal"]]
    if side == "left":
        joints[:, 1] *= -1.0
    return joints


@dataclass(frozen=True)
class RetargetConfig:
    """Human -> LEAP map and solver settings (see the module docstring for the map).

    ``finger_scale`` (index, middle, ring) and ``thumb_scale``: human -> LEAP scale; None (the
    default) derives each finger's from the models (LEAP's home reach over the template's, see
    the module docstring). ``origin_offset``: LEAP hand-frame point (m) of the human wrist;
    None is LEAP's wrist (the hand frame's origin). Weights: ``tip_weight`` and
    ``distal_weight`` per metre of position error, ``posture_weight`` per radian from
    ``posture`` (None: all zeros, open hand). ``iterations``: QP steps per frame (warm-started).
    ``damping``: Levenberg-Marquardt damping of each step; ``max_step``: largest joint change
    per step (rad), which keeps the linearised collision constraints valid (0.1 rad at 90 Hz
    is 9 rad/s). ``min_finger_distance``: gap (m) kept between geoms of different fingers,
    enforced once closer than ``collision_detection_distance`` (which must exceed how far two
    fingers can move towards each other in one step, or they may pass the check between
    steps: 3 cm for 0.1 rad steps); pairs without the thumb use ``finger_detection_distance``
    (the fingers only approach each other through their spread joints: under 1.5 cm per 0.1
    rad step for two fingers); ``collision_gain``: fraction
    of the remaining gap a step may close (mink's velocity-damper gain);
    ``collision_recovery``: fraction of an intrusion into ``min_finger_distance`` a step must
    undo (linearisation errors near box edges otherwise let a pair creep inside and stay).
    """

    finger_scale: float | None = None
    thumb_scale: float | None = None
    origin_offset: tuple[float, float, float] | None = None
    tip_weight: float = 1.0
    distal_weight: float = 0.5
    intermediate_weight: float = 0.3
    posture_weight: float = 1e-4
    posture: tuple[float, ...] | None = None
    iterations: int = 1
    damping: float = 1e-4
    max_step: float = 0.1
    min_finger_distance: float = 0.003
    collision_detection_distance: float = 0.03
    finger_detection_distance: float = 0.015
    collision_gain: float = 0.5
    collision_recovery: float = 0.5

    def __post_init__(self) -> None:
        for name in ("finger_scale", "thumb_scale", "tip_weight", "max_step", "collision_gain"):
            value = getattr(self, name)
            if value is None and name in ("finger_scale", "thumb_scale"):
                continue
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"RetargetConfig.{name} must be finite and > 0, got {value!r}")
        for name in (
            "distal_weight",
            "intermediate_weight",
            "posture_weight",
            "damping",
            "min_finger_distance",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"RetargetConfig.{name} must be finite and >= 0, got {value!r}")
        if self.collision_gain > 1:
            raise ValueError(
                f"RetargetConfig.collision_gain must be in (0, 1], got {self.collision_gain!r}"
            )
        if not (np.isfinite(self.collision_recovery) and 0 <= self.collision_recovery <= 1):
            raise ValueError(
                "RetargetConfig.collision_recovery must be in [0, 1], got "
                f"{self.collision_recovery!r}"
            )
        if not (
            self.collision_detection_distance
            >= self.finger_detection_distance
            > self.min_finger_distance
        ):
            raise ValueError(
                "RetargetConfig needs collision_detection_distance >= "
                "finger_detection_distance > min_finger_distance, got "
                f"{self.collision_detection_distance!r}, {self.finger_detection_distance!r}, "
                f"{self.min_finger_distance!r}"
            )
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ValueError(
                f"RetargetConfig.iterations must be an int >= 1, got {self.iterations!r}"
            )
        if self.origin_offset is not None:
            offset = np.asarray(self.origin_offset, dtype=float)
            if offset.shape != (3,) or not np.isfinite(offset).all():
                raise ValueError(
                    f"RetargetConfig.origin_offset must be 3 finite numbers (m) or None, "
                    f"got {self.origin_offset!r}"
                )
        if self.posture is not None:
            posture = np.asarray(self.posture, dtype=float)
            if posture.shape != (len(LEAP_HAND.joints),) or not np.isfinite(posture).all():
                raise ValueError(
                    f"RetargetConfig.posture must be {len(LEAP_HAND.joints)} finite joint values "
                    f"(rad, motor-id order) or None, got {self.posture!r}"
                )


class HandMap:
    """The human palm frame -> LEAP hand frame point map of one side, and the hand-only model."""

    def __init__(self, side: str, config: RetargetConfig):
        self.side = check_name("side", side, SIDES)
        self.config = config
        self.model = mujoco.MjModel.from_xml_path(str(mjcf_path(LEAP_HAND.mjcf(side))))
        self.data = mujoco.MjData(self.model)
        #: qpos address of each motor id.
        self.qpos_adr = np.array([self.model.joint(j).qposadr[0] for j in LEAP_HAND.joints])
        self.range = self.model.jnt_range[[self.model.joint(j).id for j in LEAP_HAND.joints]]
        self.origin_offset = (
            np.zeros(3)
            if config.origin_offset is None
            else np.asarray(config.origin_offset, dtype=float)
        )
        #: Human -> LEAP scale of each LEAP finger.
        self.scales = {f: self._scale(f) for f in LEAP_FINGERS}
        #: Scale of each of the 26 canonical joints (the finger's; the middle finger's for the
        #: wrist, palm, metacarpals and the little finger, which LEAP lacks).
        self.joint_scales = np.full(N_JOINTS, self.scales["middle"])
        for finger, scale in self.scales.items():
            for name, i in JOINT_INDEX.items():
                if name.startswith(f"{finger}_") and not name.endswith("metacarpal"):
                    self.joint_scales[i] = scale

    def _scale(self, finger: str) -> float:
        given = self.config.thumb_scale if finger == "thumb" else self.config.finger_scale
        if given is not None:
            return float(given)
        # LEAP's reach over the template's: wrist (mount origin) -> fingertip pad, open hand.
        self.forward(np.asarray(LEAP_HAND.home, dtype=float))
        leap = np.linalg.norm(self.data.site(f"{finger}_tip").xpos)
        human = np.linalg.norm(human_template(self.side)[JOINT_INDEX[f"{finger}_tip"]])
        return float(leap / human)

    def scale(self, finger: str) -> float:
        return self.scales[finger]

    def to_leap(self, p_palm: np.ndarray, finger: str) -> np.ndarray:
        return self.origin_offset + self.scales[finger] * p_palm

    def to_human(self, p_hand: np.ndarray, finger: str) -> np.ndarray:
        return (p_hand - self.origin_offset) / self.scales[finger]

    def skeleton(self, keypoints_palm: np.ndarray) -> np.ndarray:
        """All 26 joints mapped to the LEAP hand frame (each with its finger's scale)."""
        return self.origin_offset + self.joint_scales[:, None] * keypoints_palm

    def forward(self, q16: np.ndarray) -> mujoco.MjData:
        """Kinematics of the hand at joint values ``q16`` (motor-id order)."""
        self.data.qpos[self.qpos_adr] = q16
        mujoco.mj_kinematics(self.model, self.data)
        return self.data


class _PointsTask(mink.Task):
    """Positions of several sites / body origins, stacked (3 error rows per point)."""

    def __init__(self, model: mujoco.MjModel, frames: list[tuple[str, str]], costs: np.ndarray):
        super().__init__(cost=np.repeat(np.asarray(costs, dtype=float), 3), gain=1.0)
        self.model = model
        self.base_cost = self.cost.copy()
        self.is_site = np.array([kind == "site" for kind, _ in frames])
        self.ids = np.array([getattr(model, kind)(name).id for kind, name in frames])
        self.targets = np.zeros((len(frames), 3))
        self._positions = np.zeros((len(frames), 3))
        self._bodies = np.array(
            [
                model.site_bodyid[i] if site else i
                for site, i in zip(self.is_site, self.ids, strict=True)
            ],
            dtype=np.int64,
        )
        self._jacobians = PointJacobians(model)
        self._ids = self.ids.astype(np.int64)

    def _update_positions(self, data: mujoco.MjData) -> np.ndarray:
        kernels.gather_points(data.site_xpos, data.xpos, self.is_site, self._ids, self._positions)
        return self._positions

    def compute_error(self, configuration: mink.Configuration) -> np.ndarray:
        return (self._update_positions(configuration.data) - self.targets).ravel()

    def compute_jacobian(self, configuration: mink.Configuration) -> np.ndarray:
        data = configuration.data
        J = self._jacobians.points(data, self._bodies, self._update_positions(data))
        return J.reshape(-1, self.model.nv)


def finger_geoms(
    model: mujoco.MjModel, links: tuple[str, ...] | None = None
) -> dict[str, list[int]]:
    """Collision geoms of each LEAP finger (bodies named ``<finger>_<link>``; all links, or
    only those in ``links``)."""
    geoms: dict[str, list[int]] = {f: [] for f in LEAP_FINGERS}
    for g in range(model.ngeom):
        finger, _, link = model.body(model.geom_bodyid[g]).name.partition("_")
        if links is not None and link not in links:
            continue
        if finger in geoms and (model.geom_contype[g] or model.geom_conaffinity[g]):
            geoms[finger].append(g)
    return geoms


def finger_link_pairs(model: mujoco.MjModel) -> list[tuple[list[int], list[int]]]:
    """Geom groups checked against each other: every link of one finger against every link
    of another, except the pairs in :data:`NEVER_CLOSE_LINKS`."""
    body_geoms: dict[str, list[int]] = {}
    for finger_geom_ids in finger_geoms(model).values():
        for g in finger_geom_ids:
            body_geoms.setdefault(model.body(model.geom_bodyid[g]).name, []).append(g)
    names = sorted(body_geoms)
    pairs = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if a.partition("_")[0] == b.partition("_")[0]:
                continue  # same finger
            if frozenset((a, b)) in NEVER_CLOSE_LINKS:
                continue
            pairs.append((body_geoms[a], body_geoms[b]))
    return pairs


class LeapRetargeter:
    """Human palm-frame keypoints -> LEAP joint targets (motor-id order) for one side."""

    def __init__(self, side: str, config: RetargetConfig | None = None):
        self.config = config or RetargetConfig()
        self.map = HandMap(side, self.config)
        self.side = self.map.side
        model = self.model = self.map.model
        self.configuration = mink.Configuration(model)
        frames, costs, self._human_ids, self._finger_of_point = [], [], [], []
        weights = {
            "tip": self.config.tip_weight,
            "distal": self.config.distal_weight,
            "intermediate": self.config.intermediate_weight,
        }
        for finger in LEAP_FINGERS:
            for name, human, kind, leap in TARGET_POINTS:
                if weights[name] == 0.0:
                    continue
                frames.append((kind, f"{finger}_{leap}"))
                costs.append(weights[name])
                human = HUMAN_SUFFIX.get((finger, name), human)
                self._human_ids.append(JOINT_INDEX[f"{finger}_{human}"])
                self._finger_of_point.append(finger)
        self._human_ids = np.array(self._human_ids, dtype=np.int64)
        self._scales = np.array([self.map.scale(f) for f in self._finger_of_point])[:, None]
        self._point_scales = self._scales.ravel()
        self.points = _PointsTask(model, frames, np.array(costs))
        self._posture = np.zeros(model.nq)
        if self.config.posture is not None:
            self._posture[self.map.qpos_adr] = self.config.posture
        geoms = finger_geoms(model)
        pairs = finger_link_pairs(model)
        # Joint limits: mink's, applied as the QP's simple bounds on the step (hinges only).
        self.joint_limit = mink.ConfigurationLimit(model)
        thumb = set(geoms["thumb"])
        self.collision_limit = CollisionLimit(
            model,
            pairs,
            spec=mujoco.MjSpec.from_file(str(mjcf_path(LEAP_HAND.mjcf(self.side)))),
            pair_detection_distance=lambda a, b: (
                self.config.collision_detection_distance
                if a in thumb or b in thumb
                else self.config.finger_detection_distance
            ),
            minimum_distance_from_collisions=self.config.min_finger_distance,
            closest_only=True,  # ~2.5 contacts per box pair: one row per pair is enough
            collision_detection_distance=self.config.collision_detection_distance,
            gain=self.config.collision_gain,
            recovery=self.config.collision_recovery,
        )
        self._held = np.zeros(model.nv, dtype=bool)
        self._any_held = self._held_any_before = False
        self._all_tracked = np.ones(N_JOINTS, dtype=bool)
        self._posture_weight2 = float(self.config.posture_weight**2)
        self._diagonal = float(self.config.damping) + self._posture_weight2
        self._qp = StepQP(model.nv)
        #: Whether the last :meth:`retarget` made no progress: no step's QP had a solution,
        #: so the fingers held their previous joints (the caller reports the hold).
        self.infeasible = False
        #: QP steps without a solution since construction (partial frames count too).
        self.infeasible_steps = 0
        #: DAQP's exit flag of the latest step without a solution (None before any).
        self.last_exitflag: int | None = None
        self._limit_gain = float(self.joint_limit.gain)
        # Degrees of freedom (qvel addresses) and target points of each finger.
        self._finger_dofs = {
            f: np.array([model.joint(LEAP_HAND.joints[m]).dofadr[0] for m in FINGER_MOTORS[f]])
            for f in LEAP_FINGERS
        }
        self._finger_points = {
            f: np.array([i for i, g in enumerate(self._finger_of_point) if g == f])
            for f in LEAP_FINGERS
        }
        self._lower, self._upper = self.map.range[:, 0], self.map.range[:, 1]
        if model.nq != model.nv or not (model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE).all():
            raise ValueError("LeapRetargeter expects a hand model with hinge joints only")
        self._lower_qpos = model.jnt_range[:, 0][np.argsort(model.jnt_qposadr)]
        self._upper_qpos = model.jnt_range[:, 1][np.argsort(model.jnt_qposadr)]
        self.reset()

    @property
    def q(self) -> np.ndarray:
        """The current solution (motor-id order)."""
        return self.configuration.q[self.map.qpos_adr].copy()

    def reset(self, q: np.ndarray | None = None) -> None:
        """Restart from ``q`` (motor-id order; default: the LEAP home, open hand)."""
        q16 = np.asarray(LEAP_HAND.home if q is None else q, dtype=float)
        if q16.shape != (len(LEAP_HAND.joints),) or not np.isfinite(q16).all():
            raise ValueError(
                f"reset needs {len(LEAP_HAND.joints)} finite joint values (motor-id order), "
                f"got shape {q16.shape}"
            )
        qpos = np.zeros(self.model.nq)
        qpos[self.map.qpos_adr] = np.clip(q16, self._lower, self._upper)
        self.configuration.update(qpos)

    def targets(self, keypoints_palm: np.ndarray) -> np.ndarray:
        """LEAP hand-frame targets (8 x 3: tip, distal per finger of :data:`LEAP_FINGERS`)."""
        return self.map.origin_offset + self._scales * keypoints_palm[self._human_ids]

    def retarget(self, keypoints_palm: np.ndarray, tracked: np.ndarray | None = None) -> np.ndarray:
        """Joint targets (16, motor-id order, within the joint limits) for one hand frame.

        ``keypoints_palm``: the 26 canonical joints in the palm frame (wrist at the origin),
        as :func:`~beavr_sim.operator.palm.keypoints_in_palm` gives them. ``tracked``: per-joint
        flags (None: all tracked); a finger with an untracked target point (tip, distal or
        intermediate joint) holds its previous value. A step whose QP has no solution leaves
        the joints as they are (:attr:`infeasible`, :attr:`infeasible_steps`).

        Raises ValueError for keypoints or flags of the wrong shape, and for NaN/inf in a
        tracked target point (flag such joints untracked).
        """
        keypoints = np.asarray(keypoints_palm, dtype=float)
        if keypoints.shape != (N_JOINTS, 3):
            raise ValueError(
                f"retarget needs palm-frame keypoints of shape ({N_JOINTS}, 3), "
                f"got {keypoints.shape}"
            )
        if tracked is None:
            tracked = self._all_tracked
        else:
            tracked = np.asarray(tracked, dtype=bool)
            if tracked.shape != (N_JOINTS,):
                raise ValueError(f"tracked flags need shape ({N_JOINTS},), got {tracked.shape}")
        points = self.points
        status = kernels.point_targets(
            keypoints, tracked, self._human_ids, self._point_scales, self.map.origin_offset,
            points.targets, points.cost, points.base_cost,
        )  # fmt: skip
        if status < 0:
            raise ValueError(
                "retarget got NaN/inf in tracked keypoints (tips / distal joints); flag them "
                "untracked to hold those fingers"
            )
        self._any_held = status == 0
        if self._any_held:
            self._held[:] = False
            used = tracked[self._human_ids]
            for finger in LEAP_FINGERS:
                if not used[self._finger_points[finger]].all():
                    points.cost.reshape(-1, 3)[self._finger_points[finger]] = 0.0
                    self._held[self._finger_dofs[finger]] = True
        elif self._held_any_before:
            self._held[:] = False
        self._held_any_before = self._any_held
        failed = 0
        for _ in range(self.config.iterations):
            if not self._step():
                failed += 1
                self.last_exitflag = getattr(self._qp, "last_exitflag", None)
        self.infeasible = failed == self.config.iterations
        self.infeasible_steps += failed
        q16 = np.empty(self.map.qpos_adr.shape[0])
        kernels.gather_clip(
            self.configuration.data.qpos, self.map.qpos_adr, self._lower, self._upper, q16
        )
        return q16

    def _step(self) -> bool:
        """One QP step (Gauss-Newton with damping) under joint limits and collision avoidance;
        returns whether the QP had a solution (else the joints stay).

        Assembled here rather than by ``mink.solve_ik`` for speed: the tasks' weighted residuals
        are stacked, joint limits become simple bounds, and only active collision rows are kept.
        """
        cfg = self.configuration
        data, points, jac = cfg.data, self.points, self.points._jacobians
        q = data.qpos  # read only here (mink's cfg.q is a copy)
        # mink's task residuals (weights enter squared), damping and posture on the diagonal.
        qp = self._qp
        kernels.points_qp(
            data.cdof, data.subtree_com, jac.root, jac.chain,
            points._bodies, points._update_positions(data), points.targets, points.cost,
            q, self._posture, self._posture_weight2, self._diagonal,
            self._lower_qpos, self._upper_qpos, self._limit_gain, self.config.max_step,
            self._held, qp.H, qp.c, qp.lower, qp.upper,
        )  # fmt: skip
        _, A, h = self.collision_limit.active_rows(cfg, 1.0)
        dq = qp.solve(A, h)
        if dq is None and (h < 0.0).any():
            # Pushing every pair inside the gap back out at once can be more than one step
            # can do: settle for no deeper (mink's rows) this step.
            dq = qp.solve(A, np.maximum(h, 0.0))
        if dq is None:  # no solution (fingers already too close, a solver failure): hold
            return False
        if self._any_held:
            dq[self._held] = 0.0
        q += dq  # in place (data.qpos); hinges only: integrating is adding
        cfg.update()
        return True

    def retarget_converged(
        self, keypoints_palm: np.ndarray, iterations: int = 300, tolerance: float = 1e-7
    ) -> np.ndarray:
        """:meth:`retarget` repeated on one frame until the joints stop moving (offline use)."""
        q = self.retarget(keypoints_palm)
        for _ in range(iterations - 1):
            q_next = self.retarget(keypoints_palm)
            if np.max(np.abs(q_next - q)) < tolerance:
                return q_next
            q = q_next
        return q


@functools.lru_cache(maxsize=8)
def _hand_map(side: str, config: RetargetConfig) -> HandMap:
    return HandMap(side, config)


def leap_points(q16: np.ndarray, side: str, config: RetargetConfig | None = None) -> dict:
    """LEAP hand-frame points of each finger at ``q16``: ``{finger: {link: xyz}}``."""
    hand = HandMap(side, config or RetargetConfig())
    return _leap_points(hand, np.asarray(q16, dtype=float))


def _leap_points(hand: HandMap, q16: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    data = hand.forward(q16)
    out = {}
    for finger in LEAP_FINGERS:
        links = {
            "intermediate": data.body(f"{finger}_middle").xpos.copy(),
            "distal": data.body(f"{finger}_distal").xpos.copy(),
            "tip": data.site(f"{finger}_tip").xpos.copy(),
        }
        out[finger] = links
    return out


def human_keypoints_for(
    q16: np.ndarray, side: str, config: RetargetConfig | None = None
) -> np.ndarray:
    """Palm-frame human keypoints (26 x 3) whose retargeting gives back ``q16``.

    The wrist, palm, metacarpals, knuckles (index, middle, ring, little), thumb metacarpal
    and the little finger come from :data:`HUMAN_TEMPLATE_RIGHT` (mirrored for the left hand),
    so that :func:`keypoints_in_palm` of the result is the result itself. The intermediate
    (PIP; thumb MCP), distal and tip joints of thumb, index, middle and ring are LEAP's points
    at ``q16`` mapped back through the inverse of the human -> LEAP map.
    """
    hand = _hand_map(side, config or RetargetConfig())
    q = np.asarray(q16, dtype=float)
    if q.shape != (len(LEAP_HAND.joints),) or not np.isfinite(q).all():
        raise ValueError(
            f"human_keypoints_for needs {len(LEAP_HAND.joints)} finite joint values "
            f"(motor-id order), got shape {q.shape}"
        )
    joints = human_template(hand.side)
    for finger, links in _leap_points(hand, q).items():
        for link, p_hand in links.items():
            human = "proximal" if finger == "thumb" and link == "intermediate" else link
            joints[JOINT_INDEX[f"{finger}_{human}"]] = hand.to_human(p_hand, finger)
    return joints
