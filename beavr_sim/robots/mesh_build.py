"""The visual-mesh generator: our own simplified meshes of the xArm7 and the LEAP hand, from
the reference shapes (``../shared/reference``, read only; see docs/models.md "Visual
geometry").

For each of our link bodies it takes the reference link's surface (MuJoCo Menagerie STL; the
LEAP palm from the dex-urdf OBJ), moves it into our body's frame (checked: our body frames
are the reference's, to 0.1 mm), decimates it by vertex clustering and writes a small binary
STL under ``assets/meshes/``. The xArm7's links come in two parts, the white shell and the
grey joint caps (:func:`cap_faces`). The left LEAP palm (no reference mesh) is the right
palm mirrored onto the left palm's collision boxes (:func:`palm_mirror`; the fit's residual
is printed and checked).

    python -m beavr_sim.robots.mesh_build build [--reference DIR]
    python -m beavr_sim.robots.mesh_build check [--reference DIR]   # files up to date?

Deterministic: building twice gives byte-identical files (``tests/test_visuals.py``).
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.assets import assets_dir, mjcf_path
from beavr_sim.robots.meshes import (
    Mesh,
    decimate,
    decimate_labelled,
    quat_to_mat,
    read_obj,
    read_stl,
    stl_bytes,
)

DEFAULT_REFERENCE = Path(__file__).resolve().parents[2].parent / "shared" / "reference"
XARM_REF = "menagerie_ufactory_xarm7/xarm7_nohand.xml"
LEAP_REF = {
    "right": "menagerie_leap_hand/right_hand.xml",
    "left": "menagerie_leap_hand/left_hand.xml",
}
PALM_OBJ = "dex_urdf_leap_hand/meshes/visual/palm_lower.obj"
#: dex-urdf leap_hand_right.urdf: the palm visual's origin in palm_lower (rpy 0).
PALM_OBJ_ORIGIN = np.array([-0.0200, 0.02575, -0.0347])

#: Vertex-clustering cell (m) per robot (the xArm7 STLs are coarse already).
CELL = {"xarm7": 0.008, "leap": 0.004}

#: Our xArm7 body -> the reference meshes on it (link7 also carries the flange).
XARM_LINKS: dict[str, tuple[str, ...]] = {
    "link_base": ("link_base.stl",),
    **{f"link{i}": (f"link{i}.stl",) for i in range(1, 7)},
    "link7": ("link7.stl", "end_tool.stl"),
}
#: Our LEAP body (index finger and thumb; middle and ring share the index's meshes) -> the
#: reference body of the same frame.
LEAP_LINKS: dict[str, str] = {
    "finger_base": "mcp_joint",
    "finger_proximal": "pip",
    "finger_middle": "dip",
    "finger_distal": "fingertip",
    "thumb_base": "pip_4",
    "thumb_proximal": "thumb_pip",
    "thumb_middle": "thumb_dip",
    "thumb_distal": "thumb_fingertip",
}
OUR_LEAP_BODY = {
    "finger_base": "index_base",
    "finger_proximal": "index_proximal",
    "finger_middle": "index_middle",
    "finger_distal": "index_distal",
    "thumb_base": "thumb_base",
    "thumb_proximal": "thumb_proximal",
    "thumb_middle": "thumb_middle",
    "thumb_distal": "thumb_distal",
}
#: dex-urdf's LEAP URDFs, per side: the file and its palm link (the same frame as our palm
#: body: checked through the origins of the joints on the palm, PALM_JOINTS).
PALM_URDF = {
    "right": ("dex_urdf_leap_hand/leap_hand_right.urdf", "palm_lower"),
    "left": ("dex_urdf_leap_hand/leap_hand_left.urdf", "palm_lower_left"),
}
#: URDF joint on the palm (Dynamixel id) -> our body it places.
PALM_JOINTS = {"1": "index_base", "5": "middle_base", "9": "ring_base", "12": "thumb_base"}
URDF_FRAME_TOLERANCE = 6e-4  # m; the URDF gives its origins to 0.1 mm
#: The xArm7's joint caps (grey on the real arm; the links are white). The caps sit on the
#: joints whose axis crosses the arm (2, 4, 6: more than CROSS_ANGLE_DEG from the line joining
#: the neighbouring joints' origins; the others turn about the arm's own line). Where such an
#: axis leaves a link's surface (the outermost crossing of the axis line with the surface,
#: each way), the cap is the surface around that point that lies within CAP_RADIUS of the
#: axis and within CAP_DEPTH of the point along it (every corner of its faces), and is
#: connected to it through such surface. The reference meshes are smooth domes there, so
#: the radius draws the cap's rim.
CROSS_ANGLE_DEG = 45.0
CAP_RADIUS = 0.03  # m
CAP_DEPTH = 0.015  # m
#: Labels of the xArm7's two materials.
SHELL, HOUSING = 0, 1
FRAME_TOLERANCE = 1e-4  # m; our body frames vs the reference's
#: The left palm's collision boxes vs the mirrored right ones (the URDFs round to 1 mm).
MIRROR_TOLERANCE = 2.5e-3  # m
MIRROR_AXES_TOLERANCE = 0.01  # the best improper fit's rotation vs the reflection y -> -y
REFLECT_Y = np.diag([1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Pose:
    R: np.ndarray
    p: np.ndarray

    def __mul__(self, other: Pose) -> Pose:
        return Pose(self.R @ other.R, self.R @ other.p + self.p)

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.p)


def _local(element) -> Pose:
    return Pose(quat_to_mat(element.quat), np.array(element.pos, dtype=np.float64))


def _in_root(spec: mujoco.MjSpec, name: str, root: str) -> Pose:
    """Pose of body ``name`` in body ``root`` (an ancestor) at the zero configuration."""
    pose, body = Pose(np.eye(3), np.zeros(3)), spec.body(name)
    while body.name != root:
        pose = _local(body) * pose
        body = body.parent
        if body is None or body.name == "world":
            raise ValueError(f"{root!r} is not an ancestor of {name!r}")
    return pose


def _visual_mesh_geoms(spec: mujoco.MjSpec, body: str) -> list:
    """The reference body's visual mesh geoms (group 2, or every mesh geom if none is)."""
    geoms = [g for g in spec.body(body).geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]
    visual = [g for g in geoms if g.group == 2]
    return visual or geoms


