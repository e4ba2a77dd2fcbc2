"""Deforming non-penetration filter (Tang, Manocha & Tong, I3D 2010), numpy and torch.

A vertex p and a triangle (a, b, c) move linearly over t in [0, 1]. They can only
touch at a time where the four points are coplanar, i.e. where

    f(t) = (p(t) - a(t)) . n(t),     n(t) = (b(t) - a(t)) x (c(t) - a(t))

vanishes. n(t) is quadratic with Bernstein control points n0, n-hat, n1, where
n-hat = (n0 + n1 - (v_b - v_a) x (v_c - v_a)) / 2 and v are the displacements over
the step (note the *minus*: a plus misses real collisions). f is a cubic with
Bernstein coefficients [A, (2C+F)/3, (2D+E)/3, B], A = (p0-a0).n0, B = (p1-a1).n1,
C = (p0-a0).n-hat, D = (p1-a1).n-hat, E = (p0-a0).n1, F = (p1-a1).n0. If all four
coefficients share a strict sign, f has no root on [0, 1] and the pair is culled.
An edge-edge pair (u, v) vs (k, l) uses p = l and triangle (k, u, v). The formula
itself is :func:`colgnn_core.collision.kernels.bernstein_terms`.

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

from colgnn_core.collision.kernels import (ERROR_FACTOR, UNDERFLOW_GUARD, UNIT_ROUNDOFF, bernstein_terms, keep_mask,
                                           quad_points)
from colgnn_core.errors import InputError

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
            return bernstein_terms(P0, A0, B0, C0, P1, A1, B1, C1)
    return bernstein_terms(P0, A0, B0, C0, P1, A1, B1, C1)


def keep_from_coefficients(coef, mag, unit_roundoff: float):
    """Keep mask from Bernstein coefficients: False only if all 4 share a certain sign."""
    if isinstance(coef[0], np.ndarray):
        with np.errstate(over="ignore", invalid="ignore"):
            return keep_mask(coef, mag, unit_roundoff)
    return keep_mask(coef, mag, unit_roundoff)


@njit(cache=True)
def keep_quads(X0: np.ndarray, X1: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Filter keep mask [K] for pairs given as vertex quads.

    X0, X1: [V,3] float64 positions at t0 and t1; quads [K,4] int64 rows (p, a, b, c) of the
    coplanarity cubic (vertex p, triangle a b c; an edge-edge pair (u,v | k,l) is (l, k, u, v)).
    """
    K = quads.shape[0]
    keep = np.empty(K, dtype=np.bool_)
    for k in range(K):
        coef, mag = bernstein_terms(*quad_points(X0, X1, quads, k))
        keep[k] = keep_mask(coef, mag, UNIT_ROUNDOFF)
    return keep


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
    arrs = [_soa(x, n) for x, n in zip((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1",
                                                                          "c1"))]
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
    arrs = [_soa(x, n) for x, n in zip((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1",
                                                                          "c1"))]
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
