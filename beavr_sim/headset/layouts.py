"""Hand-tracking joint layouts, converted into and out of the canonical 26-joint array.

Every layout is a :class:`HandLayout`: its own joint names, the canonical joint at each of
them, and the linear map ``R_zup_source`` (a rotation, or a reflection for left-handed
sources) that takes its coordinates into ours (right-handed, Z-up: x forward, y left, z up).

Canonical joints a layout lacks are *derived* (finite positions, flagged ``tracked=False``):

- a metacarpal base (``index/middle/ring/little_metacarpal``) lies
  :data:`METACARPAL_BASE_FRACTION` of the way from the wrist to that finger's knuckle
  (``*_proximal``), about where the carpometacarpal joint sits on a human hand;
- the palm is the middle of the middle metacarpal (halfway from ``middle_metacarpal`` to
  ``middle_proximal``), where OpenXR and XR Hands put it.

Going back (:meth:`HandLayout.from_canonical`), source joints without a canonical counterpart
are derived the same way (OVR ``forearm_stub`` at the wrist, ``thumb0`` halfway from the
wrist to the thumb metacarpal).

Layouts: ``quest26`` (BEAVR Quest app, Unity XR Hands order), ``ovr24`` (legacy Meta
``OVRSkeleton`` bones), ``mediapipe21`` (MediaPipe landmarks, right-handed source frame),
``webxr25`` (WebXR Hand Input).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.wire.hand import FINGERS, JOINT_INDEX, JOINT_NAMES, N_JOINTS, HandFrame

#: Unity (left-handed: x right, y up, z forward) -> ours: x = z_u, y = -x_u, z = y_u. det -1.
R_ZUP_UNITY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
#: WebXR (right-handed: x right, y up, -z forward) -> ours: x = -z_w, y = -x_w, z = y_w. det +1.
R_ZUP_WEBXR = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
R_ZUP_UNITY.setflags(write=False)
R_ZUP_WEBXR.setflags(write=False)

#: Metacarpal base position as a fraction of the wrist -> knuckle segment (derived joints).
METACARPAL_BASE_FRACTION = 0.25

#: Derivation rules (target, from, to, fraction): target = from + fraction * (to - from).
#: Applied in order, each only when the layout lacks the target.
_CANONICAL_DERIVED: tuple[tuple[str, str, str, float], ...] = (
    *((f"{f}_metacarpal", "wrist", f"{f}_proximal", METACARPAL_BASE_FRACTION) for f in FINGERS[1:]),
    ("palm", "middle_metacarpal", "middle_proximal", 0.5),
)


def _transform(R: np.ndarray, points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points need a last axis of size 3, got shape {points.shape}")
    return points @ R.T


def unity_to_zup(points_unity: np.ndarray) -> np.ndarray:
    """Points (..., 3) in Unity's left-handed Y-up frame -> right-handed Z-up."""
    return _transform(R_ZUP_UNITY, points_unity)


def zup_to_unity(points_zup: np.ndarray) -> np.ndarray:
    """Inverse of :func:`unity_to_zup`."""
    return _transform(R_ZUP_UNITY.T, points_zup)


def webxr_to_zup(points_webxr: np.ndarray) -> np.ndarray:
    """Points (..., 3) in a WebXR reference space (right-handed, Y up, -Z forward) -> Z-up."""
    return _transform(R_ZUP_WEBXR, points_webxr)


def zup_to_webxr(points_zup: np.ndarray) -> np.ndarray:
    """Inverse of :func:`webxr_to_zup`."""
    return _transform(R_ZUP_WEBXR.T, points_zup)


def _lerp(points: np.ndarray, a: int, b: int, fraction: float) -> np.ndarray:
    return points[..., a, :] + fraction * (points[..., b, :] - points[..., a, :])


