"""Tetrahedral meshes of the deformable objects.

A :class:`TetMesh` holds rest positions, positively oriented tets and the
outward boundary triangles derived from them. Orientation convention (the same
as IPC's): a tet ``(a, b, c, d)`` is positive when
``det([x_b - x_a, x_c - x_a, x_d - x_a]) > 0``; a boundary triangle is
counter-clockwise seen from outside, so its normal ``(x1-x0) x (x2-x0)``
points out of the object.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Faces of a positive tet (a,b,c,d), each ordered so that its normal points
# away from the opposite vertex: opposite a, b, c, d respectively.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


def tet_signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes [K] (m^3) of tets [K,4] over vertices [N,3]."""
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(tets)]
    e = x[:, 1:] - x[:, :1]
    return np.einsum("ij,ij->i", e[:, 0], np.cross(e[:, 1], e[:, 2])) / 6.0


def orient_tets(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Return tets [K,4] int64 with each negative tet's last two vertices swapped.

    Use only on meshes whose inversions are an ordering artefact (e.g. files
    written with the opposite convention); degenerate tets stay degenerate and
    are caught by :meth:`TetMesh.validate`.
    """
    tets = np.array(tets, dtype=np.int64, copy=True)
    neg = tet_signed_volumes(vertices, tets) < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles [F,3] int64 of positively oriented tets [K,4], outward.

    A triangle is on the boundary when exactly one tet uses it. Faces are kept in
    the orientation of their tet, which is outward for positive tets. The order
    is deterministic (sorted by the triangle's sorted vertex ids).
    """
    tets = np.asarray(tets, dtype=np.int64)
    all_faces = tets[:, _TET_FACES].reshape(-1, 3)
    key = np.sort(all_faces, axis=1)
    _, first, inverse, counts = np.unique(key, axis=0, return_index=True, return_inverse=True, return_counts=True)
    once = counts[inverse.reshape(-1)] == 1
    order = np.lexsort(key[once].T[::-1])
    return all_faces[once][order]


def surface_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E,2] int64 (i<j, sorted rows) of triangles [F,3]."""
    faces = np.asarray(faces, dtype=np.int64)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals [N,3] of the triangles ``faces`` [F,3] (outward when the faces are);
    vertices on no face get zeros."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length: twice the area
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], face_n)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def check_closed_surface(vertices: np.ndarray, faces: np.ndarray, what: str = "surface") -> None:
    """Raise ValueError unless faces [F,3] form a closed, consistently outward, manifold surface.

    Checks: no degenerate (zero-area or repeated-index) triangle; every directed
    edge used exactly once and its reverse exactly once (watertight, 2-manifold
    edges, consistent orientation); positive enclosed volume (outward).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{what}: faces must be a non-empty [F,3] array, got shape {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{what}: face index out of range [0, {len(v)})")
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])):
        raise ValueError(f"{what}: triangle with a repeated vertex")
    x = v[f]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    scale = float(np.linalg.norm(v.max(0) - v.min(0)))
    if np.any(area2 <= 1e-14 * scale * scale):
        raise ValueError(f"{what}: {int(np.sum(area2 <= 1e-14 * scale * scale))} degenerate (zero-area) triangles")
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    d_unique, d_counts = np.unique(directed, axis=0, return_counts=True)
    if np.any(d_counts > 1):
        raise ValueError(f"{what}: {int(np.sum(d_counts > 1))} directed edges used twice (inconsistent orientation or "
                         "non-manifold)")
    # Watertight + consistent: every directed edge has its reverse.
    n_v = len(v)
    codes = d_unique[:, 0] * n_v + d_unique[:, 1]
    reverse = d_unique[:, 1] * n_v + d_unique[:, 0]
    if not np.all(np.isin(reverse, codes)):
        raise ValueError(f"{what}: open or inconsistently oriented ({int(np.sum(~np.isin(reverse, codes)))} unmatched "
                         "half-edges)")
    volume = float(np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0)
    if volume <= 0:
        raise ValueError(f"{what}: enclosed volume {volume:.3e} <= 0 (faces point inward)")