def _mesh_file(spec: mujoco.MjSpec, mesh_name: str) -> str:
    for mesh in spec.meshes:
        if mesh.name == mesh_name or Path(mesh.file).stem == mesh_name:
            return mesh.file
    raise KeyError(f"mesh {mesh_name!r} not in the reference spec")


def _check_frame(ours: Pose, theirs: Pose, what: str) -> None:
    err = max(np.abs(ours.p - theirs.p).max(), np.abs(ours.R - theirs.R).max())
    if err > FRAME_TOLERANCE:
        raise ValueError(f"{what}: our body frame differs from the reference's by {err:.2e}")


def crossing_axes(spec: mujoco.MjSpec) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Per xArm link, (origin, unit axis) in the link's frame of each of the joints at its two
    ends whose axis crosses the arm (see :data:`CROSS_ANGLE_DEG`)."""
    links = list(XARM_LINKS)  # link_base, link1..link7: joint k turns link k
    root = [_in_root(spec, body, "link_base") for body in links]
    origins = [pose.p for pose in root] + [root[-1].p]  # the flange is link7's origin
    crossing = {}
    for k in range(1, len(links)):
        (joint,) = spec.body(links[k]).joints
        if np.any(joint.pos) or not np.allclose(joint.axis, (0.0, 0.0, 1.0)):
            raise ValueError(f"{links[k]}: its joint is not the body's z axis")
        axis = root[k].R[:, 2]
        line = origins[k + 1] - origins[k - 1]
        cos = abs(axis @ line) / np.linalg.norm(line)
        if cos < np.cos(np.radians(CROSS_ANGLE_DEG)):
            crossing[k] = (origins[k], axis)
    out: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {body: [] for body in links}
    for k, (origin, axis) in crossing.items():
        for body in (links[k - 1], links[k]):  # the two links the joint joins
            frame = root[links.index(body)].inverse()
            out[body].append((frame.R @ origin + frame.p, frame.R @ axis))
    return out


def _face_frames(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Corners (m, 3, 3) and unit normals (m, 3) of the faces."""
    tri = mesh.vertices[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    return tri, np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)


