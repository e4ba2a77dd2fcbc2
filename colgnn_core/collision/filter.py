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

The numpy path runs as a numba kernel over vertex quads (:func:`keep_quads`); the torch
path (training) evaluates the same function on tensors: one implementation of the formula.

All functions return a *keep* mask: True means "may collide, pass to the narrow
phase"; False means "proved collision-free over the step".
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from numba.extending import register_jitable

from colgnn_core.errors import InputError

ERROR_FACTOR = 32.0
UNDERFLOW_GUARD = 2.0**-1000  # absolute slack for subnormal / underflowed products
_U = float(np.finfo(np.float64).eps / 2)

__all__ = [
    "ERROR_FACTOR",
    "bernstein_coefficients",
    "filter_vertex_face",
    "filter_edge_edge",
    "filter_vertex_face_torch",
    "filter_edge_edge_torch",
    "coefficients_soa",
    "keep_from_coefficients",
    "keep_quads",
    "stack_quads",
]


@register_jitable
def _cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@register_jitable
def _abs_cross(ax, ay, az, bx, by, bz):
    # Same expression tree as _cross on absolute values: bounds its rounding error.
    return ay * bz + az * by, az * bx + ax * bz, ax * by + ay * bx


@register_jitable
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@register_jitable
def _sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@register_jitable
def _add(a, b):
    return a[0] + b[0], a[1] + b[1], a[2] + b[2]


def coefficients_soa(P0, A0, B0, C0, P1, A1, B1, C1):
    """Bernstein coefficients of f(t) and their error bounds, structure-of-arrays.

    Each argument is a [3, K] array (rows x, y, z; numpy or torch). Returns
    ``(coef, bound)``, each a list of 4 [K] arrays: b0, 3*b1, 3*b2, b3 (the
    middle ones are not divided by 3: the sign is what matters) and
    ``bound`` >= |computed - exact| for each.
    """
    if isinstance(P0, np.ndarray):
        # Overflow gives inf/NaN coefficients, which keep_from_coefficients never culls.
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            return _coefficients(P0, A0, B0, C0, P1, A1, B1, C1)
    return _coefficients(P0, A0, B0, C0, P1, A1, B1, C1)


@register_jitable
def _coefficients(P0, A0, B0, C0, P1, A1, B1, C1):
    """The one implementation of the coefficients: on [3,K] arrays/tensors (rows indexable) and,
    compiled by numba, on (x, y, z) float tuples of a single pair."""
    # Leaves: positions relative to a, at t0 and t1 (one rounding each).
    d0, e0, g0 = _sub(P0, A0), _sub(B0, A0), _sub(C0, A0)
    d1, e1, g1 = _sub(P1, A1), _sub(B1, A1), _sub(C1, A1)
    n0 = _cross(e0[0], e0[1], e0[2], g0[0], g0[1], g0[2])
    n1 = _cross(e1[0], e1[1], e1[2], g1[0], g1[1], g1[2])
    # (v_b - v_a) = (b1 - a1) - (b0 - a0), exactly in reals.
    ve, vg = _sub(e1, e0), _sub(g1, g0)
    w = _cross(ve[0], ve[1], ve[2], vg[0], vg[1], vg[2])
    nh2 = _sub(_add(n0, n1), w)  # 2 * n-hat (minus sign!)
    coef = (_dot(d0, n0), _dot(d0, nh2) + _dot(d1, n0), _dot(d1, nh2) + _dot(d0, n1), _dot(d1, n1))

    ad0 = (abs(d0[0]), abs(d0[1]), abs(d0[2]))
    ae0 = (abs(e0[0]), abs(e0[1]), abs(e0[2]))
    ag0 = (abs(g0[0]), abs(g0[1]), abs(g0[2]))
    ad1 = (abs(d1[0]), abs(d1[1]), abs(d1[2]))
    ae1 = (abs(e1[0]), abs(e1[1]), abs(e1[2]))
    ag1 = (abs(g1[0]), abs(g1[1]), abs(g1[2]))
    an0 = _abs_cross(ae0[0], ae0[1], ae0[2], ag0[0], ag0[1], ag0[2])
    an1 = _abs_cross(ae1[0], ae1[1], ae1[2], ag1[0], ag1[1], ag1[2])
    ave, avg = _add(ae1, ae0), _add(ag1, ag0)
    aw = _abs_cross(ave[0], ave[1], ave[2], avg[0], avg[1], avg[2])
    anh2 = _add(_add(an0, an1), aw)
    mag = (_dot(ad0, an0), _dot(ad0, anh2) + _dot(ad1, an0), _dot(ad1, anh2) + _dot(ad0, an1), _dot(ad1, an1))
    return coef, mag


