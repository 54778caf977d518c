"""Triangle meshes as plain arrays: binary STL and OBJ reading, binary STL writing, rigid
transforms and vertex-clustering decimation (our own, deterministic: the same input gives
byte-identical output). Used by :mod:`beavr_sim.robots.mesh_build` (the asset generator) and
:mod:`beavr_sim.robots.visuals` (loading the generated meshes into a spec)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Eigenvalues of a cluster's quadric below this fraction of its largest leave that direction
#: to the cluster's mean (the planes do not pin it).
QUADRIC_CUTOFF = 0.05

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

    def subset(self, keep: np.ndarray) -> Mesh:
        """The faces where ``keep`` is true, with only the vertices they use."""
        used, remap = np.unique(self.faces[keep], return_inverse=True)
        return Mesh(self.vertices[used], remap.reshape(-1, 3).astype(np.int32))

    def cut(self, level: np.ndarray) -> Mesh:
        """The same surface with every face that ``level`` (a value per vertex) changes sign
        across split in three along its zero line, so that each face lies on one side. The new
        vertices are shared by the faces on both sides of an edge (computed once per edge)."""
        level = np.asarray(level, dtype=np.float64)
        side = level[self.faces] > 0
        split = side.any(axis=1) & ~side.all(axis=1)
        if not split.any():
            return self
        faces = self.faces[split]
        # Rotate each split face (keeping its winding) so that its lone vertex comes first.
        lone = np.argmax(_lone(side[split]), axis=1)
        faces = np.take_along_axis(faces, (lone[:, None] + np.arange(3)) % 3, axis=1)
        a, b, c = faces.T
        edges = np.sort(np.concatenate([np.stack([a, b], 1), np.stack([a, c], 1)]), axis=1)
        unique_edges, which = np.unique(edges, axis=0, return_inverse=True)
        i, j = unique_edges.T
        t = level[i] / (level[i] - level[j])
        points = self.vertices[i] + t[:, None] * (self.vertices[j] - self.vertices[i])
        ab, ac = np.split(len(self.vertices) + which.reshape(-1), 2)
        new = np.concatenate(
            [np.stack([a, ab, ac], 1), np.stack([ab, b, c], 1), np.stack([ab, c, ac], 1)]
        )
        return Mesh(
            np.concatenate([self.vertices, points]),
            np.concatenate([self.faces[~split], new]).astype(np.int32),
        )

    @staticmethod
    def merge(meshes: list[Mesh]) -> Mesh:
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
        )


def _lone(side: np.ndarray) -> np.ndarray:
    """One-hot (m, 3): the corner on its own side of a face whose corners are on both."""
    odd = side.sum(axis=1) == 1
    return np.where(odd[:, None], side, ~side)


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


def face_quadrics(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per face its plane's area-weighted quadric: ``A`` (m, 3, 3) = area n n^T, ``b`` (m, 3) =
    area (n . p) n, ``c`` (m,) = area (n . p)^2, so that the squared distance of x to the plane,
    times the area, is x^T A x - 2 b . x + c."""
    tri = mesh.vertices[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    n = np.divide(
        cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0
    )
    area = 0.5 * double_area
    offset = np.einsum("ij,ij->i", n, tri[:, 0])
    A = area[:, None, None] * n[:, :, None] * n[:, None, :]
    return A, (area * offset)[:, None] * n, area * offset**2


def decimate(mesh: Mesh, cell: float) -> Mesh:
    """:func:`decimate_labelled` without labels."""
    return decimate_labelled(mesh, np.zeros(len(mesh.faces), dtype=np.int32), cell)[0]


def decimate_labelled(mesh: Mesh, labels: np.ndarray, cell: float) -> tuple[Mesh, np.ndarray]:
    """Vertex clustering: vertices in the same cube of side ``cell`` (metres) merge into one;
    triangles that collapse, and repeated ones, are dropped. Deterministic.

    Each cluster's vertex goes where the summed squared distance to the planes of its
    original faces (area-weighted) is least, within the cluster's cube: flat faces stay flat
    and sharp edges and corners stay sharp, where the cluster's mean would round them off
    (quadric placement, after P. Lindstrom, "Out-of-core simplification of large polygonal
    models", SIGGRAPH 2000). Directions in which the planes do not pin the point (a flat or
    a cylindrical patch) keep the mean's coordinate.

    ``labels`` (one int per face, e.g. a colour) go with the faces: vertices cluster with
    vertices of their own label only, and a vertex on a border between labels stays as it is
    (its own cluster), so the borders keep their shape and the parts of different labels
    share their border vertices (:meth:`Mesh.subset` splits them without cracks); each kept
    triangle has the label of the first face that became it."""
    if not cell > 0:
        raise ValueError(f"cell must be positive, got {cell!r}")
    labels = np.asarray(labels)
    nv = len(mesh.vertices)
    # A vertex's label, and whether it is on a border between labels (faces of both).
    corner_labels = np.repeat(labels, 3)
    low = np.full(nv, np.iinfo(np.int64).max)
    high = np.full(nv, np.iinfo(np.int64).min)
    np.minimum.at(low, mesh.faces.reshape(-1), corner_labels)
    np.maximum.at(high, mesh.faces.reshape(-1), corner_labels)
    border = low < high  # (a vertex of no face has low > high)
    low = np.where(low > high, 0, low)
    cells = np.floor(mesh.vertices / cell).astype(np.int64)
    keys = np.concatenate(
        [cells, low[:, None], np.where(border, np.arange(nv), -1)[:, None]], axis=1
    )
    unique_keys, cluster = np.unique(keys, axis=0, return_inverse=True)
    unique_keys = unique_keys[:, :3]
    cluster = cluster.reshape(-1)
    n = len(unique_keys)
    counts = np.bincount(cluster, minlength=n).astype(np.float64)
    mean = (
        np.stack(
            [np.bincount(cluster, weights=mesh.vertices[:, k], minlength=n) for k in range(3)], 1
        )
        / counts[:, None]
    )
    # Sum each face's quadric into the clusters of its corners.
    A_f, b_f, _ = face_quadrics(mesh)
    corner = cluster[mesh.faces].reshape(-1)
    A = np.zeros((n, 9))
    b = np.zeros((n, 3))
    for k in range(3):
        b[:, k] = np.bincount(corner, weights=np.repeat(b_f[:, k], 3), minlength=n)
    flat = A_f.reshape(-1, 9)
    for k in range(9):
        A[:, k] = np.bincount(corner, weights=np.repeat(flat[:, k], 3), minlength=n)
    A = A.reshape(n, 3, 3)
    # Minimise x^T A x - 2 b.x about the mean, on the eigen-directions the planes pin.
    w, V = np.linalg.eigh(A)
    pinned = w > QUADRIC_CUTOFF * w[:, -1:]
    residual = b - np.einsum("nij,nj->ni", A, mean)
    coef = np.einsum("nji,nj->ni", V, residual)
    step = np.divide(coef, w, out=np.zeros_like(coef), where=pinned & (w > 0))
    vertices = mean + np.einsum("nij,nj->ni", V, step)
    vertices = np.clip(vertices, unique_keys * cell, (unique_keys + 1) * cell)
    vertices[cluster[border]] = mesh.vertices[border]  # borders stay where they are
    faces = cluster[mesh.faces]
    keep = (
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    )
    faces, labels = faces[keep], labels[keep]
    # One copy of each triangle (either winding): the first in file order.
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    first = np.sort(first)
    faces, labels = faces[first], labels[first]
    used, remap = np.unique(faces, return_inverse=True)
    return Mesh(vertices[used], remap.reshape(-1, 3).astype(np.int32)), labels


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