def surface_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume (m^3) enclosed by a closed outward triangle surface."""
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class TetMesh:
    """A tetrahedral mesh at rest.

    Attributes:
        vertices: [N,3] float64 rest positions (m).
        tets: [K,4] int64, positive volume.
        faces: [F,3] int64 boundary triangles, outward, watertight.
        surface_vertices: [S] int64 sorted unique vertex ids used by ``faces``.
        edges: [E,2] int64 unique surface edges (i<j).

    Arrays are read-only: scenes are cached and shared, so copy before editing.
    Build with :meth:`from_tets` (derives faces, surface vertices and edges).
    """

    vertices: np.ndarray
    tets: np.ndarray
    faces: np.ndarray
    surface_vertices: np.ndarray = field(default=None)  # type: ignore[assignment]
    edges: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        object.__setattr__(self, "vertices", _readonly(np.asarray(self.vertices, dtype=np.float64)))
        object.__setattr__(self, "tets", _readonly(np.asarray(self.tets, dtype=np.int64)))
        object.__setattr__(self, "faces", _readonly(np.asarray(self.faces, dtype=np.int64)))
        if self.surface_vertices is None:
            object.__setattr__(self, "surface_vertices", np.unique(self.faces))
        object.__setattr__(self, "surface_vertices", _readonly(np.asarray(self.surface_vertices, dtype=np.int64)))
        if self.edges is None:
            object.__setattr__(self, "edges", surface_edges(self.faces))
        object.__setattr__(self, "edges", _readonly(np.asarray(self.edges, dtype=np.int64)))

    @classmethod
    def from_tets(cls, vertices: np.ndarray, tets: np.ndarray, orient: bool = False) -> "TetMesh":
        """Mesh from vertices [N,3] and tets [K,4]; faces/edges derived. ``orient`` fixes flipped tets."""
        vertices = np.asarray(vertices, dtype=np.float64)
        tets = orient_tets(vertices, tets) if orient else np.asarray(tets, dtype=np.int64)
        return cls(vertices=vertices, tets=tets, faces=boundary_faces(tets))

    @property
    def num_vertices(self) -> int:
        return int(len(self.vertices))

    def volumes(self) -> np.ndarray:
        """Signed rest volumes [K] (m^3)."""
        return tet_signed_volumes(self.vertices, self.tets)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """(min [3], max [3]) of the rest vertices (m)."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def transformed(self, rotation: np.ndarray | None = None, scale: float = 1.0,
                    translation: np.ndarray | None = None) -> "TetMesh":
        """A copy with x' = scale * R x + t (rotation must be proper, det = +1, to keep orientation)."""
        x = np.asarray(self.vertices, dtype=np.float64)
        if rotation is not None:
            if np.linalg.det(rotation) <= 0:
                raise ValueError("rotation must have det +1 (a reflection would invert every tet)")
            x = x @ np.asarray(rotation).T
        x = x * float(scale)
        if translation is not None:
            x = x + np.asarray(translation, dtype=np.float64)
        return TetMesh(vertices=x, tets=self.tets, faces=self.faces, surface_vertices=self.surface_vertices,
                       edges=self.edges)

    def validate(self, min_volume_ratio: float = 1e-6) -> None:
        """Raise ValueError naming the problem, or return None if the mesh is valid.

        Checks: shapes and index ranges; every vertex used by a tet; every tet
        positive with volume > ``min_volume_ratio`` * mean volume (no degenerate
        slivers); faces equal the boundary of the tets; the surface is closed,
        manifold, consistently outward; surface volume equals the tet volume.
        """
        v, t, f = self.vertices, self.tets, self.faces
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
            raise ValueError(f"vertices must be [N>=4,3], got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices contain NaN or inf")
        if t.ndim != 2 or t.shape[1] != 4 or len(t) == 0:
            raise ValueError(f"tets must be [K>0,4], got {t.shape}")
        if t.min() < 0 or t.max() >= len(v):
            raise ValueError(f"tet index out of range [0, {len(v)})")
        unused = len(v) - len(np.unique(t))
        if unused:
            raise ValueError(f"{unused} vertices are not used by any tet (they would have no mass)")
        vol = self.volumes()
        if np.any(vol <= 0):
            raise ValueError(f"{int(np.sum(vol <= 0))} inverted or flat tets (first at index "
                             f"{int(np.argmax(vol <= 0))})")
        tiny = vol < min_volume_ratio * vol.mean()
        if np.any(tiny):
            raise ValueError(f"{int(tiny.sum())} degenerate tets (volume < {min_volume_ratio:g} x mean), first at "
                             f"index {int(np.argmax(tiny))}")
        expected = boundary_faces(t)
        if len(expected) != len(f) or not np.array_equal(
            np.unique(np.sort(expected, axis=1), axis=0), np.unique(np.sort(f, axis=1), axis=0)
        ):
            raise ValueError("faces are not the boundary of the tets")
        check_closed_surface(v, f, "object surface")
        # Each boundary face must keep its tet's (outward) orientation.
        exp_sorted = np.sort(expected, axis=1)
        order_e = np.lexsort(exp_sorted.T[::-1])
        f_sorted = np.sort(f, axis=1)
        order_f = np.lexsort(f_sorted.T[::-1])
        ne = np.cross(v[expected[order_e, 1]] - v[expected[order_e, 0]],
                      v[expected[order_e, 2]] - v[expected[order_e, 0]])
        nf = np.cross(v[f[order_f, 1]] - v[f[order_f, 0]], v[f[order_f, 2]] - v[f[order_f, 0]])
        if np.any(np.einsum("ij,ij->i", ne, nf) <= 0):
            raise ValueError("some faces point inward (orientation differs from their tet)")
        sv = surface_volume(v, f)
        if not np.isclose(sv, vol.sum(), rtol=1e-8):
            raise ValueError(f"surface volume {sv:.6e} != tet volume {vol.sum():.6e} (internal cavity or overlap)")
        if not np.array_equal(self.surface_vertices, np.unique(f)):
            raise ValueError("surface_vertices does not match the faces")
        if not np.array_equal(self.edges, surface_edges(f)):
            raise ValueError("edges do not match the faces")

    def fingerprint(self) -> str:
        """sha256 hex over rest vertices (rounded to 1e-9 m), tets and faces."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(np.round(self.vertices, 9) + 0.0).tobytes())
        h.update(np.ascontiguousarray(self.tets, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype=np.int64).tobytes())
        return h.hexdigest()

    def quality(self) -> dict[str, float]:
        """Simple quality figures: min/mean volume ratio and worst normalised radius ratio (1 = regular)."""
        x = self.vertices[self.tets]
        vol = self.volumes()
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        lengths = np.stack([np.linalg.norm(x[:, i] - x[:, j], axis=1) for i, j in pairs], axis=1)
        # Volume / (rms edge)^3, normalised so a regular tet gives 1.
        rms = np.sqrt((lengths**2).mean(axis=1))
        q = vol / rms**3 * (6.0 * np.sqrt(2.0))
        return {"min_quality": float(q.min()), "mean_quality": float(q.mean()), "min_volume": float(vol.min())}

    def save_npz(self, path: str | Path) -> None:
        """Write vertices (float64) and tets (int32 to keep assets small); faces are re-derived on load."""
        np.savez_compressed(path, vertices=self.vertices, tets=self.tets.astype(np.int32))


def load_npz(path: str | Path) -> TetMesh:
    """Load a TetMesh written by :meth:`TetMesh.save_npz`."""
    with np.load(path) as d:
        return TetMesh.from_tets(d["vertices"], d["tets"])


def load_msh(path: str | Path) -> TetMesh:
    """Load a Gmsh ``.msh`` tet mesh (via meshio), orienting tets positively.

    Drops vertices no tet uses (IPC's files may carry stray points) and reindexes.
    """
    import meshio  # local import: only scenes built from .msh files need it

    m = meshio.read(str(path))
    blocks = [c.data for c in m.cells if c.type == "tetra"]
    if not blocks:
        raise ValueError(f"{path}: no tetra cells")
    tets = np.concatenate(blocks).astype(np.int64)
    used, tets = np.unique(tets, return_inverse=True)
    tets = tets.reshape(-1, 4)
    return TetMesh.from_tets(np.asarray(m.points, dtype=np.float64)[used], tets, orient=True)
