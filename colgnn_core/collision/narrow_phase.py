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

from dataclasses import dataclass

import numpy as np
import torch

from colgnn_core.collision.filter import ERROR_FACTOR, UNDERFLOW_GUARD, coefficients_soa
from colgnn_core.errors import InputError

__all__ = [
    "NarrowResult",
    "vertex_face_narrow",
    "edge_edge_narrow",
    "cubic_roots_01",
    "narrow_soa",
    "bernstein_from_soa",
    "vertex_face_depth_torch",
    "edge_edge_depth_torch",
    "sdf_depth_torch",
]

BISECTION_STEPS = 14  # bracket to 6e-5 of the step ...
NEWTON_STEPS = 3  # ... then safeguarded Newton: toi to ~1e-12
INSIDE_TOL = 1e-9  # barycentric / segment-parameter slack at the root
_U = np.finfo(np.float64).eps / 2


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


def _bernstein_to_power(b0, b1, b2, b3):
    # f(t) = c0 + c1 t + c2 t^2 + c3 t^3 from true Bernstein coefficients.
    return b0, 3 * (b1 - b0), 3 * (b0 - 2 * b1 + b2), b3 - 3 * b2 + 3 * b1 - b0


def cubic_roots_01(b: np.ndarray) -> np.ndarray:
    """Roots in [0,1] of cubics given by Bernstein coefficients ``b`` [K,4].

    Returns [K,3] times, sorted, NaN where there is no root. The cubic is split at its
    critical points into up to 3 monotone pieces; each piece with a sign change is
    bisected (``BISECTION_STEPS``) and polished by safeguarded Newton steps, so a sign
    change is never missed; a double root without a sign change may be.
    """
    K = len(b)
    b0, b1, b2, b3 = (np.ascontiguousarray(b[:, i]) for i in range(4))
    c0, c1, c2, c3 = _bernstein_to_power(b0, b1, b2, b3)
    # Critical points: 3 c3 t^2 + 2 c2 t + c1 = 0, stable quadratic formula.
    qa, qb, qc = 3 * c3, 2 * c2, c1
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        q = -0.5 * (qb + np.copysign(sq, qb))
        r1 = q / qa
        r2 = qc / q
        lin = np.abs(qa) <= 1e-14 * (np.abs(qb) + np.abs(qc))
        r1 = np.where(lin, -qc / qb, r1)
        r2 = np.where(lin, np.nan, r2)
    r1 = np.where((r1 > 0) & (r1 < 1), r1, 1.0)  # no critical point -> empty trailing piece
    r2 = np.where((r2 > 0) & (r2 < 1), r2, 1.0)
    m1, m2 = np.minimum(r1, r2), np.maximum(r1, r2)
    lo = np.stack([np.zeros(K), m1, m2], axis=1)
    hi = np.stack([m1, m2, np.ones(K)], axis=1)

    def f(t, k):
        return ((c3[k] * t + c2[k]) * t + c1[k]) * t + c0[k]

    kk = np.broadcast_to(np.arange(K)[:, None], (K, 3))
    flo, fhi = f(lo, kk), f(hi, kk)
    # End points use the exact Bernstein values f(0) = b0, f(1) = b3.
    flo[:, 0] = b0
    fhi = np.where(hi == 1.0, b3[:, None], fhi)
    flo = np.where(lo == 1.0, b3[:, None], flo)
    bracket = (np.sign(flo) * np.sign(fhi) <= 0) & (hi > lo)
    bracket[:, 0] |= b0 == 0  # a root exactly at t = 0
    roots = np.full((K, 3), np.nan)
    pk, pj = np.nonzero(bracket)
    if len(pk):
        a, z = lo[pk, pj], hi[pk, pj]
        s_a = np.sign(flo[pk, pj])
        s_a = np.where(s_a == 0, -np.sign(fhi[pk, pj]), s_a)
        exact0 = flo[pk, pj] == 0
        C0, C1, C2, C3 = c0[pk], c1[pk], c2[pk], c3[pk]
        for _ in range(BISECTION_STEPS):
            m = 0.5 * (a + z)
            right = np.sign(((C3 * m + C2) * m + C1) * m + C0) == s_a  # root lies in (m, z]
            a = np.where(right, m, a)
            z = np.where(right, z, m)
        t = 0.5 * (a + z)
        for _ in range(NEWTON_STEPS):
            ft = ((C3 * t + C2) * t + C1) * t + C0
            dft = (3 * C3 * t + 2 * C2) * t + C1
            with np.errstate(invalid="ignore", divide="ignore"):
                tn = t - ft / dft
            t = np.where((tn >= a) & (tn <= z), tn, t)
        roots[pk, pj] = np.where(exact0, lo[pk, pj], t)
    return np.sort(roots, axis=1)  # NaN sorts last


