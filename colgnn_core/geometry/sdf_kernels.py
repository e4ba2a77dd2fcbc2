"""Compiled tool SDFs and their analytic gradients at world points: the numpy path of :class:`~colgnn_core.geometry.
tools.Tool`.

Why compiled: the correction, the broad phase and the graph call the tool's SDF 20-40 times a step, mostly on a few
dozen points. The formula code of :mod:`colgnn_core.geometry.tools` runs on numpy and torch alike, but on numpy each
call costs 40-350 us of per-operation overhead (the knife's section alone is ~60 array operations), which was 5 ms
of a ``knife_torus`` step. Here one loop over the points does the pose transform, the SDF and, if asked, the unit
gradient, point by point (a few us a call).

The formulas are those of ``tools.py`` operation for operation (the same 1e-24 under each square root of the SDF,
the same one-sided choices at kinks), so the values equal the torch path's to rounding; ``tests/test_tools.py``
checks both against each other, against finite differences and the subgradient inequality.

Shapes are numbered by :data:`SHAPE_IDS`; ``params`` [4] holds each shape's parameters in the order of
:func:`kernel_params`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SHAPE_IDS = {"sphere": 0, "cylinder": 1, "cone": 2, "blade": 3}
_EPS2 = 1e-24  # the formula code's guard under each square root of the SDF (tools._EPS2)
_TINY = 1e-300  # a direction shorter than this has no unit vector: a one-sided choice is taken instead


def kernel_params(shape: str, params: dict[str, float]) -> np.ndarray:
    """The [4] float64 parameter vector of ``shape`` for :func:`sdf_world` (m): sphere (radius), cylinder (radius,
    height), cone (radius, height, tip_radius), blade (length, height, thickness, bevel); unused entries 0."""
    order = {"sphere": ("radius",), "cylinder": ("radius", "height"), "cone": ("radius", "height", "tip_radius"),
             "blade": ("length", "height", "thickness", "bevel")}[shape]
    out = np.zeros(4)
    for i, name in enumerate(order):
        out[i] = float(params.get(name, 0.0))
    return out


@njit(cache=True, inline="always")
def _clip01(x):
    return min(max(x, 0.0), 1.0)


@njit(cache=True, inline="always")
def _sign(x):
    return -1.0 if x < 0 else 1.0


@njit(cache=True, inline="always")
def _round_box(dx, dy):
    """tools._round_box_2d: the exact distance from two per-axis excesses."""
    rx, ry = max(dx, 0.0), max(dy, 0.0)
    return min(max(dx, dy), 0.0) + math.sqrt(rx * rx + ry * ry + _EPS2)


@njit(cache=True, inline="always")
def _round_box_grad(dx, dy):
    """(gx, gy) of _round_box w.r.t. its two excesses; where both are <= 0, the larger one's axis."""
    if dx > 0 and dy > 0:
        n = math.sqrt(dx * dx + dy * dy)
        return dx / n, dy / n
    return (1.0, 0.0) if dx >= dy else (0.0, 1.0)


@njit(cache=True, inline="always")
def _radial(x, y):
    """Unit radial direction about the z axis; +x on the axis."""
    n = math.sqrt(x * x + y * y)
    if n > _TINY:
        return x / n, y / n
    return 1.0, 0.0


@njit(cache=True)
def _sphere(x, y, z, radius, grad):
    d = math.sqrt(x * x + y * y + z * z + _EPS2) - radius
    if not grad:
        return d, 0.0, 0.0, 0.0
    n = math.sqrt(x * x + y * y + z * z)
    if n > _TINY:
        return d, x / n, y / n, z / n
    return d, 0.0, 0.0, 1.0


@njit(cache=True)
def _cylinder(x, y, z, radius, height, grad):
    d = _round_box(math.sqrt(x * x + y * y + _EPS2) - radius, abs(z) - 0.5 * height)
    if not grad:
        return d, 0.0, 0.0, 0.0
    gq, gz = _round_box_grad(math.sqrt(x * x + y * y) - radius, abs(z) - 0.5 * height)
    rx, ry = _radial(x, y)
    return d, gq * rx, gq * ry, gz * _sign(z)


@njit(cache=True, inline="always")
def _cone_parts(qx, qy, radius, height, tip_radius):
    """The two candidate offsets of iq's sdCappedCone: to the caps (ca) and to the slanted side (cb)."""
    hh = 0.5 * height
    r1, r2 = tip_radius, radius
    cax = qx - min(qx, r1 if qy < 0 else r2)
    cay = abs(qy) - hh
    k2x, k2y = r2 - r1, 2.0 * hh
    t = _clip01(((r2 - qx) * k2x + (hh - qy) * k2y) / (k2x * k2x + k2y * k2y))
    cbx = qx - r2 + k2x * t
    cby = qy - hh + k2y * t
    return cax, cay, cbx, cby


