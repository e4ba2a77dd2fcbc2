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

With a clearance c (``step_candidates(..., clearance=c)``: pairs that may come
closer than c during the step, for :mod:`.clearance`) the same bound reads
s0 + s1 - d - D - 2m > 2c, and the object's swept boxes grow by c.

The remaining primitives are paired by overlapping swept boxes (box of the
primitive's vertices at t0 and t1). Tool primitives that cannot reach the box of
the remaining object primitives are dropped first. The box join sorts both sets
along the axis where the boxes are smallest relative to their spread and sweeps.
The loops over vertices, primitives and pairs run as numba kernels (compiled once,
cached on disk): at a few hundred candidates the cost of a numpy call, not the
arithmetic, dominated the vectorised version.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numba.extending import register_jitable

from colgnn_core.collision.kernels import (box_join, longest_edge, map_pairs, prim_boxes, row_distance, sphere_bounds,
                                           vertex_boxes)
from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import quat_to_matrix

__all__ = ["Surface", "CandidatePairs", "ToolSDFBound", "mesh_edges", "box_pairs", "sdf_near_primitives",
           "check_positions", "step_candidates", "active_ring", "active_primitives", "warm_up_broad_phase"]

_EMPTY_PAIRS = np.zeros((0, 2), dtype=np.int64)


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

    @property
    def edge_faces(self) -> np.ndarray:
        """[E,2] int64: the two faces sharing each edge, the lower face id first; -1 where an edge borders only one
        (an open surface) (cached)."""
        c = self.__dict__.get("_edge_faces")
        if c is None:
            owner = np.repeat(np.arange(len(self.faces)), 3)
            e = self.face_edges.reshape(-1)
            order = np.lexsort((owner, e))
            e, owner = e[order], owner[order]
            c = np.full((len(self.edges), 2), -1, dtype=np.int64)
            first = np.r_[True, e[1:] != e[:-1]]
            c[e[first], 0] = owner[first]
            c[e[~first], 1] = owner[~first]
            object.__setattr__(self, "_edge_faces", c)
        return c

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


def box_pairs(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray) -> np.ndarray:
    """All (i, j) with box a_i and box b_j overlapping (closed boxes). Boxes [K,3]; returns [K,2] int64."""
    lo_a, hi_a, lo_b, hi_b = (np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, 3))
                              for x in (lo_a, hi_a, lo_b, hi_b))
    return box_join(lo_a, hi_a, lo_b, hi_b)


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

    def lower_bounds(self, X0: np.ndarray, X1: np.ndarray, ids: np.ndarray, pose0, pose1, needed: float
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Lower bounds [K] (m) of the distance to the tool mesh (+ ``margin``) at t0 and t1 for
        the points ``X0[ids]``, ``X1[ids]`` (X [N,3]): the analytic SDF, or the bounding-sphere
        distance where that is enough.

        The SDF is evaluated only for points whose sphere bounds sum to at most ``needed``;
        any lower bound of the distance keeps the culling conservative (module docstring).
        """
        c0, c1 = (quat_to_matrix(np.asarray(p, dtype=np.float64)[3:]) @ self.center_local
                  + np.asarray(p, dtype=np.float64)[:3] for p in (pose0, pose1))
        lb0, lb1 = sphere_bounds(X0, X1, ids, c0, c1, self.radius)
        idx = np.flatnonzero((lb0 + lb1) <= needed)
        if len(idx):
            for lb, X, pose in ((lb0, X0, pose0), (lb1, X1, pose1)):
                sdf = np.asarray(self.tool.sdf(X[ids[idx]], pose), dtype=np.float64)
                lb[idx] = np.maximum(lb[idx], sdf)
        return lb0, lb1


@njit(cache=True)
def _max_row_distance(X, Y, rows):
    """max over ``rows`` of |X[r] - Y[r]| (m); all rows when ``rows`` is empty."""
    m = 0.0
    n = rows.shape[0] if rows.shape[0] else X.shape[0]
    for i in range(n):
        r = rows[i] if rows.shape[0] else i
        m = max(m, row_distance(X, r, Y, r))
    return m


_ALL_ROWS = np.zeros(0, dtype=np.int64)


def _max_edge_length(X: np.ndarray, surface: Surface, cache: dict | None) -> float:
    """Upper bound (m) on the longest surface edge at positions X [N,3].

    With a cache: exact lengths at a reference state, plus twice the largest vertex
    displacement from it (an edge grows at most by the motion of its two ends). The
    reference is refreshed when the bound gets loose.
    """
    if cache is not None and "ref" in cache and cache["ref"].shape == X.shape:
        move = _max_row_distance(X, cache["ref"], surface.vertices)
        if move <= 0.5 * cache["lmax"]:
            return cache["lmax"] + 2.0 * move
    lmax = longest_edge(X, surface.edges)
    if cache is not None:
        cache["ref"] = X.copy()
        cache["lmax"] = lmax
    return lmax


def sdf_near_primitives(X0, X1, surface: Surface, tool_bound: "ToolSDFBound", pose0, pose1,
                        tool_displacement: float, cache: dict | None = None, vertices: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ids of object surface vertices, edges and faces that may touch the tool (see module docstring).

    X0, X1: [N,3] object positions at t0 and t1 (float64, C order); pose0, pose1: tool poses [7];
    tool_displacement: largest tool-vertex motion over the step (m). ``cache`` (a dict kept
    by the caller across steps) speeds up the longest-edge bound. ``vertices``: sorted surface vertex ids to
    examine (default all): a primitive whose vertices are all among them is in the result exactly when it is in
    the result for all vertices (the bounds below are per primitive, with the same global reach); others may
    be missing or extra.
    """
    S = surface.vertices if vertices is None else vertices
    budget = tool_displacement + 2.0 * tool_bound.margin
    lmax0 = _max_edge_length(X0, surface, cache)
    lmax1 = _max_edge_length(X1, surface, cache)
    dmax = _max_row_distance(X1, X0, surface.vertices)
    # A vertex with s0 + s1 - Lmax0 - Lmax1 - Dmax > budget rules out itself and every edge and
    # face it is part of (their bounds below are at least that large).
    reach = budget + lmax0 + lmax1 + dmax
    sdf0, sdf1 = tool_bound.lower_bounds(X0, X1, S, pose0, pose1, reach)
    ve, vf = surface.vertex_edges, surface.vertex_faces
    return _near_primitives(X0, X1, S, sdf0, sdf1, budget, reach, surface.edges, surface.faces,
                            ve[0], ve[1], vf[0], vf[1])


@njit(cache=True)
def _near_primitives(X0, X1, S, sdf0, sdf1, budget, reach, edges, faces, ve_off, ve_ids, vf_off, vf_ids):
    """(near vertices, edges, faces): vertex bound s0 + s1 - d <= budget; edges and faces around
    the "hopeful" vertices (s0 + s1 <= reach) get their own bound from their vertices:
    every point is within L of each vertex, and within L/2 (segment) or L/sqrt(3)
    (triangle) of the nearest one."""
    n = X0.shape[0]
    s0 = np.full(n, np.inf)
    s1 = np.full(n, np.inf)
    disp = np.zeros(n)
    near_v = np.empty(len(S), dtype=np.int64)
    nv = 0
    for i in range(len(S)):
        v = S[i]
        s0[v], s1[v] = sdf0[i], sdf1[i]
        disp[v] = row_distance(X1, v, X0, v)
        if sdf0[i] + sdf1[i] - disp[v] <= budget:
            near_v[nv] = v
            nv += 1
    seen_e = np.zeros(len(edges), dtype=np.bool_)
    seen_f = np.zeros(len(faces), dtype=np.bool_)
    near_e = np.empty(len(edges), dtype=np.int64)
    near_f = np.empty(len(faces), dtype=np.int64)
    ne = nf = 0
    for i in range(len(S)):
        v = S[i]
        if not sdf0[i] + sdf1[i] <= reach:
            continue
        for q in range(ve_off[v], ve_off[v + 1]):
            e = ve_ids[q]
            if seen_e[e]:
                continue
            seen_e[e] = True
            a, b = edges[e, 0], edges[e, 1]
            L0, L1 = row_distance(X0, a, X0, b), row_distance(X1, a, X1, b)
            lb0 = max(max(s0[a], s0[b]) - L0, min(s0[a], s0[b]) - 0.5 * L0)
            lb1 = max(max(s1[a], s1[b]) - L1, min(s1[a], s1[b]) - 0.5 * L1)
            if lb0 + lb1 - max(disp[a], disp[b]) <= budget:
                near_e[ne] = e
                ne += 1
        for q in range(vf_off[v], vf_off[v + 1]):
            f = vf_ids[q]
            if seen_f[f]:
                continue
            seen_f[f] = True
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            L0 = max(row_distance(X0, a, X0, b), row_distance(X0, b, X0, c), row_distance(X0, c, X0, a))
            L1 = max(row_distance(X1, a, X1, b), row_distance(X1, b, X1, c), row_distance(X1, c, X1, a))
            r = 1.0 / np.sqrt(3.0)
            lb0 = max(max(s0[a], s0[b], s0[c]) - L0, min(s0[a], s0[b], s0[c]) - r * L0)
            lb1 = max(max(s1[a], s1[b], s1[c]) - L1, min(s1[a], s1[b], s1[c]) - r * L1)
            if lb0 + lb1 - max(disp[a], disp[b], disp[c]) <= budget:
                near_f[nf] = f
                nf += 1
    return near_v[:nv].copy(), np.sort(near_e[:ne]), np.sort(near_f[:nf])


def check_positions(X, n: int, name: str) -> np.ndarray:
    """``X`` as a float64 [n,3] array of finite positions (InputError naming ``name`` otherwise)."""
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] != n:
        raise InputError(f"{name} must be [{n},3], got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError(f"{name} contains NaN or inf")
    return X


def step_candidates(object_t0, object_t1, object_surface: Surface, tool_t0, tool_t1, tool_surface: Surface, *,
                    tool_bound: ToolSDFBound | None = None, tool_pose_t0=None, tool_pose_t1=None,
                    check: bool = True, cache: dict | None = None, clearance: float = 0.0,
                    active: np.ndarray | None = None) -> CandidatePairs:
    """Candidate pairs for the linear motion t0 -> t1 of object [N,3] and tool [M,3] positions (m).

    With ``tool_bound`` and both tool poses, object primitives are first culled with the
    tool's analytic SDF. ``check=False`` skips input validation (hot path, trusted arrays:
    then the tool positions must be ``tool.world_vertices(pose)`` at both ends);
    ``cache`` is a dict the caller keeps across steps of the same object (edge-length bounds).
    ``clearance`` (m): every pair that may come closer than this during the step (default: that may touch).
    ``active``: bool [N] or None (all): only object primitives with at least one active vertex take part (the
    correction's later passes re-examine only what the pass before moved or flagged).
    """
    if not clearance >= 0:
        raise InputError(f"clearance must be >= 0 (m), got {clearance}")
    if check:
        object_t0 = check_positions(object_t0, object_surface.n_vertices, "object_t0")
        object_t1 = check_positions(object_t1, object_surface.n_vertices, "object_t1")
        tool_t0 = check_positions(tool_t0, tool_surface.n_vertices, "tool_t0")
        tool_t1 = check_positions(tool_t1, tool_surface.n_vertices, "tool_t1")
    X0, X1, T0, T1 = (np.ascontiguousarray(x, dtype=np.float64) for x in (object_t0, object_t1, tool_t0, tool_t1))
    if tool_bound is not None and tool_bound.usable and tool_pose_t0 is not None and tool_pose_t1 is not None:
        D = _max_row_distance(T1, T0, _ALL_ROWS)
        bound = tool_bound
        if check:
            # The SDF describes the tool at the given poses; the positions must be that mesh.
            # A small mismatch (e.g. float32 storage) widens the margin; a large one is an error.
            dev = max(float(np.abs(tool_bound.tool.world_vertices(p) - np.asarray(x)).max())
                      for p, x in ((tool_pose_t0, tool_t0), (tool_pose_t1, tool_t1)))
            if dev > 1e-3 * max(tool_bound.radius, 1e-9):
                raise InputError(f"tool positions differ from the tool mesh at the given poses by {dev:.3g} m")
            bound = tool_bound.widened(2.0 * dev)
        # The clearance enters the SDF bound like extra tool motion: s0 + s1 - d - (D + 2c) - 2m > 0.
        # With ``active``: the SDF bounds of the active primitives' vertices only (their bounds use nothing else).
        ring = None if active is None else active_ring(active, object_surface)
        near_v, near_e, near_f = sdf_near_primitives(X0, X1, object_surface, bound, tool_pose_t0, tool_pose_t1,
                                                     D + 2.0 * clearance, cache, ring)
    else:
        near_v = object_surface.vertices
        near_e = np.arange(len(object_surface.edges))
        near_f = np.arange(len(object_surface.faces))
    if active is not None:
        near_v, near_e, near_f = active_primitives(active, near_v, near_e, near_f, object_surface.edges,
                                                   object_surface.faces)
    if len(near_v) + len(near_e) + len(near_f) == 0:
        return CandidatePairs()
    vf, fv, ee = _swept_box_pairs(X0, X1, T0, T1, near_v, near_e, near_f, object_surface.faces,
                                  object_surface.edges, tool_surface.faces, tool_surface.edges, float(clearance))
    return CandidatePairs(vf=vf, fv=fv, ee=ee)


def active_ring(active: np.ndarray, surface: Surface) -> np.ndarray:
    """Sorted ids [K] of the vertices of every face of ``surface`` with a vertex marked in ``active`` (bool [N]):
    the vertices of every primitive with an active vertex (each edge lies on a face)."""
    off, ids = surface.vertex_faces
    return _face_ring(active, surface.faces, off, ids)


@njit(cache=True)
def _face_ring(active, faces, vf_off, vf_ids):
    """:func:`active_ring` over the vertex -> face CSR (``vf_off`` [N+1], ``vf_ids``): cost in the active vertices."""
    ring = np.zeros(active.shape[0], dtype=np.bool_)
    for v in range(active.shape[0]):
        if active[v]:
            for q in range(vf_off[v], vf_off[v + 1]):
                f = vf_ids[q]
                ring[faces[f, 0]] = ring[faces[f, 1]] = ring[faces[f, 2]] = True
    return np.flatnonzero(ring)


def active_primitives(active: np.ndarray, vertices: np.ndarray, edges: np.ndarray, faces: np.ndarray,
                      all_edges: np.ndarray, all_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ids among ``vertices`` [Kv], ``edges`` [Ke] and ``faces`` [Kf] (ids into ``all_edges`` [E,2] and
    ``all_faces`` [F,3]) of the primitives with at least one vertex marked in ``active`` (bool [N])."""
    return (vertices[active[vertices]], edges[active[all_edges[edges]].any(axis=1)],
            faces[active[all_faces[faces]].any(axis=1)])


@njit(cache=True)
def _swept_box_pairs(X0, X1, T0, T1, near_v, near_e, near_f, faces, edges, tool_faces, tool_edges, grow):
    """(vf, fv, ee) pairs [K,2] whose swept boxes (box of the primitive's vertices at t0 and t1; the object's
    grown by ``grow`` m) overlap.

    Region R: box of every near object primitive. Tool primitives whose box misses R, and
    tool vertices outside it, are dropped before the join.
    """
    r_lo = np.full(3, np.inf)
    r_hi = np.full(3, -np.inf)
    vlo, vhi = vertex_boxes(X0, X1, near_v)
    elo, ehi = prim_boxes(X0, X1, edges, near_e)
    flo, fhi = prim_boxes(X0, X1, faces, near_f)
    for lo, hi in ((vlo, vhi), (elo, ehi), (flo, fhi)):
        for k in range(lo.shape[0]):
            for a in range(3):
                lo[k, a] -= grow
                hi[k, a] += grow
                r_lo[a] = min(r_lo[a], lo[k, a])
                r_hi[a] = max(r_hi[a], hi[k, a])
    # Per tool vertex, bit 2a: its swept box is below R on axis a, bit 2a+1: above. A tool
    # primitive's box misses R iff all its vertices share one of those bits.
    m = T0.shape[0]
    side = np.zeros(m, dtype=np.int64)
    for i in range(m):
        for a in range(3):
            if max(T0[i, a], T1[i, a]) < r_lo[a]:
                side[i] |= 1 << (2 * a)
            if min(T0[i, a], T1[i, a]) > r_hi[a]:
                side[i] |= 1 << (2 * a + 1)
    rel = side == 0
    vsel = np.flatnonzero(rel)
    gsel = _meeting_region(tool_faces, side)
    hsel = _meeting_region(tool_edges, side)
    tvlo, tvhi = vertex_boxes(T0, T1, vsel)
    tflo, tfhi = prim_boxes(T0, T1, tool_faces, gsel)
    telo, tehi = prim_boxes(T0, T1, tool_edges, hsel)
    vf = box_join(vlo, vhi, tflo, tfhi)
    fv = box_join(tvlo, tvhi, flo, fhi)
    ee = box_join(elo, ehi, telo, tehi)
    return map_pairs(vf, near_v, gsel), map_pairs(fv, vsel, near_f), map_pairs(ee, near_e, hsel)


@register_jitable
def _meeting_region(prims, side):
    """Ids of primitives whose box meets the region (their vertices share no 'outside' bit)."""
    keep = np.zeros(prims.shape[0], dtype=np.bool_)
    for p in range(prims.shape[0]):
        common = side[prims[p, 0]]
        for i in range(1, prims.shape[1]):
            common &= side[prims[p, i]]
        keep[p] = common == 0
    return np.flatnonzero(keep)


def warm_up_broad_phase(X: np.ndarray, surface: Surface) -> None:
    """Run every broad-phase kernel once on positions ``X`` [N,3] of ``surface`` (numba compiles them, or loads
    them from its disk cache), for :func:`colgnn_core.collision.pipeline.warm_up_kernels`."""
    S = surface.vertices
    lb0, lb1 = sphere_bounds(X, X, S, np.zeros(3), np.zeros(3), 0.1)
    ve, vf = surface.vertex_edges, surface.vertex_faces
    _near_primitives(X, X, S, lb0, lb1, 1.0, 2.0, surface.edges, surface.faces, ve[0], ve[1], vf[0], vf[1])
    active_ring(np.ones(surface.n_vertices, dtype=np.bool_), surface)
    _max_edge_length(X, surface, {})
    box_pairs(X, X + 0.1, X, X)
