"""Exact (oracle) collision checks: ipctk's CCD and intersection tests, winding numbers.

Tests and ``colgnn evaluate --exact`` use these; the fast path (broad phase +
filter + narrow phase) never depends on them. ipctk's Tight-Inclusion CCD is
conservative: it never misses a contact and may report one for pairs closer than
its tolerance.
"""

from __future__ import annotations

import numpy as np

from colgnn_core.collision.broad_phase import box_pairs
from colgnn_core.errors import InputError

__all__ = [
    "ccd_vertex_face",
    "ccd_edge_edge",
    "combined_collision_mesh",
    "has_intersections",
    "is_step_collision_free",
    "winding_numbers",
    "points_inside_mesh",
]

DEFAULT_TOLERANCE = 1e-6
DEFAULT_MAX_ITERATIONS = 1_000_000


def _ipctk():
    import ipctk  # imported lazily: the fast path must not need it

    return ipctk


def pair_arrays(args, names) -> list[np.ndarray]:
    """The 8 position arrays of K primitive pairs as float64 [K,3] each; InputError naming a bad one."""
    arrs = []
    for a, n in zip(args, names):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{n} must be [K,3], got shape {a.shape}")
        arrs.append(a)
    if len({a.shape[0] for a in arrs}) != 1:
        raise InputError("all pair inputs must have the same number of rows")
    return arrs


def _stack8(args, names) -> np.ndarray:
    return np.ascontiguousarray(np.stack(pair_arrays(args, names), axis=1))  # [K,8,3]


def _run_ccd(fn, q: np.ndarray, tolerance: float, max_iterations: int) -> tuple[np.ndarray, np.ndarray]:
    hit = np.zeros(len(q), dtype=bool)
    toi = np.full(len(q), np.inf)
    for i in range(len(q)):  # ipctk has no batched per-pair call; this is the oracle, not the hot path
        r = fn(*q[i], tolerance=tolerance, max_iterations=max_iterations)
        hit[i] = r[0]
        toi[i] = r[1] if r[0] else np.inf
    return hit, toi