def keep_from_coefficients(coef, mag, unit_roundoff: float):
    """Keep mask from Bernstein coefficients: False only if all 4 share a certain sign."""
    if isinstance(coef[0], np.ndarray):
        with np.errstate(over="ignore", invalid="ignore"):
            return _keep(coef, mag, unit_roundoff)
    return _keep(coef, mag, unit_roundoff)


@register_jitable
def _keep(coef, mag, unit_roundoff):
    """Arrays, tensors or (numba) scalars alike."""
    scale = ERROR_FACTOR * unit_roundoff
    bound = mag[0] * scale + UNDERFLOW_GUARD
    pos = coef[0] > bound
    neg = coef[0] < -bound
    for i in range(1, 4):
        bound = mag[i] * scale + UNDERFLOW_GUARD
        pos = pos & (coef[i] > bound)
        neg = neg & (coef[i] < -bound)
    # NaN/inf make every comparison False, so such pairs are kept. (x ^ True: "not" for bool
    # scalars, numpy arrays and torch tensors alike.)
    return (pos | neg) ^ True


@njit(cache=True)
def keep_quads(X0: np.ndarray, X1: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Filter keep mask [K] for pairs given as vertex quads.

    X0, X1: [V,3] float64 positions at t0 and t1; quads [K,4] int64 rows (p, a, b, c) of the
    coplanarity cubic (vertex p, triangle a b c; an edge-edge pair (u,v | k,l) is (l, k, u, v)).
    """
    K = quads.shape[0]
    keep = np.empty(K, dtype=np.bool_)
    for k in range(K):
        coef, mag = _coefficients(*_quad_points(X0, X1, quads, k))
        keep[k] = _keep(coef, mag, _U)
    return keep


@register_jitable
def _quad_points(X0, X1, quads, k):
    """The 8 (x, y, z) tuples (p, a, b, c at t0, then t1) of quad k."""
    p, a, b, c = quads[k, 0], quads[k, 1], quads[k, 2], quads[k, 3]
    return ((X0[p, 0], X0[p, 1], X0[p, 2]), (X0[a, 0], X0[a, 1], X0[a, 2]),
            (X0[b, 0], X0[b, 1], X0[b, 2]), (X0[c, 0], X0[c, 1], X0[c, 2]),
            (X1[p, 0], X1[p, 1], X1[p, 2]), (X1[a, 0], X1[a, 1], X1[a, 2]),
            (X1[b, 0], X1[b, 1], X1[b, 2]), (X1[c, 0], X1[c, 1], X1[c, 2]))


def stack_quads(points: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(X0 [4K,3], X1 [4K,3], quads [K,4]) from the 8 [K,3] arrays (p, a, b, c at t0, then t1)."""
    K = len(points[0])
    X0 = np.concatenate(points[:4]).astype(np.float64, copy=False)
    X1 = np.concatenate(points[4:]).astype(np.float64, copy=False)
    quads = np.arange(4 * K, dtype=np.int64).reshape(4, K).T.copy()
    return X0, X1, quads


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
    return keep_quads(*stack_quads([a.T for a in arrs]))


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
    coef, mag = coefficients_soa(*arrs)
    keep = keep_from_coefficients(coef, mag, u)
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
