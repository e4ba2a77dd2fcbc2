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

from colgnn_core.collision.broad_phase import CandidatePairs, Surface, ToolSDFBound, step_candidates
from colgnn_core.collision.broad_phase import _check_positions as _positions
from colgnn_core.collision.filter import coefficients_soa, keep_from_coefficients
from colgnn_core.collision.narrow_phase import (NarrowResult, bernstein_from_coefficients, edge_edge_depth_torch,
                                                 narrow_soa, vertex_face_depth_torch)
from colgnn_core.errors import InputError

__all__ = ["CollisionDetector", "StepCollisions", "pair_points", "coplanarity_points", "filter_pairs"]

_U = np.finfo(np.float64).eps / 2


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


def coplanarity_points(kind: str, pairs: np.ndarray, XT: tuple, object_surface: Surface,
                       tool_surface: Surface) -> list[np.ndarray]:
    """The 8 [3,K] arrays (p, a, b, c at t0, then t1) of the coplanarity cubic for candidate pairs.

    XT = (object_t0, object_t1, tool_t0, tool_t1) as [3,N] / [3,M] arrays. Edge-edge pairs
    (u, v | k, l) become p = l, triangle (k, u, v).
    """
    pts = pair_points(kind, pairs, *(_ColumnGather(x) for x in XT), object_surface, tool_surface)
    if kind == "ee":
        ea0, ea1, eb0, eb1, fa0, fa1, fb0, fb1 = pts
        pts = [eb1, eb0, ea0, ea1, fb1, fb0, fa0, fa1]
    return pts


def filter_pairs(kind: str, pairs: np.ndarray, object_t0, object_t1, tool_t0, tool_t1, object_surface: Surface,
                 tool_surface: Surface) -> np.ndarray:
    """Keep mask [K] of the non-penetration filter for candidate pairs of one kind ('vf', 'fv', 'ee')."""
    if len(pairs) == 0:
        return np.zeros(0, dtype=bool)
    XT = tuple(np.ascontiguousarray(np.asarray(x, dtype=np.float64).T) for x in (object_t0, object_t1, tool_t0, tool_t1))
    coef, mag = coefficients_soa(*coplanarity_points(kind, pairs, XT, object_surface, tool_surface))
    return keep_from_coefficients(coef, mag, _U)


class _ColumnGather:
    """Indexing adaptor: X[idx] on a [3,N] array returns the [3,K] columns."""

    __slots__ = ("a",)

    def __init__(self, a: np.ndarray) -> None:
        self.a = a

    def __getitem__(self, idx):
        return self.a[:, idx]


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
        self.object_surface = Surface.from_faces(object_faces, n_object, "object")
        self.tool_surface = Surface.from_faces(tool_faces, n_tool, "tool")
        self.tool_bound = ToolSDFBound(tool) if tool is not None else None
        self._cache: dict = {}
        if tool is not None and len(np.asarray(tool.vertices)) != n_tool:
            raise InputError(f"tool mesh has {len(tool.vertices)} vertices, positions have {n_tool}")

    def _surfaces(self):
        return self.object_surface, self.tool_surface

    def detect(self, object_t0, object_t1, tool_t0, tool_t1, tool_pose_t0=None, tool_pose_t1=None, *,
               narrow: bool = True, check: bool = True) -> StepCollisions:
        """Run the pipeline on positions [N,3] / [M,3] at t and t+1 (m). Poses enable SDF culling."""
        t_start = time.perf_counter()
        if check:
            object_t0 = _positions(object_t0, self.object_surface.n_vertices, "object_t0")
            object_t1 = _positions(object_t1, self.object_surface.n_vertices, "object_t1")
            tool_t0 = _positions(tool_t0, self.tool_surface.n_vertices, "tool_t0")
            tool_t1 = _positions(tool_t1, self.tool_surface.n_vertices, "tool_t1")
        XT = tuple(np.ascontiguousarray(np.asarray(x, dtype=np.float64).T)
                   for x in (object_t0, object_t1, tool_t0, tool_t1))
        cand = step_candidates(object_t0, object_t1, self.object_surface, tool_t0, tool_t1, self.tool_surface,
                               tool_bound=self.tool_bound, tool_pose_t0=tool_pose_t0, tool_pose_t1=tool_pose_t1,
                               check=check, cache=self._cache, transposed=XT)
        t_broad = time.perf_counter()
        kinds = ("vf", "fv", "ee")
        sizes = [len(getattr(cand, k)) for k in kinds]
        # One filter call over all kinds: the cost is per numpy call, not per pair.
        parts = [coplanarity_points(k, getattr(cand, k), XT, *self._surfaces()) for k in kinds]
        pts = [np.concatenate([p[i] for p in parts], axis=1) for i in range(8)]
        coef, mag = coefficients_soa(*pts)
        keep = keep_from_coefficients(coef, mag, _U)
        bounds = np.cumsum([0] + sizes)
        surv = CandidatePairs()
        for i, k in enumerate(kinds):
            setattr(surv, k, getattr(cand, k)[keep[bounds[i]:bounds[i + 1]]])
        t_filter = time.perf_counter()
        out = StepCollisions(candidates=cand, survivors=surv)
        if narrow:
            sel = np.flatnonzero(keep)
            is_ee = sel >= bounds[2]
            bern, flat = bernstein_from_coefficients([c[sel] for c in coef], [m[sel] for m in mag])
            res = narrow_soa([x[:, sel] for x in pts], is_ee, bern, flat)
            kind_of = np.searchsorted(bounds[1:], sel, side="right")
            for i, k in enumerate(kinds):
                m = kind_of == i
                setattr(out, k, NarrowResult(res.hit[m], res.toi[m], res.depth[m], res.degenerate[m]))
        t_end = time.perf_counter()
        out.timings_ms = {"broad": 1e3 * (t_broad - t_start), "filter": 1e3 * (t_filter - t_broad),
                          "narrow": 1e3 * (t_end - t_filter), "total": 1e3 * (t_end - t_start)}
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