@njit(cache=True)
def _cone(x, y, z, radius, height, tip_radius, grad):
    qy = z - 0.5 * height
    cax, cay, cbx, cby = _cone_parts(math.sqrt(x * x + y * y + _EPS2), qy, radius, height, tip_radius)
    inside = cbx < 0 and cay < 0
    d = math.sqrt(min(cax * cax + cay * cay, cbx * cbx + cby * cby) + _EPS2)
    if inside:
        d = -d
    if not grad:
        return d, 0.0, 0.0, 0.0
    cax, cay, cbx, cby = _cone_parts(math.sqrt(x * x + y * y), qy, radius, height, tip_radius)
    s = -1.0 if (cbx < 0 and cay < 0) else 1.0
    if cax * cax + cay * cay < cbx * cbx + cby * cby:
        vx, vy = cax, cay * _sign(qy)  # the cap offset is in |qy|: unfold its sign
    else:
        vx, vy = cbx, cby
    n = math.sqrt(vx * vx + vy * vy)
    if n > _TINY:
        gx2, gy2 = s * (vx / n), s * (vy / n)
    else:
        gx2, gy2 = 0.0, -1.0
    rx, ry = _radial(x, y)
    return d, gx2 * rx, gx2 * ry, gy2


@njit(cache=True, inline="always")
def _segment(u, v, ax, ay, bx, by):
    """tools._segment_distance for one point, with the offset from the closest point: (distance, du, dv)."""
    ex, ey = bx - ax, by - ay
    t = _clip01(((u - ax) * ex + (v - ay) * ey) / (ex * ex + ey * ey))
    du, dv = u - ax - t * ex, v - ay - t * ey
    return math.sqrt(du * du + dv * dv + _EPS2), du, dv


@njit(cache=True)
def _blade(x, y, z, length, height, thickness, bevel, grad):
    u, v = abs(y), z
    h = 0.5 * thickness
    nlen = math.hypot(bevel, h)
    l_bevel = (u * bevel - v * h) / nlen
    l_flat = u - h
    l_spine = v - height
    lmax = max(max(l_bevel, l_flat), l_spine)
    d1, du1, dv1 = _segment(u, v, 0.0, 0.0, h, bevel)
    d2, du2, dv2 = _segment(u, v, h, bevel, h, height)
    d3, du3, dv3 = _segment(u, v, h, height, 0.0, height)
    dsec = min(min(d1, d2), d3) if lmax > 0 else lmax
    ex = abs(x) - 0.5 * length
    d = _round_box(dsec, ex)
    if not grad:
        return d, 0.0, 0.0, 0.0
    # Inside: the normal of the nearest (largest) edge line; outside: away from the nearest segment (first on ties).
    if l_bevel >= l_flat and l_bevel >= l_spine:
        gin_u, gin_v = bevel / nlen, -h / nlen
    elif l_flat >= l_spine:
        gin_u, gin_v = 1.0, 0.0
    else:
        gin_u, gin_v = 0.0, 1.0
    if d1 <= d2 and d1 <= d3:
        du, dv = du1, dv1
    elif d2 <= d3:
        du, dv = du2, dv2
    else:
        du, dv = du3, dv3
    n = math.sqrt(du * du + dv * dv)
    if lmax <= 0 or not n > _TINY:
        gu, gv = gin_u, gin_v
    else:
        gu, gv = du / n, dv / n
    g_sec, g_x = _round_box_grad(dsec, ex)
    return d, g_x * _sign(x), g_sec * gu * _sign(y), g_sec * gv


@njit(cache=True)
def _local(shape, prm, x, y, z, grad):
    if shape == 0:
        return _sphere(x, y, z, prm[0], grad)
    if shape == 1:
        return _cylinder(x, y, z, prm[0], prm[1], grad)
    if shape == 2:
        return _cone(x, y, z, prm[0], prm[1], prm[2], grad)
    return _blade(x, y, z, prm[0], prm[1], prm[2], prm[3], grad)


@njit(cache=True)
def sdf_world(points: np.ndarray, origin: np.ndarray, rot: np.ndarray, shape: int, prm: np.ndarray,
              grad: bool) -> tuple[np.ndarray, np.ndarray]:
    """SDF [N] (m) of world ``points`` [N,3] to the tool at (``origin`` [3], ``rot`` [3,3]: tool frame to world),
    and with ``grad`` its unit outward gradient [N,3] in world axes (else an empty [0,3])."""
    n = points.shape[0]
    d = np.empty(n)
    g = np.empty((n if grad else 0, 3))
    for i in range(n):
        wx, wy, wz = points[i, 0] - origin[0], points[i, 1] - origin[1], points[i, 2] - origin[2]
        # local = (world - origin) @ rot, as transforms.inverse_transform_points
        x = wx * rot[0, 0] + wy * rot[1, 0] + wz * rot[2, 0]
        y = wx * rot[0, 1] + wy * rot[1, 1] + wz * rot[2, 1]
        z = wx * rot[0, 2] + wy * rot[1, 2] + wz * rot[2, 2]
        di, gx, gy, gz = _local(shape, prm, x, y, z, grad)
        d[i] = di
        if grad:
            g[i, 0] = rot[0, 0] * gx + rot[0, 1] * gy + rot[0, 2] * gz
            g[i, 1] = rot[1, 0] * gx + rot[1, 1] * gy + rot[1, 2] * gz
            g[i, 2] = rot[2, 0] * gx + rot[2, 1] * gy + rot[2, 2] * gz
    return d, g