def _line_crossings(tri: np.ndarray, origin: np.ndarray, axis: np.ndarray):
    """(face index, s) of every face the line ``origin + s axis`` crosses."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(axis, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-15
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
    d = origin - tri[:, 0]
    u = np.einsum("ij,ij->i", d, h) * inv
    q = np.cross(d, e1)
    v = (q @ axis) * inv
    s = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    return np.flatnonzero(hit), s[hit]


def _radial(points: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    rel = points - origin
    return np.linalg.norm(rel - (rel @ axis)[:, None] * axis, axis=1)


def split_caps(mesh: Mesh, axes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[Mesh, np.ndarray]:
    """``mesh`` cut along the caps' rims (faces split where they cross the cylinder of
    :data:`CAP_RADIUS` about each axis), and per face whether it is on a cap."""
    for origin, axis in axes:
        mesh = mesh.cut(_radial(mesh.vertices, origin, axis) - CAP_RADIUS)
    return mesh, cap_faces(mesh, axes)


def _grow(faces: np.ndarray, seed: int, allowed: np.ndarray) -> np.ndarray:
    """The faces connected to face ``seed`` (through shared vertices) by ``allowed`` faces."""
    region = np.zeros(len(faces), dtype=bool)
    region[seed] = allowed[seed]
    reached = np.zeros(faces.max() + 1, dtype=bool)
    while True:
        reached[faces[region]] = True
        grown = allowed & reached[faces].any(axis=1)
        if (grown == region).all():
            return region
        region = grown


def cap_faces(mesh: Mesh, axes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Which faces of ``mesh`` are on a joint cap (see :data:`CAP_RADIUS` and the rest): those
    whose corners all lie in the cap's cylinder, connected to the axis' exit point."""
    tri, normal = _face_frames(mesh)
    on_cap = np.zeros(len(mesh.faces), dtype=bool)
    for origin, axis in axes:
        faces, s = _line_crossings(tri, origin, axis)
        facing = normal[faces] @ axis
        for sign in (1.0, -1.0):  # the last crossing each way, leaving the link
            out = np.flatnonzero(sign * facing > 0)
            if not len(out):
                continue
            leaving = out[np.argmax(sign * s[out])]
            point = origin + s[leaving] * axis
            inside = (np.abs((mesh.vertices - point) @ axis) <= CAP_DEPTH) & (
                _radial(mesh.vertices, point, axis) <= CAP_RADIUS + 1e-9
            )
            on_cap |= _grow(mesh.faces, faces[leaving], inside[mesh.faces].all(axis=1))
    return on_cap


def xarm_meshes(reference: Path) -> dict[str, tuple[Mesh, np.ndarray]]:
    """Our xArm7 links, each in its body frame, with a label per face (:data:`SHELL`, or
    :data:`HOUSING`: the joint caps, and the flange)."""
    ref = mujoco.MjSpec.from_file(str(reference / XARM_REF))
    ours = mujoco.MjSpec.from_file(str(mjcf_path("xarm7_leap/xarm7.xml")))
    assets = (reference / XARM_REF).parent / "assets"
    axes = crossing_axes(ours)
    out = {}
    for body, files in XARM_LINKS.items():
        if body != "link_base":
            _check_frame(_in_root(ours, body, "link_base"), _in_root(ref, body, "link_base"), body)
        link, *tool = [read_stl(assets / f) for f in files]
        link, on_cap = split_caps(link, axes[body])
        labels = np.where(on_cap, HOUSING, SHELL)
        for part in tool:  # the flange: metal
            labels = np.concatenate([labels, np.full(len(part.faces), HOUSING)])
        out[body] = (Mesh.merge([link, *tool]), labels.astype(np.int32))
    return out


def _leap_link(ref: mujoco.MjSpec, ref_body: str, folder: Path) -> Mesh:
    parts = []
    for geom in _visual_mesh_geoms(ref, ref_body):
        mesh = read_stl(folder / _mesh_file(ref, geom.meshname))
        parts.append(mesh.transformed(quat_to_mat(geom.quat), np.array(geom.pos)))
    return Mesh.merge(parts)


def _improper_fit(src: np.ndarray, dst: np.ndarray) -> tuple[Pose, float]:
    """The reflection R (det -1) and p with R src + p ~ dst (least squares); max residual."""
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, -d]) @ U.T
    p = cd - R @ cs
    return Pose(R, p), float(np.linalg.norm(src @ R.T + p - dst, axis=1).max())


