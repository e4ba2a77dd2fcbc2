"""One-call collision detection for a step t -> t+1: broad phase, filter, narrow phase.

``CollisionDetector`` holds the (fixed) topology of the object surface and the tool
mesh and, optionally, the tool itself for SDF culling. ``detect`` runs the three
stages on positions at t and t+1; ``crossing_depths_torch`` gives differentiable
depths of the crossing pairs for the training loss (L_ccd).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from numba import njit

from colgnn_core.collision.broad_phase import (CandidatePairs, Surface, ToolSDFBound, check_positions, step_candidates,
                                               warm_up_broad_phase)
from colgnn_core.collision.filter import keep_quads
from colgnn_core.collision.narrow_phase import (NarrowResult, cubic_roots_01, depth_quads, edge_edge_depth_torch,
                                                filter_narrow_quads, vertex_face_depth_torch)
from colgnn_core.errors import InputError

__all__ = ["CollisionDetector", "StepCollisions", "pair_points", "pair_quads", "stacked_positions", "filter_pairs",
           "warm_up_kernels"]

def pair_points(kind: str, pairs: np.ndarray, object_t0, object_t1, tool_t0, tool_t1, object_surface: Surface,
                tool_surface: Surface) -> list:
    """The 8 [K,3] position arrays of candidate pairs, in filter / ipctk argument order.

    kind 'vf': (p0, a0, b0, c0, p1, a1, b1, c1) with p an object vertex, (a,b,c) a tool face;
    kind 'fv': the same with p a tool vertex and an object face;
    kind 'ee': (ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ...) with ea an object edge, eb a tool edge.
    Works for numpy arrays and torch tensors alike.
    """
    i, j = pairs[:, 0], pairs[:, 1]
    if kind == "vf":
        f = tool_surface.faces[j]
        P0, P1, Q0, Q1 = object_t0, object_t1, tool_t0, tool_t1
        return [P0[i], Q0[f[:, 0]], Q0[f[:, 1]], Q0[f[:, 2]], P1[i], Q1[f[:, 0]], Q1[f[:, 1]], Q1[f[:, 2]]]
    if kind == "fv":
        f = object_surface.faces[j]
        P0, P1, Q0, Q1 = tool_t0, tool_t1, object_t0, object_t1
        return [P0[i], Q0[f[:, 0]], Q0[f[:, 1]], Q0[f[:, 2]], P1[i], Q1[f[:, 0]], Q1[f[:, 1]], Q1[f[:, 2]]]
    if kind == "ee":
        ea = object_surface.edges[i]
        eb = tool_surface.edges[j]
        return [object_t0[ea[:, 0]], object_t0[ea[:, 1]], tool_t0[eb[:, 0]], tool_t0[eb[:, 1]],
                object_t1[ea[:, 0]], object_t1[ea[:, 1]], tool_t1[eb[:, 0]], tool_t1[eb[:, 1]]]
    raise ValueError(f"unknown pair kind {kind!r}")


@njit(cache=True)
def _quads_kernel(vf, fv, ee, object_faces, object_edges, tool_faces, tool_edges, n_object):
    K = len(vf) + len(fv) + len(ee)
    quads = np.empty((K, 4), dtype=np.int64)
    is_ee = np.zeros(K, dtype=np.bool_)
    r = 0
    for k in range(len(vf)):
        g = vf[k, 1]
        quads[r, 0] = vf[k, 0]
        for i in range(3):
            quads[r, 1 + i] = tool_faces[g, i] + n_object
        r += 1
    for k in range(len(fv)):
        f = fv[k, 1]
        quads[r, 0] = fv[k, 0] + n_object
        for i in range(3):
            quads[r, 1 + i] = object_faces[f, i]
        r += 1
    for k in range(len(ee)):
        e, h = ee[k, 0], ee[k, 1]
        # (u, v | k, l) -> p = l, triangle (k, u, v)
        quads[r, 0] = tool_edges[h, 1] + n_object
        quads[r, 1] = tool_edges[h, 0] + n_object
        quads[r, 2] = object_edges[e, 0]
        quads[r, 3] = object_edges[e, 1]
        is_ee[r] = True
        r += 1
    return quads, is_ee


def pair_quads(pairs: CandidatePairs, object_surface: Surface, tool_surface: Surface
               ) -> tuple[np.ndarray, np.ndarray]:
    """Coplanarity quads of candidate pairs, in the order vf, fv, ee.

    Returns (quads [K,4] int64 rows (p, a, b, c) into the stacked positions [object; tool]
    (see :func:`stacked_positions`), is_ee [K] bool). Edge-edge pairs (u, v | k, l) become
    p = l, triangle (k, u, v).
    """
    return _quads_kernel(pairs.vf, pairs.fv, pairs.ee, object_surface.faces, object_surface.edges,
                         tool_surface.faces, tool_surface.edges, object_surface.n_vertices)


def stacked_positions(object_x, tool_x) -> np.ndarray:
    """[N+M,3] float64: object positions then tool positions (what :func:`pair_quads` indexes)."""
    return np.concatenate([np.asarray(object_x, dtype=np.float64), np.asarray(tool_x, dtype=np.float64)])


def filter_pairs(kind: str, pairs: np.ndarray, object_t0, object_t1, tool_t0, tool_t1, object_surface: Surface,
                 tool_surface: Surface) -> np.ndarray:
    """Keep mask [K] of the non-penetration filter for candidate pairs of one kind ('vf', 'fv', 'ee')."""
    if kind not in ("vf", "fv", "ee"):
        raise ValueError(f"unknown pair kind {kind!r}")
    cand = CandidatePairs()
    setattr(cand, kind, np.asarray(pairs, dtype=np.int64).reshape(-1, 2))
    quads, _ = pair_quads(cand, object_surface, tool_surface)
    return keep_quads(stacked_positions(object_t0, tool_t0), stacked_positions(object_t1, tool_t1), quads)


_KERNELS_READY = False


def warm_up_kernels() -> None:
    """Load every numba kernel of the collision code (compiling it the first time on a machine,
    ~15 s, then cached on disk: ~0.4 s), so that the first real step is not the slow one.
    Idempotent; :class:`CollisionDetector` calls it."""
    global _KERNELS_READY
    if _KERNELS_READY:
        return
    # A vertex moving through a triangle: every kernel runs on real (tiny) data.
    faces = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]], dtype=np.int64)
    obj0 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tool_faces = np.array([[0, 1, 2]], dtype=np.int64)
    tool0 = np.array([[0.1, 0.1, 0.5], [0.9, 0.1, 0.5], [0.1, 0.9, 0.5]]) + [0, 0, 1.0]
    tool1 = tool0 - [0, 0, 1.0]
    so, st = Surface.from_faces(faces, 4), Surface.from_faces(tool_faces, 3)
    cand = step_candidates(obj0, obj0, so, tool0, tool1, st, check=False)
    quads, is_ee = pair_quads(cand, so, st)
    X0, X1 = stacked_positions(obj0, tool0), stacked_positions(obj0, tool1)
    filter_narrow_quads(X0, X1, quads, is_ee, True)
    keep_quads(X0, X1, quads)
    depth_quads(X0, X1, quads, is_ee)
    cubic_roots_01(np.array([[-1.0, 0.0, 0.0, 1.0]]))
    warm_up_broad_phase(obj0, so)
    _KERNELS_READY = True


@dataclass
class StepCollisions:
    """Result of :meth:`CollisionDetector.detect`.

    candidates: broad-phase pairs; survivors: pairs the filter kept; vf/fv/ee:
    :class:`NarrowResult` aligned with ``survivors`` (empty when narrow=False);
    timings_ms: broad, filter, narrow, total.
    """

    candidates: CandidatePairs
    survivors: CandidatePairs
    vf: NarrowResult = field(default_factory=NarrowResult.empty)
    fv: NarrowResult = field(default_factory=NarrowResult.empty)
    ee: NarrowResult = field(default_factory=NarrowResult.empty)
    timings_ms: dict = field(default_factory=dict)

    def crossings(self) -> CandidatePairs:
        """Pairs the narrow phase found crossing during the step."""
        return CandidatePairs(vf=self.survivors.vf[self.vf.hit], fv=self.survivors.fv[self.fv.hit],
                              ee=self.survivors.ee[self.ee.hit])

    def summary(self) -> dict:
        """N_vf (object-vertex/tool-face plus tool-vertex/object-face), N_ee, and depth mean/max (m)."""
        dvf = np.concatenate([self.vf.depth[self.vf.hit], self.fv.depth[self.fv.hit]])
        dee = self.ee.depth[self.ee.hit]
        return {
            "N_vf": int(len(dvf)), "d_vf_mean": float(dvf.mean()) if len(dvf) else 0.0,
            "d_vf_max": float(dvf.max()) if len(dvf) else 0.0,
            "N_ee": int(len(dee)), "d_ee_mean": float(dee.mean()) if len(dee) else 0.0,
            "d_ee_max": float(dee.max()) if len(dee) else 0.0,
        }


class CollisionDetector:
    """Broad phase + non-penetration filter + narrow phase for one object and one tool.

    object_faces [F,3] and tool_faces [G,3] index position arrays of n_object / n_tool rows
    (all vertices of a tet mesh may be passed; only surface vertices are used). ``tool``
    (a colgnn_core.geometry.tools.Tool) enables SDF culling when poses are passed to ``detect``.
    """

    def __init__(self, object_faces, tool_faces, n_object: int, n_tool: int, tool=None) -> None:
        warm_up_kernels()
        self.object_surface = Surface.from_faces(object_faces, n_object, "object")
        self.tool_surface = Surface.from_faces(tool_faces, n_tool, "tool")
        self.tool_bound = ToolSDFBound(tool) if tool is not None else None
        self._cache: dict = {}
        if tool is not None and len(np.asarray(tool.vertices)) != n_tool:
            raise InputError(f"tool mesh has {len(tool.vertices)} vertices, positions have {n_tool}")

    def _surfaces(self):
        return self.object_surface, self.tool_surface

    def detect(self, object_t0, object_t1, tool_t0, tool_t1, tool_pose_t0=None, tool_pose_t1=None, *,
               narrow: bool = True, check: bool = True, active: np.ndarray | None = None,
               clearance: float = 0.0) -> StepCollisions:
        """Run the pipeline on positions [N,3] / [M,3] at t and t+1 (m). Poses enable SDF culling.
        ``active``: bool [N] or None (all): only object primitives with an active vertex take part.
        ``clearance`` (m): the broad phase keeps every pair that may come that close (a superset of the touching
        ones, so the same crossings; its ``candidates`` then serve a clearance check of the same step)."""
        t_start = time.perf_counter()
        if check:
            object_t0 = check_positions(object_t0, self.object_surface.n_vertices, "object_t0")
            object_t1 = check_positions(object_t1, self.object_surface.n_vertices, "object_t1")
            tool_t0 = check_positions(tool_t0, self.tool_surface.n_vertices, "tool_t0")
            tool_t1 = check_positions(tool_t1, self.tool_surface.n_vertices, "tool_t1")
        cand = step_candidates(object_t0, object_t1, self.object_surface, tool_t0, tool_t1, self.tool_surface,
                               tool_bound=self.tool_bound, tool_pose_t0=tool_pose_t0, tool_pose_t1=tool_pose_t1,
                               check=check, cache=self._cache, active=active, clearance=clearance)
        t_broad = time.perf_counter()
        kinds = ("vf", "fv", "ee")
        quads, is_ee = pair_quads(cand, *self._surfaces())
        # One kernel call: filter every pair, narrow phase on the kept ones.
        keep, hit, toi, depth, degenerate = filter_narrow_quads(
            stacked_positions(object_t0, tool_t0), stacked_positions(object_t1, tool_t1), quads, is_ee, narrow)
        bounds = np.cumsum([0] + [len(getattr(cand, k)) for k in kinds])
        surv = CandidatePairs()
        out = StepCollisions(candidates=cand, survivors=surv)
        for i, k in enumerate(kinds):
            sl = slice(bounds[i], bounds[i + 1])
            kept = keep[sl]
            setattr(surv, k, getattr(cand, k)[kept])
            if narrow:
                setattr(out, k, NarrowResult(hit[sl][kept], toi[sl][kept], depth[sl][kept], degenerate[sl][kept]))
        t_end = time.perf_counter()
        # Filter and narrow phase run fused in one kernel: "filter_narrow" is their joint time.
        out.timings_ms = {"broad": 1e3 * (t_broad - t_start), "filter_narrow": 1e3 * (t_end - t_broad),
                          "total": 1e3 * (t_end - t_start)}
        return out

    def crossing_depths_torch(self, object_t0, object_t1: torch.Tensor, tool_t0, tool_t1, tool_pose_t0=None,
                              tool_pose_t1=None) -> dict[str, torch.Tensor]:
        """Differentiable wrong-side depths (m) of the pairs that cross during the step.

        Detection runs in numpy on detached float64 copies; the depths are then evaluated in
        torch on the crossing pairs, so gradients flow to ``object_t1`` (and to any other
        argument given as a tensor that requires grad). Returns {'vertex_face': [Kvf] (object
        vertex/tool face and tool vertex/object face), 'edge_edge': [Kee]} in object_t1's dtype.
        The training loss L_ccd = max(vertex_face) + max(edge_edge) (0 for empty sets).
        """
        def np64(x):
            return x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)

        poses = [None if p is None else np64(p) for p in (tool_pose_t0, tool_pose_t1)]
        res = self.detect(np64(object_t0), np64(object_t1), np64(tool_t0), np64(tool_t1), *poses)
        hits = res.crossings()
        dev, dt = object_t1.device, object_t1.dtype

        def tens(x):
            return x.to(device=dev, dtype=dt) if isinstance(x, torch.Tensor) else torch.as_tensor(
                np.asarray(x), dtype=dt, device=dev)

        X = [tens(x) for x in (object_t0, object_t1, tool_t0, tool_t1)]
        vf_parts = []
        for kind in ("vf", "fv"):
            pairs = torch.as_tensor(getattr(hits, kind), device=dev)
            if len(pairs):
                surf_o = _TorchSurface(self.object_surface, dev)
                surf_t = _TorchSurface(self.tool_surface, dev)
                vf_parts.append(vertex_face_depth_torch(*pair_points(kind, pairs, *X, surf_o, surf_t)))
        vf = torch.cat(vf_parts) if vf_parts else torch.zeros(0, dtype=dt, device=dev)
        if len(hits.ee):
            pairs = torch.as_tensor(hits.ee, device=dev)
            ee = edge_edge_depth_torch(*pair_points("ee", pairs, *X, _TorchSurface(self.object_surface, dev),
                                                    _TorchSurface(self.tool_surface, dev)))
        else:
            ee = torch.zeros(0, dtype=dt, device=dev)
        return {"vertex_face": vf, "edge_edge": ee}


class _TorchSurface:
    """faces/edges of a Surface as torch index tensors (for pair_points on tensors)."""

    def __init__(self, s: Surface, device) -> None:
        self.faces = torch.as_tensor(s.faces, device=device)
        self.edges = torch.as_tensor(s.edges, device=device)
