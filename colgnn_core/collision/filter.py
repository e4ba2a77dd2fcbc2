"""Deforming non-penetration filter (Tang, Manocha & Tong, I3D 2010), numpy and torch.

A vertex p and a triangle (a, b, c) move linearly over t in [0, 1]. They can only
touch at a time where the four points are coplanar, i.e. where

    f(t) = (p(t) - a(t)) . n(t),     n(t) = (b(t) - a(t)) x (c(t) - a(t))

vanishes. f is a cubic with Bernstein coefficients [A, (2C+F)/3, (2D+E)/3, B]
(see ``../shared/design/IPC-AND-CCD-NOTES.md``; note the *minus* in n-hat). If
all four coefficients share a strict sign, f has no root on [0, 1] and the pair
is culled. An edge-edge pair (u, v) vs (k, l) uses p = l and triangle (k, u, v).

Floating point: every coefficient comes with a forward error bound obtained by
evaluating the same expression tree on absolute values (``|x|`` leaves,
``|a|*|b|`` products, ``|a|+|b|`` sums) and scaling it by ``ERROR_FACTOR * u``.
The longest chain of rounded operations is 10 (leaf difference, displacement
difference, 2 in the cross product, 2 in n-hat, 3 in the dot product, the final
sum); ``ERROR_FACTOR = 32`` leaves a 3x margin over gamma_10. A pair is culled
only when every coefficient exceeds its bound with the same sign, so rounding
can never cull a pair whose exact f has a root. Overflow (inf/NaN) and
underflow (``UNDERFLOW_GUARD``) make the test keep the pair.

All functions return a *keep* mask: True means "may collide, pass to the narrow
phase"; False means "proved collision-free over the step".
"""

from __future__ import annotations

import numpy as np
import torch

from colgnn_core.errors import InputError

ERROR_FACTOR = 32.0
UNDERFLOW_GUARD = 2.0**-1000  # absolute slack for subnormal / underflowed products

__all__ = [
    "ERROR_FACTOR",
    "bernstein_coefficients",
    "filter_vertex_face",
    "filter_edge_edge",
    "filter_vertex_face_torch",
    "filter_edge_edge_torch",
    "coefficients_soa",
    "keep_from_coefficients",
]


def _cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def _abs_cross(ax, ay, az, bx, by, bz):
    # Same expression tree as _cross on absolute values: bounds its rounding error.
    return ay * bz + az * by, az * bx + ax * bz, ax * by + ay * bx


def coefficients_soa(P0, A0, B0, C0, P1, A1, B1, C1, xp=np):
    """Bernstein coefficients of f(t) and their error bounds, structure-of-arrays.

    Each argument is a [3, K] array (rows x, y, z; numpy or torch). Returns
    ``(coef, bound)``, each a list of 4 [K] arrays: b0, 3*b1, 3*b2, b3 (the
    middle ones are not divided by 3: the sign is what matters) and
    ``bound`` >= |computed - exact| for each. ``xp`` is ``np`` or ``torch``.
    """
    if xp is np:
        # Overflow gives inf/NaN coefficients, which keep_from_coefficients never culls.
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            return _coefficients_soa(P0, A0, B0, C0, P1, A1, B1, C1, xp)
    return _coefficients_soa(P0, A0, B0, C0, P1, A1, B1, C1, xp)


def _coefficients_soa(P0, A0, B0, C0, P1, A1, B1, C1, xp):
    absf = xp.abs
    # Leaves: positions relative to a, at t0 and t1 (one rounding each).
    d0 = [P0[i] - A0[i] for i in range(3)]
    e0 = [B0[i] - A0[i] for i in range(3)]
    g0 = [C0[i] - A0[i] for i in range(3)]
    d1 = [P1[i] - A1[i] for i in range(3)]
    e1 = [B1[i] - A1[i] for i in range(3)]
    g1 = [C1[i] - A1[i] for i in range(3)]
    n0 = _cross(*e0, *g0)
    n1 = _cross(*e1, *g1)
    # (v_b - v_a) = (b1 - a1) - (b0 - a0), exactly in reals.
    ve = [e1[i] - e0[i] for i in range(3)]
    vg = [g1[i] - g0[i] for i in range(3)]
    w = _cross(*ve, *vg)
    nh2 = [n0[i] + n1[i] - w[i] for i in range(3)]  # 2 * n-hat (minus sign!)

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    A = dot(d0, n0)
    B = dot(d1, n1)
    C2 = dot(d0, nh2)
    D2 = dot(d1, nh2)
    E = dot(d0, n1)
    F = dot(d1, n0)
    coef = [A, C2 + F, D2 + E, B]

    ad0 = [absf(x) for x in d0]
    ae0 = [absf(x) for x in e0]
    ag0 = [absf(x) for x in g0]
    ad1 = [absf(x) for x in d1]
    ae1 = [absf(x) for x in e1]
    ag1 = [absf(x) for x in g1]
    an0 = _abs_cross(*ae0, *ag0)
    an1 = _abs_cross(*ae1, *ag1)
    ave = [ae1[i] + ae0[i] for i in range(3)]
    avg = [ag1[i] + ag0[i] for i in range(3)]
    aw = _abs_cross(*ave, *avg)
    anh2 = [an0[i] + an1[i] + aw[i] for i in range(3)]
    aA = dot(ad0, an0)
    aB = dot(ad1, an1)
    aC2 = dot(ad0, anh2)
    aD2 = dot(ad1, anh2)
    aE = dot(ad0, an1)
    aF = dot(ad1, an0)
    mag = [aA, aC2 + aF, aD2 + aE, aB]
    return coef, mag