@dataclass(frozen=True, eq=False)
class HandLayout:
    """One source joint layout and its frame.

    ``canonical_names[i]``: the canonical joint at source joint ``i`` (None: no counterpart;
    such a joint is rebuilt by ``source_derived`` in :meth:`from_canonical`).
    ``R_zup_source``: orthogonal 3x3, ours = R_zup_source @ source.
    """

    name: str
    joint_names: tuple[str, ...]
    canonical_names: tuple[str | None, ...]
    R_zup_source: np.ndarray
    source_derived: Mapping[str, tuple[str, str, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.joint_names) != len(self.canonical_names):
            raise ValueError(
                f"layout {self.name!r}: {len(self.joint_names)} joint names but "
                f"{len(self.canonical_names)} canonical names"
            )
        mapped = [c for c in self.canonical_names if c is not None]
        for c in mapped:
            check_name("hand joint", c, JOINT_NAMES)
        if len(set(mapped)) != len(mapped):
            raise ValueError(f"layout {self.name!r} maps two joints to one canonical joint")
        for c in ("wrist", "middle_proximal", *(f"{f}_proximal" for f in FINGERS[1:])):
            if c not in mapped:
                raise ValueError(f"layout {self.name!r} lacks {c!r}, needed to derive joints")
        unmapped = {
            n for n, c in zip(self.joint_names, self.canonical_names, strict=True) if c is None
        }
        if unmapped != set(self.source_derived):
            raise ValueError(
                f"layout {self.name!r}: joints without a canonical counterpart {sorted(unmapped)}"
                f" need exactly one derivation each, got {sorted(self.source_derived)}"
            )
        R = np.array(self.R_zup_source, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9):
            raise ValueError(f"layout {self.name!r}: R_zup_source must be an orthogonal 3x3")
        R.setflags(write=False)
        object.__setattr__(self, "R_zup_source", R)
        object.__setattr__(self, "source_derived", MappingProxyType(dict(self.source_derived)))
        source = np.array([i for i, c in enumerate(self.canonical_names) if c is not None])
        target = np.array([JOINT_INDEX[c] for c in self.canonical_names if c is not None])
        object.__setattr__(self, "_source_index", source)
        object.__setattr__(self, "_canonical_index", target)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def derived_joints(self) -> tuple[str, ...]:
        """Canonical joints this layout lacks (derived, flagged untracked)."""
        mapped = set(self.canonical_names)
        return tuple(t for t, *_ in _CANONICAL_DERIVED if t not in mapped)

    def _check_shape(self, points: np.ndarray, n: int, what: str) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        if points.ndim < 2 or points.shape[-2:] != (n, 3):
            raise ValueError(
                f"layout {self.name!r}: {what} need shape (..., {n}, 3), got {points.shape}"
            )
        return points

    def to_canonical(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Source points (..., n_joints, 3) -> canonical joints (..., 26, 3) and tracked (..., 26).

        Source joints that are NaN stay NaN and untracked; derived joints are untracked.
        """
        points = self._check_shape(points, self.n_joints, "source points")
        points_zup = points @ self.R_zup_source.T
        lead = points.shape[:-2]
        joints = np.full((*lead, N_JOINTS, 3), np.nan)
        tracked = np.zeros((*lead, N_JOINTS), dtype=bool)
        joints[..., self._canonical_index, :] = points_zup[..., self._source_index, :]
        tracked[..., self._canonical_index] = np.isfinite(
            joints[..., self._canonical_index, :]
        ).all(axis=-1)
        for target in self.derived_joints:
            _, a, b, fraction = next(rule for rule in _CANONICAL_DERIVED if rule[0] == target)
            joints[..., JOINT_INDEX[target], :] = _lerp(
                joints, JOINT_INDEX[a], JOINT_INDEX[b], fraction
            )
        return joints, tracked

    def from_canonical(self, joints: np.ndarray) -> np.ndarray:
        """Canonical joints (..., 26, 3) -> source points (..., n_joints, 3) in the source frame."""
        joints = self._check_shape(joints, N_JOINTS, "canonical joints")
        out = np.empty((*joints.shape[:-2], self.n_joints, 3))
        out[..., self._source_index, :] = joints[..., self._canonical_index, :]
        for i, name in enumerate(self.joint_names):
            if name in self.source_derived:
                a, b, fraction = self.source_derived[name]
                out[..., i, :] = _lerp(joints, JOINT_INDEX[a], JOINT_INDEX[b], fraction)
        return out @ self.R_zup_source


def _quest26() -> HandLayout:
    return HandLayout("quest26", JOINT_NAMES, JOINT_NAMES, R_ZUP_UNITY)


def _ovr24() -> HandLayout:
    bones = (
        ("wrist_root", "wrist"),
        ("forearm_stub", None),
        ("thumb0", None),
        ("thumb1", "thumb_metacarpal"),
        ("thumb2", "thumb_proximal"),
        ("thumb3", "thumb_distal"),
        *(
            (f"{f}{k}", f"{f}_{j}")
            for f in ("index", "middle", "ring")
            for k, j in ((1, "proximal"), (2, "intermediate"), (3, "distal"))
        ),
        *(
            (f"pinky{k}", f"little_{j}")
            for k, j in enumerate(("metacarpal", "proximal", "intermediate", "distal"))
        ),
        *(
            (f"{f}_tip", f"{c}_tip")
            for f, c in zip(("thumb", "index", "middle", "ring", "pinky"), FINGERS, strict=True)
        ),
    )
    return HandLayout(
        "ovr24",
        tuple(b for b, _ in bones),
        tuple(c for _, c in bones),
        R_ZUP_UNITY,
        source_derived={
            "forearm_stub": ("wrist", "wrist", 0.0),
            "thumb0": ("wrist", "thumb_metacarpal", 0.5),
        },
    )


def _mediapipe_names() -> tuple[tuple[str, str], ...]:
    thumb = (("cmc", "metacarpal"), ("mcp", "proximal"), ("ip", "distal"), ("tip", "tip"))
    finger = (("mcp", "proximal"), ("pip", "intermediate"), ("dip", "distal"), ("tip", "tip"))
    source = {"index": "index_finger", "middle": "middle_finger", "ring": "ring_finger"}
    source["little"] = "pinky"
    return (
        ("wrist", "wrist"),
        *((f"thumb_{s}", f"thumb_{c}") for s, c in thumb),
        *((f"{source[f]}_{s}", f"{f}_{c}") for f in FINGERS[1:] for s, c in finger),
    )


def mediapipe21(R_zup_source: np.ndarray | None = None) -> HandLayout:
    """MediaPipe's 21 landmarks given in a right-handed frame; ``R_zup_source`` (a rotation,
    default identity) takes that frame to Z-up."""
    R = np.eye(3) if R_zup_source is None else np.asarray(R_zup_source, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9):
        raise ValueError(f"R_zup_source must be a 3x3 rotation, got {R!r}")
    if np.linalg.det(R) < 0:
        raise ValueError(
            "R_zup_source must be a rotation (det +1): MediaPipe input is right-handed"
        )
    names = _mediapipe_names()
    return HandLayout("mediapipe21", tuple(s for s, _ in names), tuple(c for _, c in names), R)


def _webxr25() -> HandLayout:
    thumb = ("metacarpal", "phalanx-proximal", "phalanx-distal", "tip")
    finger = ("metacarpal", "phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip")
    source = {"index": "index-finger", "middle": "middle-finger", "ring": "ring-finger"}
    source["little"] = "pinky-finger"
    names = ("wrist", *(f"thumb-{j}" for j in thumb))
    names += tuple(f"{source[f]}-{j}" for f in FINGERS[1:] for j in finger)
    canonical = tuple(n for n in JOINT_NAMES if n != "palm")
    return HandLayout("webxr25", names, canonical, R_ZUP_WEBXR)


#: Built-in layouts by name (read-only).
LAYOUTS: Mapping[str, HandLayout] = MappingProxyType(
    {layout.name: layout for layout in (_quest26(), _ovr24(), mediapipe21(), _webxr25())}
)


def get_layout(layout: str | HandLayout) -> HandLayout:
    """A layout by name (raises with the valid names) or the layout itself."""
    if isinstance(layout, HandLayout):
        return layout
    return LAYOUTS[check_name("hand layout", layout, LAYOUTS)]


def to_hand_frame(
    layout: str | HandLayout,
    points: np.ndarray,
    side: str,
    t_source: float,
    t_receive: float,
    **state: object,
) -> HandFrame:
    """One hand's source points -> :class:`HandFrame`; ``state``: ``pinch``, ``resolution``,
    ``paused``."""
    joints, tracked = get_layout(layout).to_canonical(points)
    if joints.shape != (N_JOINTS, 3):
        raise ValueError(f"to_hand_frame takes one hand, got joints of shape {joints.shape}")
    return HandFrame(side, t_source, t_receive, joints, tracked, **state)  # type: ignore[arg-type]
