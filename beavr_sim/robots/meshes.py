"""Triangle meshes as plain arrays: binary STL and OBJ reading, binary STL writing, rigid
transforms and vertex-clustering decimation (our own, deterministic: the same input gives
byte-identical output). Used by :mod:`beavr_sim.robots.mesh_build` (the asset generator) and
:mod:`beavr_sim.robots.visuals` (loading the generated meshes into a spec)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

_STL_RECORD = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attr", "<u2")])


@dataclass(frozen=True)
class Mesh:
    """``vertices`` (n, 3) float64 metres, ``faces`` (m, 3) int32 vertex indices, counter-
    clockwise seen from outside."""

    vertices: np.ndarray
    faces: np.ndarray

    def transformed(self, R: np.ndarray, p: np.ndarray) -> Mesh:
        """``R @ v + p`` for every vertex; a reflection (det R < 0) flips the faces' order so
        that they still face outwards."""
        faces = self.faces if np.linalg.det(R) > 0 else self.faces[:, ::-1]
        return Mesh(self.vertices @ np.asarray(R).T + np.asarray(p), np.ascontiguousarray(faces))

    @staticmethod
    def merge(meshes: list[Mesh]) -> Mesh:
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
        )


def _welded(triangles: np.ndarray) -> Mesh:
    """Shared vertices from a (m, 3, 3) triangle soup (exact duplicates merged)."""
    vertices, index = np.unique(triangles.reshape(-1, 3), axis=0, return_inverse=True)
    return Mesh(vertices.astype(np.float64), index.reshape(-1, 3).astype(np.int32))


def read_stl(path: Path | str) -> Mesh:
    """A binary STL file (the only kind the references and our assets use)."""
    data = Path(path).read_bytes()
    if len(data) < 84:
        raise ValueError(f"{path}: too short for a binary STL")
    n = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if len(data) != 84 + 50 * n:
        raise ValueError(f"{path}: not a binary STL ({len(data)} bytes for {n} triangles)")
    records = np.frombuffer(data, dtype=_STL_RECORD, count=n, offset=84)
    return _welded(records["vertices"].astype(np.float64))


def read_obj(path: Path | str) -> Mesh:
    """Vertices and faces of a Wavefront OBJ (``v`` and ``f`` lines; polygons as fans)."""
    vertices: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("v "):
            vertices.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
            idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
            faces.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
    return Mesh(np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.int32))


def stl_bytes(mesh: Mesh) -> bytes:
    """Binary STL of ``mesh`` (float32 vertices, unit face normals), header naming us."""
    tri = mesh.vertices[mesh.faces].astype(np.float32)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).astype(np.float64)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    records = np.zeros(len(tri), dtype=_STL_RECORD)
    records["normal"], records["vertices"] = normal.astype(np.float32), tri
    header = b"beavr_sim visual mesh (robots/mesh_build.py)".ljust(80, b" ")
    return header + np.uint32(len(tri)).tobytes() + records.tobytes()


def decimate(mesh: Mesh, cell: float) -> Mesh:
    """Vertex clustering: vertices in the same cube of side ``cell`` (metres) merge into their
    mean; triangles that collapse, and repeated ones, are dropped. Deterministic."""
    if not cell > 0:
        raise ValueError(f"cell must be positive, got {cell!r}")
    keys = np.floor(mesh.vertices / cell).astype(np.int64)
    _, cluster = np.unique(keys, axis=0, return_inverse=True)
    cluster = cluster.reshape(-1)
    n = int(cluster.max()) + 1
    counts = np.bincount(cluster, minlength=n).astype(np.float64)
    vertices = (
        np.stack(
            [np.bincount(cluster, weights=mesh.vertices[:, k], minlength=n) for k in range(3)], 1
        )
        / counts[:, None]
    )
    faces = cluster[mesh.faces]
    keep = (
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    )
    faces = faces[keep]
    # One copy of each triangle (either winding): the first in file order.
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces = faces[np.sort(first)]
    used, remap = np.unique(faces, return_inverse=True)
    return Mesh(vertices[used], remap.reshape(-1, 3).astype(np.int32))


def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = np.asarray(quat, dtype=np.float64) / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
