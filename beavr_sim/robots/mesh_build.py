"""The visual-mesh generator: our own simplified meshes of the xArm7 and the LEAP hand, from
the reference shapes (``../shared/reference``, read only; see docs/models.md "Visual
geometry").

For each of our link bodies it takes the reference link's surface (MuJoCo Menagerie STL; the
LEAP palm from the dex-urdf OBJ), moves it into our body's frame (checked: our body frames
are the reference's, to 0.1 mm), decimates it by vertex clustering and writes a small binary
STL under ``assets/meshes/``. The left LEAP palm (no reference mesh) is the right palm
mirrored onto the left hand's finger mounts (the fit's residual is printed and checked).

    python -m beavr_sim.robots.mesh_build build [--reference DIR]
    python -m beavr_sim.robots.mesh_build check [--reference DIR]   # files up to date?

Deterministic: building twice gives byte-identical files (``tests/test_visuals.py``).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.assets import assets_dir, mjcf_path
from beavr_sim.robots.meshes import (
    Mesh,
    decimate,
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
CELL = {"xarm7": 0.005, "leap": 0.0025}

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
#: Finger bases that pin the palm. Not the thumb: the left hand's thumb module sits 29 mm
#: further out than the mirror image of the right one (the same, unmirrored, finger modules).
PALM_MOUNTS = ("index_base", "middle_base", "ring_base")
FRAME_TOLERANCE = 1e-4  # m; our body frames vs the reference's
MIRROR_TOLERANCE = 1e-3  # m; left finger mounts vs the mirrored right ones


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


def xarm_meshes(reference: Path) -> dict[str, Mesh]:
    """Our xArm7 links, each in its body frame."""
    ref = mujoco.MjSpec.from_file(str(reference / XARM_REF))
    ours = mujoco.MjSpec.from_file(str(mjcf_path("xarm7_leap/xarm7.xml")))
    assets = (reference / XARM_REF).parent / "assets"
    out = {}
    for body, files in XARM_LINKS.items():
        if body != "link_base":
            _check_frame(_in_root(ours, body, "link_base"), _in_root(ref, body, "link_base"), body)
        out[body] = Mesh.merge([read_stl(assets / f) for f in files])
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


def _palm_points(spec: mujoco.MjSpec) -> np.ndarray:
    """Points that pin a palm in its frame: the finger mounts, the palm centre (palmar face)
    and the hand's mount origin (wrist end), which span all three axes."""
    mounts = [_in_root(spec, b, "palm").p for b in PALM_MOUNTS]
    centre = np.array(spec.site("palm_centre").pos, dtype=np.float64)
    wrist = _local(spec.body("palm")).inverse().p
    return np.array([*mounts, centre, wrist])


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
    mirror, residual = _improper_fit(_palm_points(ours["right"]), _palm_points(ours["left"]))
    print(
        f"left palm: the right one mirrored onto the left mounts, residual {residual * 1e3:.3f} mm"
    )
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
    for robot, meshes in (("xarm7", xarm_meshes(reference)), ("leap", leap_meshes(reference))):
        for name, mesh in meshes.items():
            files[root / robot / f"{name}.stl"] = stl_bytes(decimate(mesh, CELL[robot]))
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.robots.mesh_build")
    parser.add_argument("command", choices=("build", "check"))
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    args = parser.parse_args(argv)
    files = build(args.reference)
    stale = [p for p, b in files.items() if not p.is_file() or p.read_bytes() != b]
    if args.command == "check":
        for p in stale:
            print(f"out of date: {p}")
        return 1 if stale else 0
    for path, data in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        print(f"{path.relative_to(assets_dir())}: {len(data) // 50} triangles, {len(data)} bytes")
    print(f"total {sum(map(len, files.values()))} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
