"""Narrow phase for the pairs the filter keeps: crossing test, time of impact, depth at t+1.

Vertex-face: the coplanarity cubic f(t) (see :mod:`.filter`) is split at its
critical points into monotone pieces; each piece whose end values differ in sign
is bisected to a root, and at each root (earliest first) the vertex is tested
against the triangle with barycentric coordinates. Edge-edge: the same cubic for
the four edge end points; at a root the two segments must intersect (line
parameters in [0, 1]).

The depth on the wrong side at t+1 is

* vertex-face: the distance of the vertex from the triangle's *plane* at t+1,
  counted on the side opposite to where it started;
* edge-edge: the distance between the two *lines* at t+1, likewise signed.

Both are 0 when the primitive ended on its starting side. They are polynomials
divided by a norm, so the torch versions are differentiable; :func:`sdf_depth_torch`
gives the SDF depth max(0, -sdf) of points inside the tool.

This narrow phase is fast and accurate but not exact: grazing contacts (f touching
0 without changing sign) and pairs coplanar over the whole step are flagged
``degenerate`` rather than resolved. Use :mod:`.exact` where exactness matters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from numba import njit
from numba.extending import register_jitable

from colgnn_core.collision.exact import pair_arrays
from colgnn_core.collision.filter import stack_quads
from colgnn_core.collision.kernels import (ERROR_FACTOR, UNDERFLOW_GUARD, UNIT_ROUNDOFF, bernstein_terms, keep_mask,
                                           quad_points, vec_cross, vec_dot, vec_sub)
from colgnn_core.errors import InputError

__all__ = [
    "NarrowResult",
    "vertex_face_narrow",
    "edge_edge_narrow",
    "cubic_roots_01",
    "filter_narrow_quads",
    "depth_quads",
    "vertex_face_depth_torch",
    "edge_edge_depth_torch",
    "sdf_depth_torch",
]

BISECTION_STEPS = 14  # bracket to 6e-5 of the step ...
NEWTON_STEPS = 3  # ... then safeguarded Newton: toi to ~1e-12
INSIDE_TOL = 1e-9  # barycentric / segment-parameter slack at the root


@dataclass
class NarrowResult:
    """Per-pair results, each [K]: hit (crossing in [0,1]), toi (inf if none), depth (m, >= 0, 0 where
    not hit), degenerate (coplanar over the whole step or a degenerate triangle / parallel edges at
    the root; not resolved by this narrow phase)."""

    hit: np.ndarray
    toi: np.ndarray
    depth: np.ndarray
    degenerate: np.ndarray

    @classmethod
    def empty(cls) -> "NarrowResult":
        return cls(np.zeros(0, bool), np.zeros(0), np.zeros(0), np.zeros(0, bool))


@register_jitable
def _sign(x):
    # np.sign for one float (NaN stays NaN).
    if x > 0:
        return 1.0
    if x < 0:
        return -1.0
    return x * 0.0


@register_jitable
def _cubic(c0, c1, c2, c3, t):
    return ((c3 * t + c2) * t + c1) * t + c0


@register_jitable
def _piece_root(c0, c1, c2, c3, lo, hi, flo, fhi):
    """Root in a monotone piece [lo, hi] whose end values ``flo``, ``fhi`` bracket 0: bisection, then
    safeguarded Newton (never leaves the bracket)."""
    if flo == 0:
        return lo
    s_a = _sign(flo)
    a, z = lo, hi
    for _ in range(BISECTION_STEPS):
        m = 0.5 * (a + z)
        if _sign(_cubic(c0, c1, c2, c3, m)) == s_a:  # root lies in (m, z]
            a = m
        else:
            z = m
    t = 0.5 * (a + z)
    for _ in range(NEWTON_STEPS):
        dft = (3 * c3 * t + 2 * c2) * t + c1
        if dft != 0:
            tn = t - _cubic(c0, c1, c2, c3, t) / dft
            if a <= tn <= z:
                t = tn
    return t


@register_jitable
def _critical_points(c1, c2, c3):
    """Critical points of the cubic inside (0, 1), as (m1 <= m2); 1.0 stands for "none"."""
    qa, qb, qc = 3 * c3, 2 * c2, c1
    r1 = r2 = np.nan
    if abs(qa) <= 1e-14 * (abs(qb) + abs(qc)):
        if qb != 0:
            r1 = -qc / qb
    else:
        disc = qb * qb - 4 * qa * qc
        if disc >= 0:
            # Stable quadratic formula.
            q = -0.5 * (qb + math.copysign(math.sqrt(disc), qb))
            r1 = q / qa
            if q != 0:
                r2 = qc / q
    r1 = r1 if 0 < r1 < 1 else 1.0
    r2 = r2 if 0 < r2 < 1 else 1.0
    return min(r1, r2), max(r1, r2)


@register_jitable
def _cubic_roots(b0, b1, b2, b3):
    """Roots in [0,1] of one cubic with Bernstein coefficients b0..b3: sorted (r0, r1, r2), NaN last."""
    c0, c1, c2, c3 = b0, 3 * (b1 - b0), 3 * (b0 - 2 * b1 + b2), b3 - 3 * b2 + 3 * b1 - b0
    m1, m2 = _critical_points(c1, c2, c3)
    r0 = _piece(c0, c1, c2, c3, b0, b3, 0.0, m1)
    r1 = _piece(c0, c1, c2, c3, b0, b3, m1, m2)
    r2 = _piece(c0, c1, c2, c3, b0, b3, m2, 1.0)
    # Pieces are ordered, so the roots are: only move the NaNs last.
    if np.isnan(r1):
        r1, r2 = r2, r1
    if np.isnan(r0):
        r0, r1, r2 = r1, r2, r0
    return r0, r1, r2


@register_jitable
def _piece(c0, c1, c2, c3, b0, b3, lo, hi):
    """Root of the monotone piece [lo, hi], or NaN when its end values do not bracket 0."""
    # End points use the exact Bernstein values f(0) = b0, f(1) = b3.
    flo = b0 if lo == 0.0 else (b3 if lo == 1.0 else _cubic(c0, c1, c2, c3, lo))
    fhi = b3 if hi == 1.0 else _cubic(c0, c1, c2, c3, hi)
    if (_sign(flo) * _sign(fhi) <= 0 and hi > lo) or (lo == 0.0 and b0 == 0):
        return _piece_root(c0, c1, c2, c3, lo, hi, flo, fhi)
    return np.nan


@njit(cache=True)
def _cubic_roots_kernel(b: np.ndarray) -> np.ndarray:
    out = np.empty((b.shape[0], 3))
    for k in range(b.shape[0]):
        out[k, 0], out[k, 1], out[k, 2] = _cubic_roots(b[k, 0], b[k, 1], b[k, 2], b[k, 3])
    return out


def cubic_roots_01(b: np.ndarray) -> np.ndarray:
    """Roots in [0,1] of cubics given by Bernstein coefficients ``b`` [K,4].

    Returns [K,3] times, sorted, NaN where there is no root. The cubic is split at its
    critical points into up to 3 monotone pieces; each piece with a sign change is
    bisected (``BISECTION_STEPS``) and polished by safeguarded Newton steps, so a sign
    change is never missed; a double root without a sign change may be.
    """
    b = np.asarray(b, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 4:
        raise InputError(f"Bernstein coefficients must be [K,4], got shape {b.shape}")
    return _cubic_roots_kernel(np.ascontiguousarray(b))


@register_jitable
def _lerp3(x0, x1, t):
    return x0[0] + (x1[0] - x0[0]) * t, x0[1] + (x1[1] - x0[1]) * t, x0[2] + (x1[2] - x0[2]) * t


@register_jitable
def _inside_at(P, A, B, C, is_ee):
    """(inside, degenerate) at a coplanar instant. Vertex-face: barycentric coordinates of P in
    (A, B, C). Edge-edge (u, v | k, l) = (B, C | A, P): line parameters of the closest points."""
    if is_ee:
        x, y, w = vec_sub(C, B), vec_sub(P, A), vec_sub(B, A)
    else:
        x, y, w = vec_sub(B, A), vec_sub(C, A), vec_sub(P, A)
    xx, xy, yy, wx, wy = vec_dot(x, x), vec_dot(x, y), vec_dot(y, y), vec_dot(w, x), vec_dot(w, y)
    den = xx * yy - xy * xy
    # Parallel (sin^2 of the angle below 1e-13): the closest points are undefined. den carries a rounding error of a
    # few ulp of xx * yy, so a tighter bound let two exactly parallel edges (a grid edge under a tool edge, 12 mm
    # apart) through with garbage parameters, as a crossing no push could remove.
    if not den > 1e-13 * (xx * yy) + 1e-300:
        return False, True
    u1 = (yy * wx - xy * wy) / den
    u2 = (xx * wy - xy * wx) / den
    tol = INSIDE_TOL
    if is_ee:
        # w = u - k, so the closest-point parameters are s = -u1 on (u, v) and u2 on (k, l).
        s = -u1
        return (s >= -tol) and (s <= 1 + tol) and (u2 >= -tol) and (u2 <= 1 + tol), False
    return (u1 >= -tol) and (u2 >= -tol) and (u1 + u2 <= 1 + tol), False


@register_jitable
def _depth_at_t1(p1, a1, b1, c1, is_ee, b0, b3):
    """Wrong-side depth at t1 (m): plane distance (vf) or line distance (ee), 0 if on the start side.

    vf: n = (b-a) x (c-a), f = (p-a).n. ee (u,v|k,l) = (b,c|a,p): n = (v-u) x (l-k), f = -(k-u).n,
    which has the sign of the coplanarity cubic at t1. Side at t0 = sign f(0); if f(0) == 0 the
    pair "starts" opposite to where it ends.
    """
    if is_ee:
        x, y = vec_sub(c1, b1), vec_sub(p1, a1)
    else:
        x, y = vec_sub(b1, a1), vec_sub(c1, a1)
    n = vec_cross(x[0], x[1], x[2], y[0], y[1], y[2])
    f1 = -vec_dot(vec_sub(a1, b1), n) if is_ee else vec_dot(vec_sub(p1, a1), n)
    nn = np.sqrt(vec_dot(n, n))
    side = _sign(b0)
    if side == 0:
        side = -_sign(b3)
    if not nn > 0:
        return 0.0
    return max(-side * f1 / nn, 0.0)


@register_jitable
def _narrow_one(pts, is_ee, coef, mag):
    """(hit, toi, depth, degenerate) of one filtered pair from its 8 points and filter coefficients."""
    flat = True
    for i in range(4):
        flat = flat and abs(coef[i]) <= mag[i] * (ERROR_FACTOR * UNIT_ROUNDOFF) + UNDERFLOW_GUARD
    if flat:
        return False, np.inf, 0.0, True
    b0, b3 = coef[0], coef[3]
    roots = _cubic_roots(b0, coef[1] / 3.0, coef[2] / 3.0, b3)
    degenerate = False
    for j in range(3):
        t = roots[j]
        if np.isnan(t):
            break
        P, A = _lerp3(pts[0], pts[4], t), _lerp3(pts[1], pts[5], t)
        B, C = _lerp3(pts[2], pts[6], t), _lerp3(pts[3], pts[7], t)
        inside, bad = _inside_at(P, A, B, C, is_ee)
        degenerate = degenerate or bad
        if inside:
            return True, t, _depth_at_t1(pts[4], pts[5], pts[6], pts[7], is_ee, b0, b3), degenerate
    return False, np.inf, 0.0, degenerate


@njit(cache=True)
def filter_narrow_quads(X0, X1, quads, is_ee, narrow):
    """Filter, then (if ``narrow``) narrow phase, for pairs given as vertex quads.

    X0, X1 [V,3] float64 positions (m) at t0 and t1; quads [K,4] int64 (p, a, b, c), see
    :func:`colgnn_core.collision.filter.keep_quads`; is_ee [K] bool marks edge-edge rows.
    Returns keep [K] bool and hit, toi, depth, degenerate [K] (hit False, toi inf, depth 0,
    degenerate False where not kept or not ``narrow``).
    """
    K = quads.shape[0]
    keep = np.zeros(K, dtype=np.bool_)
    hit = np.zeros(K, dtype=np.bool_)
    degenerate = np.zeros(K, dtype=np.bool_)
    toi = np.full(K, np.inf)
    depth = np.zeros(K)
    for k in range(K):
        pts = quad_points(X0, X1, quads, k)
        coef, mag = bernstein_terms(*pts)
        keep[k] = keep_mask(coef, mag, UNIT_ROUNDOFF)
        if keep[k] and narrow:
            hit[k], toi[k], depth[k], degenerate[k] = _narrow_one(pts, is_ee[k], coef, mag)
    return keep, hit, toi, depth, degenerate


@njit(cache=True)
def depth_quads(X0, X1, quads, is_ee):
    """Wrong-side depth at t1 [K] (m) of pairs known to cross (e.g. by exact CCD), as vertex quads
    (see :func:`filter_narrow_quads`): plane distance (vf) or line distance (ee)."""
    K = quads.shape[0]
    depth = np.zeros(K)
    for k in range(K):
        pts = quad_points(X0, X1, quads, k)
        coef, _ = bernstein_terms(*pts)
        depth[k] = _depth_at_t1(pts[4], pts[5], pts[6], pts[7], is_ee[k], coef[0], coef[3])
    return depth


def _narrow_points(points: list[np.ndarray], is_ee: bool) -> NarrowResult:
    X0, X1, quads = stack_quads(points)
    flags = np.full(len(quads), is_ee, dtype=bool)
    _, hit, toi, depth, degenerate = filter_narrow_quads(X0, X1, quads, flags, True)
    return NarrowResult(hit=hit, toi=toi, depth=depth, degenerate=degenerate)


def vertex_face_narrow(p0, a0, b0, c0, p1, a1, b1, c1) -> NarrowResult:
    """Crossing, toi and plane depth at t1 for K vertex-triangle pairs ([K,3] positions, m)."""
    pts = pair_arrays((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1", "c1"))
    return _narrow_points(pts, False)


def edge_edge_narrow(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1) -> NarrowResult:
    """Crossing, toi and line depth at t1 for K edge-edge pairs (ipctk argument order)."""
    u0, v0, k0, l0, u1, v1, k1, l1 = pair_arrays(
        (ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1),
        ("ea0_t0", "ea1_t0", "eb0_t0", "eb1_t0", "ea0_t1", "ea1_t1", "eb0_t1", "eb1_t1"))
    return _narrow_points([l0, k0, u0, v0, l1, k1, u1, v1], True)


def _torch_start_side(f0: torch.Tensor, f1: torch.Tensor) -> torch.Tensor:
    s = torch.sign(f0)
    return torch.where(s == 0, -torch.sign(f1), s).detach()


def vertex_face_depth_torch(p0, a0, b0, c0, p1, a1, b1, c1, eps: float = 1e-30) -> torch.Tensor:
    """Differentiable depth [K] (m, >= 0) of p1 behind the plane of (a1, b1, c1), on the side opposite
    to where p0 started relative to (a0, b0, c0). [K,3] tensors; gradients flow to the t1 positions."""
    n0 = torch.linalg.cross(b0 - a0, c0 - a0, dim=-1)
    f0 = ((p0 - a0) * n0).sum(-1)
    n1 = torch.linalg.cross(b1 - a1, c1 - a1, dim=-1)
    f1 = ((p1 - a1) * n1).sum(-1)
    side = _torch_start_side(f0, f1)
    nn = torch.sqrt((n1 * n1).sum(-1) + eps)
    return torch.relu(-side * f1 / nn)


def edge_edge_depth_torch(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1,
                          eps: float = 1e-30) -> torch.Tensor:
    """Differentiable depth [K] (m, >= 0): distance between the edge lines at t1 when the edges ended
    on the opposite side of each other from where they started."""
    n0 = torch.linalg.cross(ea1_t0 - ea0_t0, eb1_t0 - eb0_t0, dim=-1)
    f0 = -((eb0_t0 - ea0_t0) * n0).sum(-1)
    n1 = torch.linalg.cross(ea1_t1 - ea0_t1, eb1_t1 - eb0_t1, dim=-1)
    f1 = -((eb0_t1 - ea0_t1) * n1).sum(-1)
    side = _torch_start_side(f0, f1)
    nn = torch.sqrt((n1 * n1).sum(-1) + eps)
    return torch.relu(-side * f1 / nn)


def sdf_depth_torch(tool, points: torch.Tensor, pose) -> torch.Tensor:
    """Differentiable SDF depth max(0, -sdf) [N] (m) of world points [N,3] inside the tool at ``pose``."""
    if not isinstance(points, torch.Tensor) or points.ndim != 2 or points.shape[-1] != 3:
        raise InputError("points must be a [N,3] torch tensor")
    pose_t = pose if isinstance(pose, torch.Tensor) else torch.as_tensor(np.asarray(pose), dtype=points.dtype)
    return torch.relu(-tool.sdf_torch(points, pose_t))
