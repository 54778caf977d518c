"""LEAP retargeting benchmark: ours (mink) against dex-retargeting's vector retargeting.

Both run on the same frames of the real human hand trace in the reference folder
(``human_hand_trace/human_joint_right_mediapipe21.npz``, MediaPipe 21 landmarks, right hand,
wrist-attached frame). Joint limits, finger-finger penetration, fingertip direction and pinch
fidelity are all measured on our LEAP MJCF, so the two methods are scored identically:

- fingertip direction error: the angle between the human's wrist -> tip and LEAP's wrist (the
  hand frame's origin, the mount) -> fingertip pad, per finger;
- fingertip position error after scaling: each method's own fingertip target (ours: the
  human tip through our map; dex-retargeting: 1.6 x the human's wrist -> tip vector from its
  ``base`` link) against where its fingertip ended up (ours: the pad site; theirs: its
  ``*_tip_head`` link), per finger;
- pinch fidelity: frames where the human's thumb and index tips are within
  :data:`HUMAN_PINCH_M` and LEAP's thumb and index pad sites within :data:`ROBOT_PINCH_M`,
  and the reverse (a robot pinch without a human one).

The trace's frame is already right-handed with the palm frame's axes (fingers along +z, palm
facing +x, thumb at +y): :data:`R_CANONICAL_TRACE` is the identity and no reflection is needed.
"""

from __future__ import annotations

import time
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.operator.palm import keypoints_in_palm
from beavr_sim.operator.retarget import (
    LEAP_FINGERS,
    LeapRetargeter,
    RetargetConfig,
    finger_geoms,
)
from beavr_sim.reference import find_reference_dir
from beavr_sim.wire.hand import JOINT_INDEX, N_JOINTS

TRACE = "human_hand_trace/human_joint_right_mediapipe21.npz"
#: Rotation from the trace's frame to the canonical (right-handed) frame of HandFrame.
R_CANONICAL_TRACE = np.eye(3)
#: MediaPipe landmark of each canonical joint it has (the rest are derived).
_MEDIAPIPE = {
    "wrist": 0,
    **{f"thumb_{j}": 1 + i for i, j in enumerate(("metacarpal", "proximal", "distal", "tip"))},
    **{
        f"{finger}_{j}": base + i
        for finger, base in (("index", 5), ("middle", 9), ("ring", 13), ("little", 17))
        for i, j in enumerate(("proximal", "intermediate", "distal", "tip"))
    },
}
#: MediaPipe landmarks of the wrist and of each LEAP finger's tip (dex-retargeting's vectors).
_MEDIAPIPE_TIPS = (4, 8, 12, 16)
_DEX_TIP_LINKS = ("thumb_tip_head", "index_tip_head", "middle_tip_head", "ring_tip_head")
#: A human pinch: thumb and index tips within 2 cm; a robot pinch: LEAP's pads within 1 cm.
HUMAN_PINCH_M = 0.02
ROBOT_PINCH_M = 0.01


def mediapipe_to_canonical(landmarks: np.ndarray) -> np.ndarray:
    """MediaPipe 21 landmarks (..., 21, 3) -> the 26 canonical joints (..., 26, 3).

    ``palm`` is the midpoint of the wrist and middle knuckle; the finger metacarpal joints lie a
    quarter of the way from the wrist to their knuckle.
    """
    mp = np.asarray(landmarks, dtype=float)
    if mp.shape[-2:] != (21, 3):
        raise ValueError(f"MediaPipe landmarks need shape (..., 21, 3), got {mp.shape}")
    out = np.zeros(mp.shape[:-2] + (N_JOINTS, 3))
    for name, i in _MEDIAPIPE.items():
        out[..., JOINT_INDEX[name], :] = mp[..., i, :]
    wrist = mp[..., 0, :]
    out[..., JOINT_INDEX["palm"], :] = 0.5 * (wrist + mp[..., 9, :])
    for finger, knuckle in (("index", 5), ("middle", 9), ("ring", 13), ("little", 17)):
        out[..., JOINT_INDEX[f"{finger}_metacarpal"], :] = wrist + 0.25 * (
            mp[..., knuckle, :] - wrist
        )
    return out