def _urdf_palm(reference: Path, side: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The centres of the palm link's collision boxes (in file order) and the origins of the
    joints on the palm, in the palm frame, from dex-urdf's URDF of ``side``."""
    file, link = PALM_URDF[side]
    root = ET.parse(reference / file).getroot()
    (palm,) = [e for e in root.iter("link") if e.get("name") == link]
    boxes = [
        [float(x) for x in c.find("origin").get("xyz").split()]
        for c in palm.iter("collision")
        if c.find("geometry/box") is not None
    ]
    joints = {
        j.get("name"): np.array([float(x) for x in j.find("origin").get("xyz").split()])
        for j in root.iter("joint")
        if j.find("parent").get("link") == link
    }
    return np.array(boxes), joints


def palm_mirror(reference: Path, ours: dict[str, mujoco.MjSpec]) -> tuple[Pose, float]:
    """The left palm as the right one mirrored: the reflection y -> -y (both palm frames'
    axes agree: checked) and the shift that best maps the right palm's collision boxes onto
    the left palm's (dex-urdf: the palm's own shape, per side); the largest box residual.

    Not the finger mounts: each finger's body frame sits 15 mm to the side of its module's
    centre line, on the same side on both hands (the same, unmirrored modules), so a mirror
    that maps the mounts onto each other moves the palm 29 mm across (the thumb base then
    floated off it, and the fingers sat off their blocks)."""
    boxes = {}
    for side in PALM_URDF:
        boxes[side], joints = _urdf_palm(reference, side)
        for joint, body in PALM_JOINTS.items():
            err = np.abs(joints[joint] - _in_root(ours[side], body, "palm").p).max()
            if err > URDF_FRAME_TOLERANCE:
                raise ValueError(f"leap_{side} {body}: the URDF's palm frame differs by {err:.2e}")
    right, left = boxes["right"], boxes["left"]
    best, _ = _improper_fit(right, left)
    if np.abs(best.R - REFLECT_Y).max() > MIRROR_AXES_TOLERANCE:
        raise ValueError(f"the palms are not mirror images across y: {best.R.round(3)}")
    shift = left.mean(axis=0) - REFLECT_Y @ right.mean(axis=0)
    residual = np.linalg.norm(right @ REFLECT_Y + shift - left, axis=1).max()
    return Pose(REFLECT_Y, shift), float(residual)


def leap_meshes(reference: Path) -> dict[str, Mesh]:
    """Our LEAP links (both sides' fingers are the same modules), and the palm per side."""
    refs = {s: mujoco.MjSpec.from_file(str(reference / f)) for s, f in LEAP_REF.items()}
    ours = {s: mujoco.MjSpec.from_file(str(mjcf_path(f"xarm7_leap/leap_{s}.xml"))) for s in refs}
    folder = (reference / LEAP_REF["right"]).parent / "assets"
    for side in refs:  # every mapped frame agrees with the reference, both sides
        for key, ref_body in LEAP_LINKS.items():
            for finger, suffix in (("index", ""), ("middle", "_2"), ("ring", "_3")):
                if not key.startswith("finger"):
                    if finger != "index":
                        continue
                    mine, theirs = OUR_LEAP_BODY[key], ref_body
                else:
                    mine = OUR_LEAP_BODY[key].replace("index", finger)
                    theirs = ref_body + suffix
                _check_frame(
                    _in_root(ours[side], mine, "palm"),
                    _in_root(refs[side], theirs, "palm_lower"),
                    f"leap_{side} {mine}",
                )
    out = {key: _leap_link(refs["right"], body, folder) for key, body in LEAP_LINKS.items()}
    palm = read_obj(reference / PALM_OBJ).transformed(np.eye(3), PALM_OBJ_ORIGIN)
    out["palm_right"] = palm
    mirror, residual = palm_mirror(reference, ours)
    print(f"left palm: the right one mirrored onto the left's boxes, {residual * 1e3:.2f} mm")
    if residual > MIRROR_TOLERANCE:
        raise ValueError(f"left palm mirror fit residual {residual * 1e3:.2f} mm is too large")
    out["palm_left"] = palm.transformed(mirror.R, mirror.p)
    return out


def build(reference: Path = DEFAULT_REFERENCE) -> dict[Path, bytes]:
    """Every generated file: path -> its bytes (not written)."""
    if not reference.is_dir():
        raise FileNotFoundError(f"reference folder not found: {reference} (pass --reference)")
    root = assets_dir() / "meshes"
    files: dict[Path, bytes] = {}
    for name, (mesh, labels) in xarm_meshes(reference).items():
        coarse, coarse_labels = decimate_labelled(mesh, labels, CELL["xarm7"])
        for label, part in ((SHELL, "shell"), (HOUSING, "housing")):
            if (coarse_labels == label).any():  # the base has no cap
                files[root / "xarm7" / f"{name}_{part}.stl"] = stl_bytes(
                    coarse.subset(coarse_labels == label)
                )
    for name, mesh in leap_meshes(reference).items():
        files[root / "leap" / f"{name}.stl"] = stl_bytes(decimate(mesh, CELL["leap"]))
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.robots.mesh_build")
    parser.add_argument("command", choices=("build", "check"))
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    args = parser.parse_args(argv)
    files = build(args.reference)
    stale = [p for p, b in files.items() if not p.is_file() or p.read_bytes() != b]
    extra = sorted(set((assets_dir() / "meshes").rglob("*.stl")) - set(files))
    if args.command == "check":
        for p in stale:
            print(f"out of date: {p}")
        for p in extra:
            print(f"not generated (remove it): {p}")
        return 1 if stale or extra else 0
    for path in extra:  # meshes of an older layout
        path.unlink()
        print(f"removed {path.relative_to(assets_dir())}")
    for path, data in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        triangles = (len(data) - 84) // 50
        print(f"{path.relative_to(assets_dir())}: {triangles} triangles, {len(data)} bytes")
    print(f"total {sum(map(len, files.values()))} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
