"""A user's surface mesh made ready for tetrahedralization: read, repaired, checked, oriented and scaled.

:func:`import_surface` reads ``.obj``, ``.stl``, ``.ply`` (trimesh) or a Gmsh ``.msh`` tet mesh (its boundary),
repairs what can be repaired and refuses the rest with an :class:`~colgnn_core.errors.InputError` naming the
problem. Repairs, each listed in :attr:`SurfaceImport.repairs`:

* duplicate vertices merged (seams of OBJ exports; within 1e-8 of the bounding-box diagonal), unused vertices,
  zero-area and duplicate triangles removed;
* inconsistent winding made consistent, and the whole surface turned outward (positive enclosed volume);
* holes closed: every boundary loop is filled with a fan around its centroid;
* small loose pieces (< 1% of the volume, e.g. a stray triangle shell) dropped.

Refused: an unreadable or empty file; edges shared by more than two triangles (non-manifold); a surface still
open after the hole filling; several pieces of similar size (which one is the object?); a flat surface that
encloses no volume.

The surface is then turned so that ``up`` becomes +z and scaled so that its longest bounding-box side is ``size``
metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.tetmesh import check_closed_surface, load_msh, surface_volume

SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".msh")
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
LOOSE_PIECE_FRACTION = 0.01  # pieces below this fraction of the volume are dropped; larger ones are refused


@dataclass
class SurfaceImport:
    """A closed, outward, manifold triangle surface in metres, z up, and what was done to get it."""

    vertices: np.ndarray  # [N,3] m
    faces: np.ndarray     # [F,3] int64, outward
    source: str
    up: str
    scale: float          # metres per file unit
    repairs: list[str] = field(default_factory=list)

    @property
    def extents(self) -> np.ndarray:
        return self.vertices.max(axis=0) - self.vertices.min(axis=0)

    def area(self) -> float:
        x = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1).sum())

    def mean_edge_length(self) -> float:
        x = self.vertices[self.faces]
        return float(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2).mean())


def default_up(path: str | Path) -> str:
    """The usual up axis of a file type: z for STL (CAD), y for OBJ/PLY/MSH (modelling tools and scan archives)."""
    return "z" if Path(path).suffix.lower() == ".stl" else "y"


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    suffix = path.suffix.lower()
    if suffix not in SURFACE_SUFFIXES:
        raise InputError(f"{path}: unsupported mesh type {suffix!r}; use one of {', '.join(SURFACE_SUFFIXES)}")
    if not path.is_file():
        raise InputError(f"no such mesh file: {path}")
    try:
        if suffix == ".msh":
            mesh = load_msh(path)
            return np.asarray(mesh.vertices), np.asarray(mesh.faces)
        import trimesh  # lazy: trimesh is slow to import and only mesh import needs it

        surf = trimesh.load(str(path), process=False, force="mesh")
        v, f = np.asarray(surf.vertices, dtype=np.float64), np.asarray(surf.faces, dtype=np.int64)
    except InputError:
        raise
    except Exception as exc:  # trimesh/meshio raise many kinds of errors for a broken file
        raise InputError(f"{path}: cannot read the mesh ({type(exc).__name__}: {exc})") from None
    if v.ndim != 2 or len(v) < 4 or f.ndim != 2 or len(f) < 4 or f.shape[1] != 3:
        raise InputError(f"{path}: not a triangle surface ({len(v)} vertices, {len(f)} triangles)")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{path}: vertex coordinates contain NaN or inf")
    return v, f


def _clean(v: np.ndarray, f: np.ndarray, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Merge duplicate vertices, drop degenerate/duplicate triangles and unused vertices."""
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    if diag <= 0:
        raise InputError("degenerate mesh: all vertices coincide")
    key = np.round(v / (1e-8 * diag)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if len(first) < len(v):
        repairs.append(f"merged {len(v) - len(first)} duplicate vertices")
    v, f = v[first], inverse[f]
    x = v[f]
    area2 = np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2]) | (area2 <= 1e-14 * diag * diag)
    if bad.any():
        repairs.append(f"removed {int(bad.sum())} zero-area triangles")
        f = f[~bad]
    _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    if len(keep) < len(f):
        repairs.append(f"removed {len(f) - len(keep)} duplicate triangles")
        f = f[np.sort(keep)]
    if len(f) < 4:
        raise InputError(f"degenerate mesh: only {len(f)} triangles with a non-zero area")
    used, f = np.unique(f, return_inverse=True)
    if len(used) < len(v):
        repairs.append(f"removed {len(v) - len(used)} unused vertices")
    return v[used], f.reshape(-1, 3)