def keep_from_coefficients(coef, mag, unit_roundoff: float, xp=np):
    """Keep mask from Bernstein coefficients: False only if all 4 share a certain sign."""
    if xp is np:
        with np.errstate(over="ignore", invalid="ignore"):
            return _keep(coef, mag, unit_roundoff)
    return _keep(coef, mag, unit_roundoff)


def _keep(coef, mag, unit_roundoff: float):
    pos = None
    neg = None
    for c, m in zip(coef, mag):
        bound = m * (ERROR_FACTOR * unit_roundoff) + UNDERFLOW_GUARD
        p = c > bound
        n = c < -bound
        pos = p if pos is None else (pos & p)
        neg = n if neg is None else (neg & n)
    # NaN/inf make every comparison False, so such pairs are kept.
    return ~(pos | neg)


def _soa(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must be [K,3], got shape {a.shape}")
    return np.ascontiguousarray(a.T)


def _check_same_k(arrays) -> None:
    ks = {a.shape[1] for a in arrays}
    if len(ks) != 1:
        raise InputError(f"all filter inputs must have the same number of rows, got {sorted(ks)}")


def bernstein_coefficients(p0, a0, b0, c0, p1, a1, b1, c1) -> tuple[np.ndarray, np.ndarray]:
    """Bernstein coefficients [K,4] of f(t) for vertex-face pairs, and their error bounds [K,4].

    Inputs are [K,3] positions (any length unit). Coefficients are b0, b1, b2, b3 of
    f(t) = sum_i b_i B_i(t), f in length^3.
    """
    arrs = [_soa(x, n) for x, n in zip((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1", "c1"))]
    _check_same_k(arrs)
    coef, mag = coefficients_soa(*arrs)
    c = np.stack(coef, axis=1)
    m = np.stack(mag, axis=1) * (ERROR_FACTOR * np.finfo(np.float64).eps / 2) + UNDERFLOW_GUARD
    # Dividing by 3 adds one rounding, covered by the margin in ERROR_FACTOR.
    c[:, 1:3] /= 3.0
    m[:, 1:3] /= 3.0
    return c, m


def filter_vertex_face(p0, a0, b0, c0, p1, a1, b1, c1) -> np.ndarray:
    """Keep mask [K] bool for vertex p vs triangle (a, b, c) moving linearly t0 -> t1.

    All inputs [K,3] float64. False = certainly no contact during the step.
    """
    arrs = [_soa(x, n) for x, n in zip((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1", "c1"))]
    _check_same_k(arrs)
    coef, mag = coefficients_soa(*arrs)
    return keep_from_coefficients(coef, mag, np.finfo(np.float64).eps / 2)


def filter_edge_edge(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1) -> np.ndarray:
    """Keep mask [K] bool for edge (ea0, ea1) vs edge (eb0, eb1) (ipctk argument order).

    Uses p = eb1 and the triangle (eb0, ea0, ea1).
    """
    return filter_vertex_face(eb1_t0, eb0_t0, ea0_t0, ea1_t0, eb1_t1, eb0_t1, ea0_t1, ea1_t1)


def _torch_soa(x: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise InputError(f"{name} must be a torch.Tensor")
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"{name} must be [K,3], got shape {tuple(x.shape)}")
    if not x.is_floating_point():
        raise InputError(f"{name} must be a floating-point tensor")
    return x.detach().T


def filter_vertex_face_torch(p0, a0, b0, c0, p1, a1, b1, c1) -> torch.Tensor:
    """Torch version of :func:`filter_vertex_face`: [K,3] tensors -> [K] bool keep mask.

    The unit roundoff follows the dtype (float32 inputs get the float32 bound), so the
    test stays conservative in either precision. No gradient flows through a mask.
    """
    names = ("p0", "a0", "b0", "c0", "p1", "a1", "b1", "c1")
    arrs = [_torch_soa(x, n) for x, n in zip((p0, a0, b0, c0, p1, a1, b1, c1), names)]
    _check_same_k(arrs)
    dtype = torch.promote_types(arrs[0].dtype, torch.float32)
    for a in arrs[1:]:
        dtype = torch.promote_types(dtype, a.dtype)
    arrs = [a.to(dtype) for a in arrs]
    u = float(torch.finfo(dtype).eps) / 2
    coef, mag = coefficients_soa(*arrs, xp=torch)
    keep = keep_from_coefficients(coef, mag, u, xp=torch)
    if dtype != torch.float64:
        # float32 underflows long before float64: never cull a pair with a tiny bound.
        tiny = float(torch.finfo(dtype).tiny) * 1e6
        small = torch.zeros_like(keep)
        for m in mag:
            small |= m < tiny
        keep = keep | small
    return keep


def filter_edge_edge_torch(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1) -> torch.Tensor:
    """Torch version of :func:`filter_edge_edge`."""
    return filter_vertex_face_torch(eb1_t0, eb0_t0, ea0_t0, ea1_t0, eb1_t1, eb0_t1, ea0_t1, ea1_t1)