def ccd_vertex_face(p0, a0, b0, c0, p1, a1, b1, c1, *, tolerance: float = DEFAULT_TOLERANCE,
                    max_iterations: int = DEFAULT_MAX_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Tight-Inclusion CCD for K vertex-triangle pairs ([K,3] each). Returns (hit [K] bool, toi [K], inf if none)."""
    q = _stack8((p0, a0, b0, c0, p1, a1, b1, c1), ("p0", "a0", "b0", "c0", "p1", "a1", "b1", "c1"))
    return _run_ccd(_ipctk().tight_inclusion.point_triangle_ccd, q, tolerance, max_iterations)


def ccd_edge_edge(ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1, *,
                  tolerance: float = DEFAULT_TOLERANCE,
                  max_iterations: int = DEFAULT_MAX_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Tight-Inclusion CCD for K edge-edge pairs ([K,3] each). Returns (hit [K] bool, toi [K])."""
    q = _stack8((ea0_t0, ea1_t0, eb0_t0, eb1_t0, ea0_t1, ea1_t1, eb0_t1, eb1_t1),
                ("ea0_t0", "ea1_t0", "eb0_t0", "eb1_t0", "ea0_t1", "ea1_t1", "eb0_t1", "eb1_t1"))
    return _run_ccd(_ipctk().tight_inclusion.edge_edge_ccd, q, tolerance, max_iterations)


def _check_mesh(V, F, name: str) -> tuple[np.ndarray, np.ndarray]:
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise InputError(f"{name} vertices must be a non-empty [N,3] array, got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise InputError(f"{name} faces must be a non-empty [F,3] array, got shape {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        raise InputError(f"{name} faces must be integers")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(f"{name} faces index out of range [0,{len(V)})")
    if not np.all(np.isfinite(V)):
        raise InputError(f"{name} vertices contain NaN or inf")
    return V, F.astype(np.int64)


def combined_collision_mesh(object_V, object_F, tool_V, tool_F):
    """ipctk CollisionMesh of object + tool (tool vertices after the object's); tool-tool pairs excluded.

    Returns ``(mesh, V)`` with V the stacked [N+M,3] vertices.
    """
    ipctk = _ipctk()
    object_V, object_F = _check_mesh(object_V, object_F, "object")
    tool_V, tool_F = _check_mesh(tool_V, tool_F, "tool")
    n = len(object_V)
    V = np.asfortranarray(np.vstack([object_V, tool_V]))
    F = np.asfortranarray(np.vstack([object_F, tool_F + n]).astype(np.int32))
    E = np.asfortranarray(ipctk.edges(F).astype(np.int32))
    mesh = ipctk.CollisionMesh(V, E, F)
    mesh.can_collide = ipctk.make_static_obstacle_filter(n)
    return mesh, V


def has_intersections(object_V, object_F, tool_V, tool_F) -> bool:
    """True if any triangle of the object intersects the tool (or the object itself).

    Oracle for the intersecting-triangle-pairs metric; tool self-intersections are ignored.
    """
    ipctk = _ipctk()
    mesh, V = combined_collision_mesh(object_V, object_F, tool_V, tool_F)
    return bool(ipctk.has_intersections(mesh, V, broad_phase=ipctk.LBVH()))


def object_tool_collision_mesh(object_V, object_F, tool_V, tool_F):
    """ipctk CollisionMesh of the object *surface* and the tool in which only object–tool pairs can collide.

    Object self-contact and tool self-contact are excluded (link triangles make the object one connected
    component and the tool another). Returns ``(mesh, V)``, V the stacked [S+M,3] vertices (the object's
    surface vertices first, in the order of ``np.unique(object_F)``).
    """
    ipctk = _ipctk()
    object_V, object_F = _check_mesh(object_V, object_F, "object")
    ids = np.unique(object_F)
    remap = np.full(len(object_V), -1)
    remap[ids] = np.arange(len(ids))
    surface_V, surface_F = object_V[ids], remap[object_F]
    mesh, V = combined_collision_mesh(surface_V, surface_F, tool_V, tool_F)
    n = len(ids)
    link = np.stack([np.zeros(n, dtype=np.int64), np.arange(n), np.arange(n)], axis=1)
    F = np.asfortranarray(np.vstack([surface_F, link, np.asarray(tool_F) + n]).astype(np.int32))
    mesh.can_collide = ipctk.make_connected_components_filter(F)
    return mesh, V


def tool_intersects(object_V, object_F, tool_V, tool_F) -> bool:
    """True if the object surface intersects the tool (object self-intersection is not counted)."""
    ipctk = _ipctk()
    mesh, V = object_tool_collision_mesh(object_V, object_F, tool_V, tool_F)
    return bool(ipctk.has_intersections(mesh, V, broad_phase=ipctk.LBVH()))


def self_intersects(object_V, object_F) -> bool:
    """True if the object surface intersects itself (non-adjacent triangles crossing)."""
    ipctk = _ipctk()
    object_V, object_F = _check_mesh(object_V, object_F, "object")
    F = np.asfortranarray(object_F.astype(np.int32))
    mesh = ipctk.CollisionMesh(np.asfortranarray(object_V), np.asfortranarray(ipctk.edges(F).astype(np.int32)), F)
    return bool(ipctk.has_intersections(mesh, np.asfortranarray(object_V), broad_phase=ipctk.LBVH()))


def tool_step_free(object_V0, object_V1, object_F, tool_V0, tool_V1, tool_F, *, contact_only: bool = False,
                   tolerance: float = DEFAULT_TOLERANCE) -> bool:
    """True if the linear step of the object *surface* and the tool has no object–tool contact (ipctk
    Tight-Inclusion CCD; object self-contact is not counted).

    By default with ipctk's conservative rescaling 0.8: a pair that comes closer than min(0.2 x its initial
    distance, 1e-4 m) counts as a collision (IPC's line-search clearance), which is stricter than "no contact".
    ``contact_only``: rescaling 1, i.e. only a real touch (separation 0) counts.
    """
    ipctk = _ipctk()
    object_V1, _ = _check_mesh(object_V1, object_F, "object t1")
    tool_V1, _ = _check_mesh(tool_V1, tool_F, "tool t1")
    if np.shape(object_V0) != object_V1.shape or np.shape(tool_V0) != tool_V1.shape:
        raise InputError("t0 and t1 vertex arrays must have the same shape")
    mesh, V0 = object_tool_collision_mesh(object_V0, object_F, tool_V0, tool_F)
    V1 = np.asfortranarray(np.vstack([object_V1[np.unique(object_F)], tool_V1]))
    ccd = ipctk.TightInclusionCCD(tolerance=tolerance, max_iterations=DEFAULT_MAX_ITERATIONS,
                                  conservative_rescaling=1.0 if contact_only else 0.8)
    return bool(ipctk.is_step_collision_free(mesh, V0, V1, broad_phase=ipctk.LBVH(), narrow_phase_ccd=ccd))


def is_step_collision_free(object_V0, object_V1, object_F, tool_V0, tool_V1, tool_F, *,
                           tolerance: float = DEFAULT_TOLERANCE) -> bool:
    """True if the linear motion V0 -> V1 of object and tool has no contact (ipctk Tight-Inclusion).

    Note: ipctk's docstring says the opposite; True really means collision-free.
    """
    ipctk = _ipctk()
    object_V0, object_F = _check_mesh(object_V0, object_F, "object t0")
    object_V1, _ = _check_mesh(object_V1, object_F, "object t1")
    tool_V0, tool_F = _check_mesh(tool_V0, tool_F, "tool t0")
    tool_V1, _ = _check_mesh(tool_V1, tool_F, "tool t1")
    if object_V0.shape != object_V1.shape or tool_V0.shape != tool_V1.shape:
        raise InputError("t0 and t1 vertex arrays must have the same shape")
    mesh, V0 = combined_collision_mesh(object_V0, object_F, tool_V0, tool_F)
    V1 = np.asfortranarray(np.vstack([object_V1, tool_V1]))
    ccd = ipctk.TightInclusionCCD(tolerance=tolerance, max_iterations=DEFAULT_MAX_ITERATIONS)
    return bool(ipctk.is_step_collision_free(mesh, V0, V1, broad_phase=ipctk.LBVH(), narrow_phase_ccd=ccd))


def _check_points(points) -> np.ndarray:
    """Query points as float64 [K,3]; InputError for a wrong shape or NaN/inf."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"points must be [K,3], got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InputError("points contain NaN or inf")
    return P


def winding_numbers(V, F, points, *, chunk: int = 2_000_000) -> np.ndarray:
    """Generalised winding number [K] of a closed, outward-oriented triangle mesh at ``points`` [K,3].

    ~1 inside, ~0 outside (Jacobson et al. 2013, solid angles by Van Oosterom & Strackee).
    """
    V, F = _check_mesh(V, F, "mesh")
    P = _check_points(points)
    out = np.zeros(len(P))
    if len(P) == 0:
        return out
    T = V[F]  # [F,3,3]
    step = max(1, chunk // len(F))
    for s in range(0, len(P), step):  # chunks bound memory; each chunk is vectorised over points x faces
        q = P[s:s + step, None, None, :]
        r = T[None] - q  # [k,F,3,3]
        a, b, c = r[..., 0, :], r[..., 1, :], r[..., 2, :]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("kfi,kfi->kf", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("kfi,kfi->kf", a, b) * lc + np.einsum("kfi,kfi->kf", b, c) * la \
            + np.einsum("kfi,kfi->kf", c, a) * lb
        out[s:s + step] = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
    return out


# A fixed, "generic" ray direction for the parity test: axis-aligned rays hit the edges and
# vertical faces of axis-aligned meshes (cylinders, boxes) far too often.
_RAY_ROTATION = np.linalg.qr(np.array([[0.8263, -0.3121, 0.4689], [0.2217, 0.9372, 0.2689],
                                       [-0.5177, -0.1553, 0.8413]]))[0]


def points_inside_mesh(V, F, points) -> np.ndarray:
    """Bool [K]: point strictly inside the closed triangle mesh (V [N,3], F [F,3]).

    Ray parity along a fixed generic direction, vectorised over (point, face) pairs
    found with the box join; points whose ray passes within 1e-10 (relative) of an edge or
    vertex, or that lie on the surface, fall back to the generalised winding number (> 0.5).
    """
    V, F = _check_mesh(V, F, "mesh")
    P = _check_points(points)
    inside = np.zeros(len(P), dtype=bool)
    lo, hi = V.min(axis=0), V.max(axis=0)
    cand = np.flatnonzero(np.all((P >= lo) & (P <= hi), axis=1))
    if len(cand) == 0:
        return inside
    Vr = V @ _RAY_ROTATION  # ray = +z in the rotated frame
    Q = P[cand] @ _RAY_ROTATION
    T = Vr[F]
    flo, fhi = T.min(axis=1), T.max(axis=1)
    qhi = Q.copy()
    qhi[:, 2] = Vr[:, 2].max() + 1.0
    pairs = box_pairs(Q, qhi, flo, fhi)
    i, f = pairs[:, 0], pairs[:, 1]
    a, b, c, q = T[f, 0], T[f, 1], T[f, 2], Q[i]
    scale = float(np.linalg.norm(hi - lo))
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        u = ((q[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (q[:, 1] - a[:, 1])) / det
        v = ((b[:, 0] - a[:, 0]) * (q[:, 1] - a[:, 1]) - (q[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    w = 1.0 - u - v
    eps = 1e-10
    flat = np.abs(det) <= 1e-14 * scale * scale  # face seen edge-on along the ray
    inside2d = (u > eps) & (v > eps) & (w > eps)
    near_edge = (u > -eps) & (v > -eps) & (w > -eps) & ~inside2d
    z = a[:, 2] + u * (b[:, 2] - a[:, 2]) + v * (c[:, 2] - a[:, 2])
    on_surface = inside2d & ~flat & (np.abs(z - q[:, 2]) <= eps * scale)
    crossing = inside2d & ~flat & (z > q[:, 2]) & ~on_surface
    ambiguous = np.zeros(len(cand), dtype=bool)
    ambiguous[i[(near_edge & ~flat) | on_surface]] = True
    # An edge-on face the ray actually touches (point inside its 2-D bounding box) is ambiguous too.
    ambiguous[i[flat & (q[:, 0] >= flo[f, 0]) & (q[:, 0] <= fhi[f, 0]) & (q[:, 1] >= flo[f, 1])
                & (q[:, 1] <= fhi[f, 1]) & (fhi[f, 2] >= q[:, 2])]] = True
    parity = np.bincount(i[crossing], minlength=len(cand)) % 2 == 1
    if ambiguous.any():
        amb = np.flatnonzero(ambiguous)
        parity[amb] = winding_numbers(V, F, P[cand[amb]]) > 0.5
    inside[cand] = parity
    return inside