def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _cross3(x, y):
    return np.stack([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]])


def _lerp(x0, x1, t):
    return x0 + (x1 - x0) * t


def _soa_inputs(args, names) -> list[np.ndarray]:
    out = []
    for a, n in zip(args, names):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{n} must be [K,3], got shape {a.shape}")
        out.append(np.ascontiguousarray(a.T))
    if len({a.shape[1] for a in out}) != 1:
        raise InputError("all narrow-phase inputs must have the same number of rows")
    return out


def bernstein_from_soa(pts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(bern [K,4] true Bernstein coefficients, flat [K] bool: all within rounding of 0) from
    the 8 coplanarity arrays (p, a, b, c at t0 then t1), each [3,K]."""
    coef, mag = coefficients_soa(*pts)
    return bernstein_from_coefficients(coef, mag)


def bernstein_from_coefficients(coef, mag) -> tuple[np.ndarray, np.ndarray]:
    """Convert filter coefficients (middle ones x3) and magnitudes to (bern [K,4], flat [K])."""
    b = np.stack([coef[0], coef[1] / 3.0, coef[2] / 3.0, coef[3]], axis=1)
    flat = np.ones(len(b), dtype=bool)
    for c, m in zip(coef, mag):
        flat &= np.abs(c) <= m * (ERROR_FACTOR * _U) + UNDERFLOW_GUARD
    return b, flat


def narrow_soa(pts: list[np.ndarray], is_ee: np.ndarray, bern: np.ndarray, flat: np.ndarray) -> NarrowResult:
    """Narrow phase on pairs in coplanarity form: ``pts`` = (p, a, b, c at t0, then at t1), each
    [3,K]; vertex-face rows are (vertex; triangle), edge-edge rows (u,v | k,l) are (l; k, u, v).
    ``is_ee`` [K] bool marks edge-edge rows; ``bern``/``flat`` from :func:`bernstein_from_soa`."""
    K = pts[0].shape[1]
    if K == 0:
        return NarrowResult.empty()
    p0, a0, b0, c0, p1, a1, b1, c1 = pts
    roots = cubic_roots_01(bern)
    hit = np.zeros(K, dtype=bool)
    toi = np.full(K, np.inf)
    degenerate = flat.copy()
    for j in range(3):  # at most 3 roots per pair: loop over root slots, vectorised over pairs
        t = roots[:, j]
        idx = np.flatnonzero(~np.isnan(t) & ~hit & ~flat)
        if len(idx) == 0:
            continue
        tt = t[idx]
        P, A, B, C = (_lerp(x0[:, idx], x1[:, idx], tt) for x0, x1 in ((p0, p1), (a0, a1), (b0, b1), (c0, c1)))
        ee = is_ee[idx]
        # vertex-face: barycentric coordinates of P in (A, B, C)
        e0, e1, e2 = B - A, C - A, P - A
        # edge-edge (u, v | k, l) = (B, C | A, P): line parameters of the closest points
        d1, d2, r = C - B, P - A, B - A
        x, y, w = np.where(ee, d1, e0), np.where(ee, d2, e1), np.where(ee, r, e2)
        xx, xy, yy, wx, wy = _dot(x, x), _dot(x, y), _dot(y, y), _dot(w, x), _dot(w, y)
        den = xx * yy - xy * xy
        bad = den <= 1e-24 * (xx * yy) + 1e-300
        with np.errstate(invalid="ignore", divide="ignore"):
            # vf: beta, gamma; ee: s along (u,v) = (xy*wy - wx*yy)/den with w = u - k sign flipped below
            u1 = (yy * wx - xy * wy) / den
            u2 = (xx * wy - xy * wx) / den
        # For ee, r = u - k, so the closest-point parameters are s = -u1 and w = u2.
        tol = INSIDE_TOL
        inside_vf = (u1 >= -tol) & (u2 >= -tol) & (u1 + u2 <= 1 + tol)
        s_ee = -u1
        inside_ee = (s_ee >= -tol) & (s_ee <= 1 + tol) & (u2 >= -tol) & (u2 <= 1 + tol)
        inside = np.where(ee, inside_ee, inside_vf)
        degenerate[idx[bad]] = True
        ok = inside & ~bad
        hit[idx[ok]] = True
        toi[idx[ok]] = tt[ok]
    depth = np.zeros(K)
    if hit.any():
        h = np.flatnonzero(hit)
        depth[h] = _depth_soa([x[:, h] for x in pts], is_ee[h], bern[h])
    return NarrowResult(hit=hit, toi=toi, depth=depth, degenerate=degenerate)


def _start_side(b: np.ndarray) -> np.ndarray:
    # Side at t0 = sign f(0); if f(0) == 0 the pair "starts" opposite to where it ends.
    s = np.sign(b[:, 0])
    return np.where(s == 0, -np.sign(b[:, 3]), s)


def _depth_soa(pts, is_ee, bern) -> np.ndarray:
    """Wrong-side depth at t1 (m): plane distance (vf) or line distance (ee), 0 if on the start side."""
    p1, a1, b1, c1 = pts[4], pts[5], pts[6], pts[7]
    # vf: n = (b-a) x (c-a), f = (p-a).n.  ee (u,v|k,l) = (b,c|a,p): n = (v-u) x (l-k), f = -(k-u).n,
    # which has the sign of the coplanarity cubic at t1.
    n_vf = _cross3(b1 - a1, c1 - a1)
    n_ee = _cross3(c1 - b1, p1 - a1)
    n = np.where(is_ee, n_ee, n_vf)
    f1 = np.where(is_ee, -_dot(a1 - b1, n_ee), _dot(p1 - a1, n_vf))
    nn = np.sqrt(_dot(n, n))
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(nn > 0, -_start_side(bern) * f1 / nn, 0.0)
    return np.maximum(d, 0.0)


def vertex_face_narrow(p0, a0, b0, c0, p1, a1, b1, c1) -> NarrowResult:
    """Crossing, toi and plane depth at t1 for K vertex-triangle pairs ([K,3] positions, m)."""
    pts = _soa_inputs((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1", "c1"))
    bern, flat = bernstein_from_soa(pts)
    return narrow_soa(pts, np.zeros(pts[0].shape[1], dtype=bool), bern, flat)


def edge_edge_narrow(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1) -> NarrowResult:
    """Crossing, toi and line depth at t1 for K edge-edge pairs (ipctk argument order)."""
    u0, v0, k0, l0, u1, v1, k1, l1 = _soa_inputs(
        (ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1),
        ("ea0_t0", "ea1_t0", "eb0_t0", "eb1_t0", "ea0_t1", "ea1_t1", "eb0_t1", "eb1_t1"))
    pts = [l0, k0, u0, v0, l1, k1, u1, v1]
    bern, flat = bernstein_from_soa(pts)
    return narrow_soa(pts, np.ones(pts[0].shape[1], dtype=bool), bern, flat)


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