def load_trace(reference_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(MediaPipe landmarks as stored (N, 21, 3), canonical joints in the palm frame (N, 26, 3))."""
    landmarks = np.load(reference_dir / TRACE)["keypoints"]
    joints = mediapipe_to_canonical(landmarks @ R_CANONICAL_TRACE.T)
    return landmarks, np.stack([keypoints_in_palm(j, "right") for j in joints])


class HandScorer:
    """Joint-limit, penetration and fingertip-direction scores of LEAP joint vectors."""

    def __init__(self, side: str = "right", penetration_tolerance: float = 1e-3):
        self.retargeter_map = LeapRetargeter(side).map
        self.model = self.retargeter_map.model
        self.data = mujoco.MjData(self.model)
        self.tolerance = penetration_tolerance
        self._finger_of_geom = np.full(self.model.ngeom, -1)
        for i, geoms in enumerate(finger_geoms(self.model).values()):
            self._finger_of_geom[geoms] = i
        self._tip_sites = [self.model.site(f"{f}_tip").id for f in LEAP_FINGERS]
        self._human_tips = [JOINT_INDEX[f"{f}_tip"] for f in LEAP_FINGERS]

    def min_finger_distance(self, q16: np.ndarray) -> float:
        """Smallest contact distance between geoms of different fingers (0 if none touch)."""
        self.data.qpos[self.retargeter_map.qpos_adr] = q16
        mujoco.mj_forward(self.model, self.data)
        worst = 0.0
        for c in self.data.contact[: self.data.ncon]:
            f1, f2 = self._finger_of_geom[c.geom1], self._finger_of_geom[c.geom2]
            if f1 >= 0 and f2 >= 0 and f1 != f2:
                worst = min(worst, float(c.dist))
        return worst

    def tip_angles(self, q16: np.ndarray, keypoints_palm: np.ndarray) -> np.ndarray:
        """Angle (deg) between human wrist->tip and LEAP hand origin->tip, per LEAP finger."""
        self.data.qpos[self.retargeter_map.qpos_adr] = q16
        mujoco.mj_kinematics(self.model, self.data)
        robot = self.data.site_xpos[self._tip_sites]
        human = keypoints_palm[self._human_tips]
        cos = np.sum(robot * human, axis=1) / (
            np.linalg.norm(robot, axis=1) * np.linalg.norm(human, axis=1)
        )
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    def pinch_distance(self, q16: np.ndarray) -> float:
        """Distance (m) between LEAP's thumb and index fingertip-pad sites."""
        self.data.qpos[self.retargeter_map.qpos_adr] = q16
        mujoco.mj_kinematics(self.model, self.data)
        thumb, index = self._tip_sites[0], self._tip_sites[1]
        return float(np.linalg.norm(self.data.site_xpos[thumb] - self.data.site_xpos[index]))

    def pinch(self, Q: np.ndarray, keypoints_palm: np.ndarray) -> dict:
        """Pinch fidelity (thumb-index): human pinch frames, and how many LEAP reproduced."""
        thumb, index = self._human_tips[0], self._human_tips[1]
        human = np.linalg.norm(keypoints_palm[:, thumb] - keypoints_palm[:, index], axis=1)
        robot = np.array([self.pinch_distance(q) for q in Q])
        human_pinch, robot_pinch = human < HUMAN_PINCH_M, robot < ROBOT_PINCH_M
        during = robot[human_pinch]
        return {
            "human_pinch_frames": int(human_pinch.sum()),
            "robot_pinch_frames": int(robot_pinch.sum()),
            "reproduced": int((human_pinch & robot_pinch).sum()),
            "robot_pinch_without_human": int((robot_pinch & ~human_pinch).sum()),
            "robot_distance_during_human_pinch_mm": (
                {
                    "min": round(float(during.min()) * 1e3, 1),
                    "mean": round(float(during.mean()) * 1e3, 1),
                }
                if during.size
                else None
            ),
            "closest_robot_distance_mm": round(float(robot.min()) * 1e3, 1),
        }

    def score(
        self,
        Q: np.ndarray,
        keypoints_palm: np.ndarray,
        times_s: np.ndarray,
        position_errors: np.ndarray | None = None,
        per_frame: dict | None = None,
    ) -> dict:
        """Scores of joint vectors ``Q`` (N x 16) for ``keypoints_palm`` (N x 26 x 3).
        ``position_errors``: the method's own fingertip position errors (N x 4, m).
        ``per_frame``: filled with the direction errors per frame (``tip_error_deg``, N x 4)."""
        lower, upper = self.retargeter_map.range.T
        distances = np.array([self.min_finger_distance(q) for q in Q])
        angles = np.array([self.tip_angles(q, k) for q, k in zip(Q, keypoints_palm, strict=True)])
        if per_frame is not None:
            per_frame["tip_error_deg"] = angles
        ms = np.asarray(times_s) * 1e3
        extra = {}
        if position_errors is not None:
            mm = np.asarray(position_errors) * 1e3
            extra["tip_position_error_mm"] = {
                f: {"mean": round(float(e.mean()), 1), "p95": round(float(np.percentile(e, 95)), 1)}
                for f, e in zip(LEAP_FINGERS, mm.T, strict=True)
            }
        return {
            "time_ms": {
                "mean": round(float(ms.mean()), 4),
                "p50": round(float(np.percentile(ms, 50)), 4),
                "p99": round(float(np.percentile(ms, 99)), 4),
            },
            "joint_limit_violations": int(((Q < lower - 1e-9) | (Q > upper + 1e-9)).sum()),
            "max_joint_limit_violation_rad": float(
                np.maximum(np.maximum(lower - Q, Q - upper), 0.0).max()
            ),
            "penetration_frames": int((distances < -self.tolerance).sum()),
            "worst_finger_distance_mm": round(float(distances.min()) * 1e3, 3),
            "tip_direction_error_deg": {
                f: round(float(a), 2)
                for f, a in zip(LEAP_FINGERS, angles.mean(axis=0), strict=True)
            },
            "tip_direction_error_p95_deg": {
                f: round(float(a), 2)
                for f, a in zip(LEAP_FINGERS, np.percentile(angles, 95, axis=0), strict=True)
            },
            **extra,
            "pinch": self.pinch(Q, keypoints_palm),
        }


def run_ours(keypoints_palm: np.ndarray, config: RetargetConfig | None = None):
    """Our retargeting of each frame: (joints N x 16, seconds per frame N, fingertip position
    errors after scaling N x 4 in m: pad site against its mapped human tip)."""
    retargeter = LeapRetargeter("right", config)
    tips = retargeter.map
    tip_sites = [retargeter.model.site(f"{f}_tip").id for f in LEAP_FINGERS]
    human_tips = [JOINT_INDEX[f"{f}_tip"] for f in LEAP_FINGERS]
    scales = np.array([tips.scale(f) for f in LEAP_FINGERS])[:, None]
    Q, times, errors = [], [], []
    for keypoints in keypoints_palm:
        start = time.perf_counter()
        Q.append(retargeter.retarget(keypoints))
        times.append(time.perf_counter() - start)
        target = tips.origin_offset + scales * keypoints[human_tips]
        reached = retargeter.configuration.data.site_xpos[tip_sites]
        errors.append(np.linalg.norm(reached - target, axis=1))
    return np.array(Q), np.array(times), np.array(errors)


def _dex_retargeting(urdf: Path):
    from dex_retargeting.retargeting_config import RetargetingConfig

    config = {
        "type": "vector",
        "urdf_path": str(urdf),
        "target_joint_names": [str(i) for i in range(16)],
        "target_origin_link_names": ["base"] * 4,
        "target_task_link_names": list(_DEX_TIP_LINKS),
        "target_link_human_indices": np.array([[0, 0, 0, 0], list(_MEDIAPIPE_TIPS)]),
        "scaling_factor": 1.6,  # dex-retargeting's own LEAP value
        "low_pass_alpha": 1.0,  # no filtering, like ours: scores the solver, not a filter
    }
    return RetargetingConfig.from_dict(config).build(), config


#: Our LEAP body -> the dex URDF link with the same frame origin (joint axis point).
_DEX_LINK = {
    **{
        f"{finger}_{ours}": f"{theirs}{suffix}"
        for finger, suffix in (("index", ""), ("middle", "_2"), ("ring", "_3"))
        for ours, theirs in (
            ("base", "mcp_joint"),
            ("proximal", "pip"),
            ("middle", "dip"),
            ("distal", "fingertip"),
        )
    },
    "thumb_base": "thumb_temp_base",
    "thumb_proximal": "thumb_pip",
    "thumb_middle": "thumb_dip",
    "thumb_distal": "thumb_fingertip",
}


def R_base_hand(retargeting, scorer: HandScorer) -> tuple[np.ndarray, list[int], float]:
    """Rotation from our LEAP ``hand`` frame to the dex URDF ``base`` frame, dex's joint order
    (index of each motor id), and the fit's largest residual (m): Kabsch on corresponding link
    origins over a few joint vectors."""
    robot = retargeting.optimizer.robot
    names = list(robot.dof_joint_names)
    order = [names.index(str(i)) for i in range(16)]
    link_ids = [robot.get_link_index(n) for n in _DEX_LINK.values()]
    rng = np.random.default_rng(0)
    ours, theirs = [], []
    lower, upper = scorer.retargeter_map.range.T
    for q in [np.zeros(16)] + [rng.uniform(lower, upper) * 0.5 for _ in range(5)]:
        q_pin = np.zeros(len(names))
        q_pin[order] = q
        robot.compute_forward_kinematics(q_pin)
        theirs += [robot.get_link_pose(i)[:3, 3] for i in link_ids]
        scorer.data.qpos[scorer.retargeter_map.qpos_adr] = q
        mujoco.mj_kinematics(scorer.model, scorer.data)
        ours += [scorer.data.body(b).xpos.copy() for b in _DEX_LINK]
    A, B = np.array(ours), np.array(theirs)
    A0, B0 = A - A.mean(0), B - B.mean(0)
    U, _, Vt = np.linalg.svd(A0.T @ B0)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    residual = float(np.linalg.norm(A0 @ R.T - B0, axis=1).max())
    return R, order, residual


def run_dex(keypoints_palm: np.ndarray, urdf: Path, scorer: HandScorer):
    retargeting, config = _dex_retargeting(urdf)
    R, order, residual = R_base_hand(retargeting, scorer)
    config["R_base_hand_fit_residual_mm"] = round(residual * 1e3, 3)
    # Feed dex-retargeting the same human hand, in its base frame: wrist->tip vectors.
    tips = keypoints_palm[:, [JOINT_INDEX[f"{f}_tip"] for f in LEAP_FINGERS]]
    vectors = tips @ R.T
    robot = retargeting.optimizer.robot
    base = robot.get_link_index("base")
    tip_links = [robot.get_link_index(n) for n in _DEX_TIP_LINKS]
    scaling = float(config["scaling_factor"])
    Q, times, errors = [], [], []
    for v in vectors:
        start = time.perf_counter()
        q_pin = retargeting.retarget(v)
        times.append(time.perf_counter() - start)
        Q.append(np.asarray(q_pin)[order])
        # Its own objective's residual: base -> tip link against the scaled human vector.
        robot.compute_forward_kinematics(np.asarray(q_pin))
        origin = robot.get_link_pose(base)[:3, 3]
        reached = np.array([robot.get_link_pose(i)[:3, 3] - origin for i in tip_links])
        errors.append(np.linalg.norm(reached - scaling * v, axis=1))
    return np.array(Q), np.array(times), config, np.array(errors)


def run(
    frames: int | None = None, reference_dir: Path | None = None, samples: dict | None = None
) -> dict:
    """Run both retargeters on the trace; returns the JSON-ready result. ``samples``: a dict
    filled with each method's time per frame (``time_ms``: method -> ms array) and fingertip
    direction error per frame (``tip_error_deg``: method -> N x 4 array, fingers in the order
    of :data:`LEAP_FINGERS`); the keys of both are ``ours`` and ``dex-retargeting``."""
    samples = {} if samples is None else samples
    reference_dir = reference_dir or find_reference_dir()
    if reference_dir is None:
        raise FileNotFoundError(
            "reference folder not found (../shared/reference or $BEAVR_REFERENCE_DIR): the "
            "retarget benchmark needs its human hand trace"
        )
    landmarks, keypoints = load_trace(reference_dir)
    if frames is not None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        landmarks, keypoints = landmarks[:frames], keypoints[:frames]
    scorer = HandScorer("right")
    Q, times, errors = run_ours(keypoints)
    per_frame: dict = {}
    result = {
        "frames": len(keypoints),
        "ours": scorer.score(Q, keypoints, times, errors, per_frame),
    }
    samples.setdefault("time_ms", {})["ours"] = np.asarray(times) * 1e3
    samples.setdefault("tip_error_deg", {})["ours"] = per_frame["tip_error_deg"]
    try:
        import dex_retargeting.retargeting_config  # noqa: F401
    except ImportError as error:
        result["dex_retargeting"] = (
            f"not run: {error}. Install it with `pip install dex-retargeting` (it needs pin and "
            "nlopt from PyPI, plus torch and six: `pip install torch six`)."
        )
        return result
    urdf = reference_dir / "dex_urdf_leap_hand" / "leap_hand_right.urdf"
    Q_dex, times_dex, config, errors_dex = run_dex(keypoints, urdf, scorer)
    result["dex_retargeting"] = scorer.score(Q_dex, keypoints, times_dex, errors_dex, per_frame)
    samples["time_ms"]["dex-retargeting"] = np.asarray(times_dex) * 1e3
    samples["tip_error_deg"]["dex-retargeting"] = per_frame["tip_error_deg"]
    result["dex_retargeting"]["config"] = {
        k: (v.tolist() if isinstance(v, np.ndarray) else v)
        for k, v in config.items()
        if k != "urdf_path"
    }
    result["time_ratio_ours_over_dex"] = round(
        result["ours"]["time_ms"]["mean"] / result["dex_retargeting"]["time_ms"]["mean"], 4
    )
    return result
