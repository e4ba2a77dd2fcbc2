"""Broad phase for one step t -> t+1: SDF culling, then swept bounding boxes.

Both the object surface and the tool mesh move linearly (vertex by vertex) over
the step. Candidate pairs are

* ``vf``: object vertex vs tool face,
* ``fv``: tool vertex vs object face,
* ``ee``: object edge vs tool edge.

SDF culling (optional; needs the tool's analytic SDF and both tool poses). Let
m be how far the tool *mesh* can stick out of the analytic shape (the largest
SDF of a tool mesh vertex, >= 0; valid because the tool is convex, which is
checked), D the largest tool vertex displacement over the step and s0, s1 the
SDF of an object primitive at the two ends. The tool at time t is within t*D of
the tool at t0 and within (1-t)*D of the tool at t1; the SDF is 1-Lipschitz. So
a primitive whose points move at most d cannot touch the tool during the step if

    s0 + s1 - d - D - 2m > 0.

For an edge or a triangle the SDF lower bound comes from its vertices: every
point of a segment of length L is within L of either end and within L/2 of the
nearer one; every point of a triangle with longest edge L is within L of each
vertex and within L/sqrt(3) of the nearest one. Any lower bound of the distance
works in place of the SDF, so far from the tool the (cheaper) distance to the
tool mesh's bounding sphere is used, and the SDF is evaluated only for vertices
where it can matter. A vertex with s0 + s1 - Lmax0 - Lmax1 - dmax > D + 2m
(Lmax: an upper bound of the longest surface edge; dmax: the largest vertex
motion) rules out every edge and face it belongs to, so only the edges and faces
around the remaining vertices get the exact test.

The remaining primitives are paired by overlapping swept boxes (box of the
primitive's vertices at t0 and t1). Tool primitives that cannot reach the box of
the remaining object primitives are dropped first. The box join sorts both sets
along the axis where the boxes are smallest relative to their spread and expands
index ranges from ``searchsorted``: vectorised, no Python loop over pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import quat_to_matrix

__all__ = ["Surface", "CandidatePairs", "ToolSDFBound", "mesh_edges", "box_pairs", "sdf_near_primitives",
           "step_candidates"]

_EMPTY_PAIRS = np.zeros((0, 2), dtype=np.int64)
_BRUTE_FORCE_PAIRS = 16384  # box_pairs compares all pairs directly below this many


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E,2] (i < j, sorted) of a triangle list [F,3]."""
    faces = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


