"""Rays against triangles: where a ray first crosses a triangle soup, in barycentric terms (units: those of the
input, m in the project)."""

from __future__ import annotations

import numpy as np

__all__ = ["ray_faces"]


def ray_faces(tri: np.ndarray, origin: np.ndarray, direction: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Moeller-Trumbore against every triangle ``tri`` [F,3,3]: (hit [F] bool, ray parameter t [F], barycentric
    weights [F,3]) for the ray origin + t direction, t > 0."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(direction, e2)
    a = np.einsum("fi,fi->f", e1, h)
    ok = np.abs(a) > 1e-18
    f = 1.0 / np.where(ok, a, 1.0)
    s = origin - tri[:, 0]
    u = f * np.einsum("fi,fi->f", s, h)
    q = np.cross(s, e1)
    v = f * (q @ direction)
    t = f * np.einsum("fi,fi->f", e2, q)
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hit, t, np.stack([1.0 - u - v, u, v], axis=1)
