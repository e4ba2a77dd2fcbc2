"""Shared generators for the collision tests: random and adversarial CCD pairs, exact arithmetic.

Every generator returns a [K,8,3] float64 array in ipctk argument order (vertex-face:
p0, a0, b0, c0, p1, a1, b1, c1; edge-edge: ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ...).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np


def _from_contact(rng, point_t, others_t, t_star, speed):
    """Positions at t0/t1 of points moving linearly through given positions at time t_star."""
    pts = np.concatenate([point_t[:, None], others_t], axis=1)  # [K,4,3]
    v = rng.normal(size=pts.shape) * speed[:, None, None]
    x0 = pts - t_star[:, None, None] * v
    x1 = pts + (1 - t_star)[:, None, None] * v
    return np.concatenate([x0, x1], axis=1)


def colliding_vf(rng, k: int) -> np.ndarray:
    """Vertex-face pairs that touch at a random time (point inside the triangle at t*)."""
    tri = rng.normal(size=(k, 3, 3))
    w = rng.dirichlet([1, 1, 1], size=k)
    p = np.einsum("ki,kij->kj", w, tri)
    return _from_contact(rng, p, tri, rng.uniform(0, 1, k), rng.uniform(0.1, 3, k))


def colliding_ee(rng, k: int) -> np.ndarray:
    """Edge-edge pairs whose segments intersect at a random time."""
    c = rng.normal(size=(k, 3))
    da, db = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
    sa, sb = rng.uniform(0, 1, (k, 1)), rng.uniform(0, 1, (k, 1))
    ea = np.stack([c - sa * da, c + (1 - sa) * da], axis=1)
    eb = np.stack([c - sb * db, c + (1 - sb) * db], axis=1)
    others = np.concatenate([ea[:, 1:], eb], axis=1)  # ea1, eb0, eb1
    return _from_contact(rng, ea[:, 0], others, rng.uniform(0, 1, k), rng.uniform(0.1, 3, k))


def random_pairs(rng, k: int) -> np.ndarray:
    """Unstructured pairs: points in a unit box, displacements of random size."""
    x0 = rng.uniform(-1, 1, size=(k, 4, 3))
    x1 = x0 + rng.normal(size=(k, 4, 3)) * rng.choice([0.0, 0.01, 0.3, 2.0], size=(k, 1, 1))
    return np.concatenate([x0, x1], axis=1)


def near_coplanar(rng, k: int) -> np.ndarray:
    """All 8 points in (or within eps of) one plane through the origin, with sliding motion."""
    q = np.concatenate([random_pairs(rng, k)[:, :, :2], np.zeros((k, 8, 1))], axis=2)
    eps = rng.choice([0.0, 1e-15, 1e-12, 1e-9, 1e-6], size=(k, 1, 1))
    q[:, :, 2] = rng.normal(size=(k, 8)) * eps[:, :, 0]
    R = np.linalg.qr(rng.normal(size=(k, 3, 3)))[0]
    return np.einsum("kij,knj->kni", R, q)


def parallel_edges(rng, k: int) -> np.ndarray:
    """Edge b = edge a shifted (optionally slightly rotated), moving in parallel or towards each other."""
    a0 = rng.normal(size=(k, 2, 3))
    shift = rng.normal(size=(k, 1, 3)) * rng.choice([1.0, 1e-3, 1e-8], size=(k, 1, 1))
    b0 = a0 + shift + rng.normal(size=(k, 2, 3)) * rng.choice([0.0, 1e-12, 1e-7], size=(k, 1, 1))
    v = rng.normal(size=(k, 1, 3)) * rng.choice([0.0, 0.5], size=(k, 1, 1))
    a1 = a0 + v
    b1 = b0 + v - shift * rng.choice([0.0, 0.5, 1.0, 2.0], size=(k, 1, 1))
    return np.concatenate([a0, b0, a1, b1], axis=1)


def zero_motion(rng, k: int) -> np.ndarray:
    """t1 == t0: static pairs (separated, touching and coplanar)."""
    x0 = random_pairs(rng, k)[:, :4]
    touch = rng.uniform(size=k) < 0.3
    w = rng.dirichlet([1, 1, 1], size=k)
    x0[touch, 0] = np.einsum("ki,kij->kj", w[touch], x0[touch, 1:])
    return np.concatenate([x0, x0], axis=1)


def degenerate_triangles(rng, k: int) -> np.ndarray:
    """Triangles with repeated or collinear vertices (n == 0), or edges of zero length."""
    x = random_pairs(rng, k)
    mode = rng.integers(0, 3, size=k)
    x[mode == 0, 2] = x[mode == 0, 1]
    x[mode == 0, 6] = x[mode == 0, 5]
    s = rng.uniform(-1, 2, size=(k, 1))
    col = x[:, 1] + s * (x[:, 2] - x[:, 1])
    x[mode == 1, 3] = col[mode == 1]
    x[mode == 1, 7] = x[mode == 1, 5] + s[mode == 1] * (x[mode == 1, 6] - x[mode == 1, 5])
    x[mode == 2, 1] = x[mode == 2, 0]
    return x


def rescale(rng, q: np.ndarray) -> np.ndarray:
    """Scale by 1e-30 .. 1e30 and translate far from the origin (cancellation)."""
    k = len(q)
    s = 10.0 ** rng.choice([-30, -12, -6, 0, 6, 12, 30], size=(k, 1, 1))
    off = rng.normal(size=(k, 1, 3)) * rng.choice([0.0, 1.0, 1e3, 1e6], size=(k, 1, 1))
    return (q + off) * s


def exact_bernstein_signs(q: np.ndarray) -> np.ndarray:
    """Signs [K,4] of the exact Bernstein coefficients of the coplanarity cubic (vertex-face order),
    computed in rational arithmetic from the float64 inputs."""
    out = np.zeros((len(q), 4), dtype=np.int64)
    for i, row in enumerate(q):
        P = [[Fraction(float(c)) for c in pt] for pt in row]
        p0, a0, b0, c0, p1, a1, b1, c1 = P

        def sub(x, y):
            return [x[j] - y[j] for j in range(3)]

        def cross(x, y):
            return [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]]

        def dot(x, y):
            return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]

        d0, e0, g0 = sub(p0, a0), sub(b0, a0), sub(c0, a0)
        d1, e1, g1 = sub(p1, a1), sub(b1, a1), sub(c1, a1)
        n0, n1 = cross(e0, g0), cross(e1, g1)
        w = cross(sub(e1, e0), sub(g1, g0))
        nh = [(n0[j] + n1[j] - w[j]) / 2 for j in range(3)]
        A, B = dot(d0, n0), dot(d1, n1)
        C, D, E, F = dot(d0, nh), dot(d1, nh), dot(d0, n1), dot(d1, n0)
        for j, v in enumerate((A, 2 * C + F, 2 * D + E, B)):
            out[i, j] = (v > 0) - (v < 0)
    return out


def ee_as_vf(q: np.ndarray) -> np.ndarray:
    """Edge-edge rows (ea0, ea1, eb0, eb1 at t0, t1) -> coplanarity rows (eb1; eb0, ea0, ea1)."""
    idx = [3, 2, 0, 1, 7, 6, 4, 5]
    return q[:, idx]