@dataclass(frozen=True)
class Surface:
    """Triangle-surface topology used by the collision code (build once per mesh).

    faces [F,3] int64, edges [E,2] int64 (i<j), vertices [S] int64 sorted ids used by
    faces, face_edges [F,3] int64 index of each face's edges in ``edges``,
    n_vertices: length of the position arrays this surface indexes.
    """

    faces: np.ndarray
    edges: np.ndarray
    vertices: np.ndarray
    face_edges: np.ndarray
    n_vertices: int

    @property
    def vertex_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR (offsets [n+1], edge ids) of the edges incident to each vertex (cached)."""
        return self._csr("_vertex_edges", self.edges)

    @property
    def vertex_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR (offsets [n+1], face ids) of the faces incident to each vertex (cached)."""
        return self._csr("_vertex_faces", self.faces)

    def _csr(self, name: str, prims: np.ndarray):
        c = self.__dict__.get(name)
        if c is None:
            owner = np.repeat(np.arange(len(prims)), prims.shape[1])
            v = prims.reshape(-1)
            order = np.argsort(v, kind="stable")
            offsets = np.zeros(self.n_vertices + 1, dtype=np.int64)
            np.cumsum(np.bincount(v, minlength=self.n_vertices), out=offsets[1:])
            c = (offsets, owner[order])
            object.__setattr__(self, name, c)
        return c

    def incident(self, csr: tuple[np.ndarray, np.ndarray], vertices: np.ndarray) -> np.ndarray:
        """Sorted unique ids of the primitives incident to ``vertices`` (vectorised CSR gather)."""
        offsets, ids = csr
        starts = offsets[vertices]
        counts = offsets[vertices + 1] - starts
        _, idx = _ranges(starts, counts)
        return np.unique(ids[idx])

    @property
    def edge_cols(self) -> tuple[np.ndarray, np.ndarray]:
        """Contiguous edge end-point columns (cached): gathers on them are faster than on [E,2] slices."""
        return self._cols("_edge_cols", self.edges)

    def _cols(self, name: str, a: np.ndarray):
        c = self.__dict__.get(name)
        if c is None:
            c = tuple(np.ascontiguousarray(a[:, i]) for i in range(a.shape[1]))
            object.__setattr__(self, name, c)
        return c

    @classmethod
    def from_faces(cls, faces, n_vertices: int | None = None, name: str = "mesh") -> "Surface":
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise InputError(f"{name} faces must be a non-empty [F,3] array, got shape {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise InputError(f"{name} faces must be integers, got {f.dtype}")
        f = f.astype(np.int64)
        if f.min() < 0 or (n_vertices is not None and f.max() >= n_vertices):
            raise InputError(f"{name} faces index out of range [0,{n_vertices})")
        n = int(n_vertices) if n_vertices is not None else int(f.max()) + 1
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        e.sort(axis=1)
        edges, inverse = np.unique(e, axis=0, return_inverse=True)
        face_edges = inverse.reshape(-1)
        face_edges = np.stack([face_edges[: len(f)], face_edges[len(f): 2 * len(f)], face_edges[2 * len(f):]], axis=1)
        return cls(faces=f, edges=edges, vertices=np.unique(f), face_edges=face_edges, n_vertices=n)


@dataclass
class CandidatePairs:
    """Pairs of primitives that may touch during the step, each [K,2] int64.

    vf: (object vertex id, tool face id); fv: (tool vertex id, object face id);
    ee: (object edge id, tool edge id). Edge ids index ``Surface.edges``.
    """

    vf: np.ndarray = field(default_factory=lambda: _EMPTY_PAIRS.copy())
    fv: np.ndarray = field(default_factory=lambda: _EMPTY_PAIRS.copy())
    ee: np.ndarray = field(default_factory=lambda: _EMPTY_PAIRS.copy())

    def total(self) -> int:
        return len(self.vf) + len(self.fv) + len(self.ee)

    def counts(self) -> dict[str, int]:
        return {"vf": len(self.vf), "fv": len(self.fv), "ee": len(self.ee)}


def _ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(owner, index) for the concatenation of ranges [starts[i], starts[i]+counts[i])."""
    owner = np.repeat(np.arange(len(counts)), counts)
    if len(owner) == 0:
        return owner, owner
    offsets = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, np.repeat(starts, counts) + offsets


def box_pairs(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray, soa: bool = False) -> np.ndarray:
    """All (i, j) with box a_i and box b_j overlapping (closed boxes). Returns [K,2] int64.

    Boxes are [K,3] (or [3,K] with ``soa=True``). Two intervals overlap iff lo_b lies in
    [lo_a, hi_a] or lo_a lies in (lo_b, hi_b]; both are contiguous ranges of the sorted
    lower corners, found with searchsorted along the axis giving the fewest 1-D overlaps.
    """
    if not soa:
        lo_a, hi_a, lo_b, hi_b = (np.ascontiguousarray(np.asarray(x, dtype=np.float64).T) for x in (lo_a, hi_a, lo_b, hi_b))
    na, nb = lo_a.shape[1], lo_b.shape[1]
    if na == 0 or nb == 0:
        return _EMPTY_PAIRS.copy()
    if na * nb <= _BRUTE_FORCE_PAIRS:
        # Small sets: one broadcast comparison beats sorting (numpy cost is per call).
        ok = (lo_a[0][:, None] <= hi_b[0][None, :]) & (lo_b[0][None, :] <= hi_a[0][:, None])
        for k in (1, 2):
            ok &= (lo_a[k][:, None] <= hi_b[k][None, :]) & (lo_b[k][None, :] <= hi_a[k][:, None])
        ia, ib = np.nonzero(ok)
        return np.stack([ia, ib], axis=1).astype(np.int64, copy=False)
    # Sweep along the axis where the boxes are smallest relative to the spread of their corners:
    # it gives the fewest 1-D overlaps (a cheap proxy for trying all three axes).
    size = (hi_a - lo_a).sum(axis=1) / na + (hi_b - lo_b).sum(axis=1) / nb
    spread = np.maximum(hi_a.max(axis=1), hi_b.max(axis=1)) - np.minimum(lo_a.min(axis=1), lo_b.min(axis=1))
    k = int(np.argmax(spread / np.maximum(size, 1e-300)))
    ob = np.argsort(lo_b[k], kind="stable")
    oa = np.argsort(lo_a[k], kind="stable")
    sb, sa = lo_b[k][ob], lo_a[k][oa]
    i0 = np.searchsorted(sb, lo_a[k], "left")
    c1 = np.searchsorted(sb, hi_a[k], "right") - i0
    j0 = np.searchsorted(sa, lo_b[k], "right")
    c2 = np.searchsorted(sa, hi_b[k], "right") - j0
    np.maximum(c1, 0, out=c1)
    np.maximum(c2, 0, out=c2)
    best = (int(c1.sum() + c2.sum()), oa, ob, i0, c1, j0, c2)
    n, oa, ob, i0, c1, j0, c2 = best
    if n == 0:
        return _EMPTY_PAIRS.copy()
    a1, r1 = _ranges(i0, c1)
    b2, r2 = _ranges(j0, c2)
    ia = np.concatenate([a1, oa[r2]])
    ib = np.concatenate([ob[r1], b2])
    ok = (lo_a[0, ia] <= hi_b[0, ib]) & (lo_b[0, ib] <= hi_a[0, ia])
    for k in (1, 2):
        ok &= (lo_a[k, ia] <= hi_b[k, ib]) & (lo_b[k, ib] <= hi_a[k, ia])
    return np.stack([ia[ok], ib[ok]], axis=1)


class ToolSDFBound:
    """Pre-computed facts for SDF culling with one tool: tessellation margin and convexity.

    ``tool`` must provide ``vertices`` [M,3] (tool frame), ``faces`` [G,3],
    ``sdf_local(p)`` and ``sdf(points, pose)`` (see colgnn_core.geometry.tools.Tool).
    ``usable`` is False when the tool mesh is not convex; then SDF culling is skipped
    (the convex-hull argument for the margin would not hold).
    """

    def __init__(self, tool) -> None:
        V = np.asarray(tool.vertices, dtype=np.float64)
        F = np.asarray(tool.faces, dtype=np.int64)
        self.tool = tool
        scale = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
        # Slack for rounding in the SDF and the sums below: far above float64 error, far below mm.
        self.slack = 1e-9 * max(scale, 1.0) + 1e-7 * scale
        self.margin = max(0.0, float(np.max(tool.sdf_local(V)))) + self.slack
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        # Convex and outward: every vertex is on or behind every face plane.
        side = (V @ n.T) - np.einsum("gi,gi->g", V[F[:, 0]], n)[None, :]
        self.usable = bool(np.all(side <= 1e-9 * max(scale, 1e-12)))
        # Bounding sphere (tool frame) of the mesh: |x - c| - r is a cheap lower bound of the distance.
        self.center_local = 0.5 * (V.min(axis=0) + V.max(axis=0))
        self.radius = float(np.sqrt(((V - self.center_local) ** 2).sum(axis=1)).max())

    def widened(self, extra: float) -> "ToolSDFBound":
        """A copy whose margin is larger by ``extra`` m (tool positions slightly off the posed mesh)."""
        if extra <= 0:
            return self
        out = object.__new__(ToolSDFBound)
        out.__dict__.update(self.__dict__)
        out.margin = self.margin + extra
        return out

    def lower_bounds(self, P0T: np.ndarray, P1T: np.ndarray, pose0, pose1, needed: float
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Lower bounds [K] (m) of the distance to the tool mesh (+ ``margin``) at t0 and t1 for
        points [3,K]: the analytic SDF, or the bounding-sphere distance where that is enough.

        The SDF is evaluated only for points whose sphere bounds sum to at most ``needed``;
        any lower bound of the distance keeps the culling conservative (module docstring).
        """
        out = []
        for PT, pose in ((P0T, pose0), (P1T, pose1)):
            pose = np.asarray(pose, dtype=np.float64)
            c = quat_to_matrix(pose[3:]) @ self.center_local + pose[:3]
            d = PT - c[:, None]
            out.append(_norm_soa(d[0], d[1], d[2]) - self.radius)
        idx = np.flatnonzero((out[0] + out[1]) <= needed)
        if len(idx):
            for i, (PT, pose) in enumerate(((P0T, pose0), (P1T, pose1))):
                sdf = np.asarray(self.tool.sdf(PT[:, idx].T, pose), dtype=np.float64)
                out[i][idx] = np.maximum(out[i][idx], sdf)
        return out[0], out[1]


def _norm_soa(d0, d1, d2):
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


def _max_edge_length(XT: np.ndarray, surface: Surface, cache: dict | None) -> float:
    """Upper bound (m) on the longest surface edge at positions XT [3,N].

    With a cache: exact lengths at a reference state, plus twice the largest vertex
    displacement from it (an edge grows at most by the motion of its two ends). The
    reference is refreshed when the bound gets loose.
    """
    if cache is not None and "ref" in cache and cache["ref"].shape == XT.shape:
        d = XT - cache["ref"]
        move = float(np.sqrt((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).max()))
        if move <= 0.5 * cache["lmax"]:
            return cache["lmax"] + 2.0 * move
    ea, eb = surface.edge_cols
    lmax = float(_norm_soa(*(XT[k][ea] - XT[k][eb] for k in range(3))).max())
    if cache is not None:
        cache["ref"] = XT.copy()
        cache["lmax"] = lmax
    return lmax


def sdf_near_primitives(X0T, X1T, surface: Surface, tool_bound: "ToolSDFBound", pose0, pose1,
                        tool_displacement: float, cache: dict | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ids of object surface vertices, edges and faces that may touch the tool (see module docstring).

    X0T, X1T: [3,N] object positions at t0 and t1; pose0, pose1: tool poses [7];
    tool_displacement: largest tool-vertex motion over the step (m). ``cache`` (a dict kept
    by the caller across steps) speeds up the longest-edge bound.
    """
    n = surface.n_vertices
    S = surface.vertices
    dX = X1T[:, S] - X0T[:, S]
    disp_s = _norm_soa(dX[0], dX[1], dX[2])
    budget = tool_displacement + 2.0 * tool_bound.margin
    lmax0 = _max_edge_length(X0T, surface, cache)
    lmax1 = _max_edge_length(X1T, surface, cache)
    dmax = float(disp_s.max())
    # A vertex with s0 + s1 - Lmax0 - Lmax1 - Dmax > budget rules out itself and every edge and
    # face it is part of (their bounds below are at least that large).
    reach = budget + lmax0 + lmax1 + dmax
    sdf0, sdf1 = tool_bound.lower_bounds(X0T[:, S], X1T[:, S], pose0, pose1, reach)
    near_v = S[(sdf0 + sdf1 - disp_s) <= budget]
    hopeful = S[(sdf0 + sdf1) <= reach]
    if len(hopeful) == 0:
        return near_v, np.zeros(0, np.int64), np.zeros(0, np.int64)
    s0 = np.full(n, np.inf)
    s1 = np.full(n, np.inf)
    disp = np.zeros(n)
    s0[S], s1[S], disp[S] = sdf0, sdf1, disp_s
    Ei = surface.incident(surface.vertex_edges, hopeful)
    E = surface.edges[Ei]
    Fi = surface.incident(surface.vertex_faces, hopeful)
    F = surface.faces[Fi]
    out = []
    for prims, kind in ((E, "e"), (F, "f")):
        cols = [np.ascontiguousarray(prims[:, i]) for i in range(prims.shape[1])]
        P0 = [X0T[:, c] for c in cols]
        P1 = [X1T[:, c] for c in cols]
        k = len(cols)
        pairs = [(i, (i + 1) % k) for i in range(k)] if k == 3 else [(0, 1)]
        L0 = np.max([_norm_soa(*(P0[i] - P0[j])) for i, j in pairs], axis=0)
        L1 = np.max([_norm_soa(*(P1[i] - P1[j])) for i, j in pairs], axis=0)
        v0 = np.array([s0[c] for c in cols])
        v1 = np.array([s1[c] for c in cols])
        # Every point is within L of each vertex, and within L/2 (segment) or L/sqrt(3)
        # (triangle) of the nearest one.
        near_factor = 0.5 if k == 2 else 1.0 / np.sqrt(3.0)
        lb0 = np.maximum(v0.max(axis=0) - L0, v0.min(axis=0) - near_factor * L0)
        lb1 = np.maximum(v1.max(axis=0) - L1, v1.min(axis=0) - near_factor * L1)
        d = np.max([disp[c] for c in cols], axis=0)
        out.append(lb0 + lb1 - d <= budget)
    near_e = Ei[out[0]]
    near_f = Fi[out[1]]
    return near_v, near_e, near_f


def _check_positions(X, n: int, name: str) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] != n:
        raise InputError(f"{name} must be [{n},3], got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError(f"{name} contains NaN or inf")
    return X


def step_candidates(object_t0, object_t1, object_surface: Surface, tool_t0, tool_t1, tool_surface: Surface, *,
                tool_bound: ToolSDFBound | None = None, tool_pose_t0=None, tool_pose_t1=None,
                check: bool = True, cache: dict | None = None, transposed: tuple | None = None) -> CandidatePairs:
    """Candidate pairs for the linear motion t0 -> t1 of object [N,3] and tool [M,3] positions (m).

    With ``tool_bound`` and both tool poses, object primitives are first culled with the
    tool's analytic SDF. ``check=False`` skips input validation (hot path, trusted arrays:
    then the tool positions must be ``tool.world_vertices(pose)`` at both ends);
    ``cache`` is a dict the caller keeps across steps of the same object (edge-length bound);
    ``transposed`` optionally gives the four position arrays already as contiguous [3,N] arrays.
    """
    if check:
        object_t0 = _check_positions(object_t0, object_surface.n_vertices, "object_t0")
        object_t1 = _check_positions(object_t1, object_surface.n_vertices, "object_t1")
        tool_t0 = _check_positions(tool_t0, tool_surface.n_vertices, "tool_t0")
        tool_t1 = _check_positions(tool_t1, tool_surface.n_vertices, "tool_t1")
    if transposed is not None:
        X0T, X1T, T0T, T1T = transposed
    else:
        X0T, X1T, T0T, T1T = (np.ascontiguousarray(np.asarray(x, dtype=np.float64).T)
                              for x in (object_t0, object_t1, tool_t0, tool_t1))
    if tool_bound is not None and tool_bound.usable and tool_pose_t0 is not None and tool_pose_t1 is not None:
        dT = T1T - T0T
        D = float(_norm_soa(dT[0], dT[1], dT[2]).max())
        bound = tool_bound
        if check:
            # The SDF describes the tool at the given poses; the positions must be that mesh.
            # A small mismatch (e.g. float32 storage) widens the margin; a large one is an error.
            dev = max(float(np.abs(tool_bound.tool.world_vertices(p) - np.asarray(x)).max())
                      for p, x in ((tool_pose_t0, tool_t0), (tool_pose_t1, tool_t1)))
            if dev > 1e-3 * max(tool_bound.radius, 1e-9):
                raise InputError(f"tool positions differ from the tool mesh at the given poses by {dev:.3g} m")
            bound = tool_bound.widened(2.0 * dev)
        near_v, near_e, near_f = sdf_near_primitives(X0T, X1T, object_surface, bound, tool_pose_t0,
                                                     tool_pose_t1, D, cache)
    else:
        near_v = object_surface.vertices
        near_e = np.arange(len(object_surface.edges))
        near_f = np.arange(len(object_surface.faces))
    out = CandidatePairs()
    if len(near_v) + len(near_e) + len(near_f) == 0:
        return out
    # Per-vertex swept boxes; a primitive's box is the union of its vertices' boxes.
    olo, ohi = np.minimum(X0T, X1T), np.maximum(X0T, X1T)
    tlo, thi = np.minimum(T0T, T1T), np.maximum(T0T, T1T)
    # Region R: box of every near object primitive. A tool face/edge whose box meets R has
    # *every* vertex box within Lt (its longest edge over the step) of R, so tool primitives
    # with a vertex outside R + Lt are dropped before the pairwise join.
    ids = np.unique(np.concatenate([near_v, object_surface.edges[near_e].ravel(), object_surface.faces[near_f].ravel()]))
    r_lo, r_hi = olo[:, ids].min(axis=1), ohi[:, ids].max(axis=1)
    lt = max(_max_edge_length(T0T, tool_surface, None if cache is None else cache.setdefault("tool", {})),
             _max_edge_length(T1T, tool_surface, None if cache is None else cache.setdefault("tool", {})))
    rel = np.all((tlo <= (r_hi + lt)[:, None]) & (thi >= (r_lo - lt)[:, None]), axis=0)
    if not rel.any():
        return out
    if len(near_v):
        G = tool_surface.faces
        gsel = np.flatnonzero(rel[G[:, 0]] & rel[G[:, 1]] & rel[G[:, 2]])
        p = box_pairs(olo[:, near_v], ohi[:, near_v], *_prim_boxes(tlo, thi, G[gsel]), soa=True)
        out.vf = np.stack([near_v[p[:, 0]], gsel[p[:, 1]]], axis=1)
    if len(near_f):
        vsel = np.flatnonzero(rel)
        p = box_pairs(tlo[:, vsel], thi[:, vsel], *_prim_boxes(olo, ohi, object_surface.faces[near_f]), soa=True)
        out.fv = np.stack([vsel[p[:, 0]], near_f[p[:, 1]]], axis=1)
    if len(near_e):
        H = tool_surface.edges
        hsel = np.flatnonzero(rel[H[:, 0]] & rel[H[:, 1]])
        p = box_pairs(*_prim_boxes(olo, ohi, object_surface.edges[near_e]), *_prim_boxes(tlo, thi, H[hsel]), soa=True)
        out.ee = np.stack([near_e[p[:, 0]], hsel[p[:, 1]]], axis=1)
    return out


def _prim_boxes(vlo: np.ndarray, vhi: np.ndarray, prims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes [3,K] of primitives [K,k] from per-vertex boxes [3,N] (gathers + elementwise min/max)."""
    lo = vlo[:, prims[:, 0]]
    hi = vhi[:, prims[:, 0]]
    for i in range(1, prims.shape[1]):
        np.minimum(lo, vlo[:, prims[:, i]], out=lo)
        np.maximum(hi, vhi[:, prims[:, i]], out=hi)
    return lo, hi
