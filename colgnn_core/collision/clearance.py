"""Clearance over a step: may an object–tool primitive pair come closer than a threshold during t -> t+1?

"No contact during the step" is weaker than what the exact oracle checks. ipctk's ``is_step_collision_free`` with
Tight-Inclusion CCD and its default conservative rescaling 0.8 (IPC's line-search clearance) reports a step as
colliding when any pair comes closer than min(0.2 d0, 1e-4 m) during it, d0 being the pair's distance at t and the
distance measured in the max norm (|v|_inf >= |v|_2 / sqrt(3)). A surface sliding along the tool can pass 0.1 mm
from it mid-step with both ends 0.2 mm away: no contact, yet a "crossing" for the oracle. This module decides the
stronger property

    every pair keeps a Euclidean distance > min(CLEARANCE, CLEARANCE_RATIO x d0) during the whole linear step,

which implies the oracle's: CLEARANCE = 1.8e-4 m > sqrt(3) x 1e-4 m and CLEARANCE_RATIO = 0.5 > sqrt(3) x 0.2 (the
slack, 4% and 44%, covers the oracle's own tolerance of 1e-6).

Candidates come from the broad phase with the clearance (:func:`~colgnn_core.collision.broad_phase.step_candidates`
with ``clearance``: its SDF bound and swept boxes grown by it). Each candidate pair gets additive CCD (Li et al.
2020, "Codimensional Incremental Potential Contact"): L bounds the motion of any point of one primitive relative to
any point of the other over the step (each vertex's displacement about the mean of the pair's four, the largest per
primitive, summed), so from a time t where the distance is d > thr it cannot reach thr before t + (d - thr) / L.
The next time examined is t + 0.9 (d - thr) / L; a pair passes when that reaches 1, and is flagged when a distance
<= thr + FLAG_TOLERANCE is found (a pair closing at the bounding speed approaches thr geometrically and would never
reach it) or after ``max_iterations`` (conservative). Distances are exact (point–triangle, segment–segment).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange
from numba.extending import register_jitable

from colgnn_core.collision.broad_phase import CandidatePairs, Surface, ToolSDFBound, step_candidates
from colgnn_core.collision.kernels import (JOIN_CHUNKS, changed_rows, lerp, point_triangle_distance, row3, row_order,
                                           segment_distance)

__all__ = ["CLEARANCE", "CLEARANCE_RATIO", "ClearanceResult", "StepClearance", "clearance_pairs", "warm_up_clearance"]

CLEARANCE = 1.8e-4        # m: > sqrt(3) x 1e-4, the oracle's absolute clearance (max norm) in the Euclidean norm
CLEARANCE_RATIO = 0.5     # > sqrt(3) x 0.2 = 0.35, the oracle's relative clearance likewise
MAX_ITERATIONS = 2000     # additive-CCD iterations per pair before it is flagged anyway
STEP_FRACTION = 0.9       # of the largest safe advance (d - thr) / L taken per iteration
FLAG_TOLERANCE = 1e-7     # m: a distance within this of the threshold flags the pair
_NO_PAIRS = np.zeros((0, 2), dtype=np.int64)


@dataclass
class ClearanceResult:
    """Pairs that may come closer than the clearance (:meth:`StepClearance.check`).

    vf (object vertex, tool face), fv (tool vertex, object face), ee (object edge, tool edge): [K,2] ids of the
    flagged pairs; per kind, ``t`` (time in [0,1] where the distance was found at or below the threshold),
    ``d`` (that distance, m) and ``d0`` (the distance at t = 0, m) as dicts of [K] arrays; ``candidates``: pairs
    examined.
    """

    vf: np.ndarray = field(default_factory=lambda: _NO_PAIRS)
    fv: np.ndarray = field(default_factory=lambda: _NO_PAIRS)
    ee: np.ndarray = field(default_factory=lambda: _NO_PAIRS)
    t: dict = field(default_factory=dict)
    d: dict = field(default_factory=dict)
    d0: dict = field(default_factory=dict)
    candidates: int = 0

    @property
    def violations(self) -> int:
        return len(self.vf) + len(self.fv) + len(self.ee)


@njit(cache=True)
def _distance(is_ee, P):
    if is_ee:
        return segment_distance(row3(P, 0), row3(P, 1), row3(P, 2), row3(P, 3))[0]
    return point_triangle_distance(row3(P, 0), row3(P, 1), row3(P, 2), row3(P, 3))


@njit(cache=True)
def _pair_clearance(is_ee, P0, P1, delta, rho, max_iterations):
    """(ok, t, d, d0) for one pair: rows 0-3 of P0 / P1 [4,3] are (point, triangle) or (edge, edge) at t = 0 / 1.
    ok: the distance stays > min(delta, rho d0) over [0, 1]; else (t, d) where it was found at or within
    FLAG_TOLERANCE of that threshold."""
    m0 = (P1[0, 0] - P0[0, 0] + P1[1, 0] - P0[1, 0] + P1[2, 0] - P0[2, 0] + P1[3, 0] - P0[3, 0]) / 4.0
    m1 = (P1[0, 1] - P0[0, 1] + P1[1, 1] - P0[1, 1] + P1[2, 1] - P0[2, 1] + P1[3, 1] - P0[3, 1]) / 4.0
    m2 = (P1[0, 2] - P0[0, 2] + P1[1, 2] - P0[1, 2] + P1[2, 2] - P0[2, 2] + P1[3, 2] - P0[3, 2]) / 4.0
    dev = np.empty(4)
    for i in range(4):
        r0, r1, r2 = P1[i, 0] - P0[i, 0] - m0, P1[i, 1] - P0[i, 1] - m1, P1[i, 2] - P0[i, 2] - m2
        dev[i] = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if is_ee:
        L = max(dev[0], dev[1]) + max(dev[2], dev[3])
    else:
        L = dev[0] + max(dev[1], dev[2], dev[3])
    d0 = _distance(is_ee, P0)
    thr = min(delta, rho * d0)
    if not d0 > thr + FLAG_TOLERANCE:
        return False, 0.0, d0, d0
    if L <= 0.0:  # the pair moves rigidly by one translation: its distance is constant
        return True, 1.0, d0, d0
    t, d = 0.0, d0
    P = np.empty((4, 3))
    for _ in range(max_iterations):
        t += STEP_FRACTION * (d - thr) / L
        if t >= 1.0:
            return True, 1.0, d, d0
        for i in range(4):
            P[i, 0], P[i, 1], P[i, 2] = lerp(row3(P0, i), row3(P1, i), t)
        d = _distance(is_ee, P)
        if not d > thr + FLAG_TOLERANCE:
            return False, t, d, d0
    return False, t, d, d0


@njit(cache=True, parallel=True)
def clearance_pairs(X0, X1, T0, T1, vf, fv, ee, faces, edges, tool_faces, tool_edges, delta, rho, max_iterations):
    """ok [K], t [K], d [K], d0 [K] of :func:`_pair_clearance` for the pairs vf, fv, ee (stacked in that order);
    the pairs are independent and run in ``JOIN_CHUNKS`` blocks on numba's threads."""
    K = vf.shape[0] + fv.shape[0] + ee.shape[0]
    ok = np.empty(K, dtype=np.bool_)
    ts, ds, d0s = np.empty(K), np.empty(K), np.empty(K)
    for c in prange(JOIN_CHUNKS):
        P0, P1 = np.empty((4, 3)), np.empty((4, 3))
        for r in range(c * K // JOIN_CHUNKS, (c + 1) * K // JOIN_CHUNKS):
            _pair_points(r, X0, X1, T0, T1, vf, fv, ee, faces, edges, tool_faces, tool_edges, P0, P1)
            ok[r], ts[r], ds[r], d0s[r] = _pair_clearance(r >= vf.shape[0] + fv.shape[0], P0, P1, delta, rho,
                                                          max_iterations)
    return ok, ts, ds, d0s


@register_jitable
def _pair_points(r, X0, X1, T0, T1, vf, fv, ee, faces, edges, tool_faces, tool_edges, P0, P1):
    """Fill P0 / P1 [4,3] with row r of the stacked pairs (vf: object vertex, tool face; fv: tool vertex, object
    face; ee: object edge, tool edge) at t = 0 / 1."""
    nv, nf = vf.shape[0], fv.shape[0]
    if r < nv:
        v, g = vf[r, 0], vf[r, 1]
        P0[0], P1[0] = X0[v], X1[v]
        for j in range(3):
            P0[1 + j], P1[1 + j] = T0[tool_faces[g, j]], T1[tool_faces[g, j]]
    elif r < nv + nf:
        v, f = fv[r - nv, 0], fv[r - nv, 1]
        P0[0], P1[0] = T0[v], T1[v]
        for j in range(3):
            P0[1 + j], P1[1 + j] = X0[faces[f, j]], X1[faces[f, j]]
    else:
        e, h = ee[r - nv - nf, 0], ee[r - nv - nf, 1]
        for j in range(2):
            P0[j], P1[j] = X0[edges[e, j]], X1[edges[e, j]]
            P0[2 + j], P1[2 + j] = T0[tool_edges[h, j]], T1[tool_edges[h, j]]


class StepClearance:
    """Clearance checks of steps of one object surface against one convex tool (module docstring).

    Args:
        object_surface, tool_surface: the :class:`~colgnn_core.collision.broad_phase.Surface` of each.
        tool_bound: the tool's :class:`~colgnn_core.collision.broad_phase.ToolSDFBound` (SDF culling).
        clearance, ratio: the threshold min(clearance, ratio x d0) (m, fraction).
    """

    def __init__(self, object_surface: Surface, tool_surface: Surface, tool_bound: ToolSDFBound, *,
                 clearance: float = CLEARANCE, ratio: float = CLEARANCE_RATIO, max_iterations: int = MAX_ITERATIONS):
        self.surface = object_surface
        self.tool_surface = tool_surface
        self.tool_bound = tool_bound
        self.clearance = float(clearance)
        self.ratio = float(ratio)
        self.max_iterations = int(max_iterations)
        self._cache: dict = {}

    def check(self, X0, X1, T0, T1, pose0, pose1, *, known: tuple[CandidatePairs, np.ndarray] | None = None
              ) -> ClearanceResult:
        """The pairs of the linear step (object X0 -> X1 [N,3], tool T0 -> T1 [M,3] = the tool mesh at
        ``pose0`` -> ``pose1``, m) that may come closer than the threshold, each kind in row order.

        ``known``: (candidates, X1_ref [N,3]): the broad phase with this clearance of the same step (X0, T0, T1, poses)
        but ending at X1_ref. Its pairs of primitives whose vertices are the same in X1 stand (same positions, same
        pairs); only primitives with a vertex that differs get a broad phase here."""
        X0, X1, T0, T1 = (np.ascontiguousarray(x, dtype=np.float64) for x in (X0, X1, T0, T1))
        cand = self._candidates(X0, X1, T0, T1, pose0, pose1, known)
        s, ts = self.surface, self.tool_surface
        ok, t, d, d0 = clearance_pairs(X0, X1, T0, T1, cand.vf, cand.fv, cand.ee, s.faces, s.edges, ts.faces,
                                        ts.edges, self.clearance, self.ratio, self.max_iterations)
        out = ClearanceResult(candidates=len(ok))
        start = 0
        for kind in ("vf", "fv", "ee"):
            pairs = getattr(cand, kind)
            sl = slice(start, start + len(pairs))
            start += len(pairs)
            bad = np.flatnonzero(~ok[sl])
            bad = bad[row_order(pairs[bad])]  # the same order whichever way the candidates were gathered
            setattr(out, kind, pairs[bad])
            out.t[kind], out.d[kind], out.d0[kind] = t[sl][bad], d[sl][bad], d0[sl][bad]
        return out

    def _candidates(self, X0, X1, T0, T1, pose0, pose1, known) -> CandidatePairs:
        """The broad phase of :meth:`check`: from scratch, or ``known``'s pairs of unchanged primitives plus a broad
        phase of the changed ones."""
        def broad(active=None):
            return step_candidates(X0, X1, self.surface, T0, T1, self.tool_surface, tool_bound=self.tool_bound,
                                   tool_pose_t0=pose0, tool_pose_t1=pose1, check=False, cache=self._cache,
                                   clearance=self.clearance, active=active)

        if known is None:
            return broad()
        ref, X1_ref = known
        moved = changed_rows(X1, np.ascontiguousarray(X1_ref, dtype=np.float64))
        if not moved.any():
            return ref
        fresh = broad(moved)
        F, E = self.surface.faces, self.surface.edges
        keep = {"vf": ~moved[ref.vf[:, 0]], "fv": ~moved[F[ref.fv[:, 1]]].any(axis=1),
                "ee": ~moved[E[ref.ee[:, 0]]].any(axis=1)}
        return CandidatePairs(**{k: np.concatenate([getattr(ref, k)[keep[k]], getattr(fresh, k)]) for k in keep})


def warm_up_clearance() -> None:
    """Compile (or load from numba's disk cache) the clearance kernels on a tiny case."""
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    faces = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]], dtype=np.int64)
    edges = np.array([[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]], dtype=np.int64)
    pair = np.zeros((1, 2), dtype=np.int64)
    clearance_pairs(X, X + 0.1, X + 2.0, X + 1.9, pair, pair, pair, faces, edges, faces, edges, CLEARANCE,
                     CLEARANCE_RATIO, MAX_ITERATIONS)