def _edge_counts(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def _fill_holes(v: np.ndarray, f: np.ndarray, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Fill every boundary loop with a fan around its centroid (orientation fixed afterwards)."""
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    edges, counts = _edge_counts(f)
    if np.any(counts > 2):
        raise InputError(f"non-manifold surface: {int(np.sum(counts > 2))} edges are shared by more than two "
                         "triangles; fix it in a mesh editor (e.g. split the touching parts)")
    boundary = edges[counts == 1]
    if not len(boundary):
        return v, f
    # Each boundary edge in the direction its triangle uses it; a loop runs against it.
    bset = {tuple(e) for e in boundary}
    half = [(int(a), int(b)) for a, b in directed if (min(a, b), max(a, b)) in bset]
    nxt: dict[int, int] = {}
    for a, b in half:
        if b in nxt:  # two boundary edges leave one vertex: the hole's rim touches itself
            raise InputError("the surface is not closed and a hole's rim touches itself (a non-manifold vertex); "
                             "close the hole in a mesh editor")
        nxt[b] = a
    new_v, new_f, seen, loops = [v], [f], set(), 0
    n = len(v)
    for start in list(nxt):
        if start in seen:
            continue
        loop, cur = [], start
        while cur not in seen:
            seen.add(cur)
            loop.append(cur)
            cur = nxt.get(cur, -1)
            if cur < 0:
                raise InputError("the surface is not closed and a hole's rim is not a closed loop")
        if cur != start:
            raise InputError("the surface is not closed and a hole's rim is not a simple loop")
        c = v[loop].mean(axis=0)
        new_v.append(c[None])
        new_f.append(np.array([[loop[i], loop[(i + 1) % len(loop)], n] for i in range(len(loop))], dtype=np.int64))
        n += 1
        loops += 1
    repairs.append(f"closed {loops} hole(s) ({len(boundary)} boundary edges)")
    return np.concatenate(new_v), np.concatenate(new_f)


def _components(f: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected-component label [F] of each triangle (through shared vertices)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(np.arange(len(f)), 3)
    adj = coo_matrix((np.ones(len(rows)), (rows, f.reshape(-1))), shape=(len(f), n_vertices)).tocsr()
    _, vertex_label = connected_components(adj.T @ adj, directed=False)
    return vertex_label[f[:, 0]]


def _orient(v: np.ndarray, f: np.ndarray, repairs: list[str]) -> np.ndarray:
    """Consistent winding (trimesh), then outward (positive volume)."""
    import trimesh  # lazy: see _read

    mesh = trimesh.Trimesh(v, f, process=False)
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        if not mesh.is_winding_consistent:
            raise InputError("the surface's triangles cannot be wound consistently (a one-sided surface such as a "
                             "Moebius strip)")
        repairs.append("made the triangle winding consistent")
    f = np.asarray(mesh.faces, dtype=np.int64)
    if surface_volume(v, f) < 0:
        f = f[:, [0, 2, 1]]
        repairs.append("turned the surface outward")
    return f


def _largest_piece(v: np.ndarray, f: np.ndarray, repairs: list[str]) -> np.ndarray:
    label = _components(f, len(v))
    pieces = np.unique(label)
    if len(pieces) == 1:
        return f
    vols = np.array([abs(surface_volume(v, f[label == p])) for p in pieces])
    order = np.argsort(vols)[::-1]
    total = vols.sum()
    small = vols[order[1:]] < LOOSE_PIECE_FRACTION * total
    if not small.all():
        raise InputError(f"the mesh has {len(pieces)} separate pieces of similar size (volumes "
                         f"{', '.join(f'{100 * x / total:.0f}%' for x in vols[order][:5])}); give one object")
    repairs.append(f"dropped {len(pieces) - 1} loose piece(s) ({100 * vols[order[1:]].sum() / total:.2g}% of the "
                   "volume)")
    return f[label == pieces[order[0]]]


def _up_rotation(up: str) -> np.ndarray:
    """Proper rotation taking the axis ``up`` to +z."""
    if up not in UP_AXES:
        raise InputError(f"unknown up axis {up!r}; valid: {', '.join(UP_AXES)}")
    rot = {"z": np.eye(3), "-z": np.diag([1.0, -1.0, -1.0]),
           "y": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),     # +90 deg about x: y -> z
           "-y": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
           "x": np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]]),     # -90 deg about y: x -> z
           "-x": np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]])}[up]
    return rot


def import_surface(path: str | Path, size: float, up: str | None = None) -> SurfaceImport:
    """Read, repair, check, orient (``up`` -> +z; default :func:`default_up`) and scale (longest side ``size`` m)
    a surface. InputError naming the problem when it cannot be made a closed manifold surface."""
    path = Path(path)
    if not (np.isfinite(size) and size > 0):
        raise InputError(f"--size must be a positive length in metres, got {size}")
    up = up or default_up(path)
    rot = _up_rotation(up)
    v, f = _read(path)
    repairs: list[str] = []
    try:
        v, f = _clean(v, f, repairs)
        v, f = _fill_holes(v, f, repairs)
        v, f = _clean(v, f, repairs)  # a fan over a degenerate (flat, collinear) hole adds zero-area triangles
        f = _orient(v, f, repairs)
        f = _largest_piece(v, f, repairs)
        used, f = np.unique(f, return_inverse=True)
        v, f = v[used], f.reshape(-1, 3)
        extent = v.max(0) - v.min(0)
        vol = surface_volume(v, f)
        if vol <= 1e-9 * float(extent.max()) ** 3:
            raise InputError(f"degenerate mesh: it encloses no volume (flat or an open sheet; bbox "
                             f"{' x '.join(f'{e:.3g}' for e in extent)} file units)")
        check_closed_surface(v, f, "the repaired surface")
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path.name}: the surface is still not a closed manifold after repair: {exc}") from None
    scale = float(size) / float(extent.max())
    v = (v @ rot.T) * scale
    return SurfaceImport(vertices=v, faces=f, source=path.name, up=up, scale=scale, repairs=repairs)


def obj_text(vertices: np.ndarray, faces: np.ndarray) -> str:
    """A plain OBJ (``v`` and 1-based ``f`` lines) of a triangle surface."""
    return ("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in vertices)
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
