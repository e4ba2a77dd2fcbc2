"""Rigid, kinematic tools: analytic signed distance functions and surface meshes.

Each tool is described in its own frame (tool frame); a pose ``[px,py,pz,qx,qy,qz,qw]``
maps it to the world. Conventions in the tool frame (the "working point" sits at
the origin so a trajectory drives the point that touches the object):

* ``sphere``   radius ``radius``; centre at the origin.
* ``cylinder`` radius ``radius``, length ``height``; axis along z, centred at the origin.
* ``cone``     tip at the origin (radius ``tip_radius``, default 0 = sharp), axis +z,
  base of radius ``radius`` at z = ``height``.
* ``blade``    a knife: length ``length`` along x (centred), thickness ``thickness`` along y
  (centred), spine at z = ``height``; the cross-section narrows over the bottom
  ``bevel`` metres to a sharp edge, a line along x at z = 0.

The SDFs are exact Euclidean distances of the ideal shapes (Inigo Quilez's
formulas for the capped cylinder and the capped cone; an exact convex-polygon
distance extruded along x for the blade), negative inside. The same formula code
runs on numpy arrays and on torch tensors: ``sdf_torch`` is differentiable. The
numpy methods ``sdf``, ``sdf_local`` and ``sdf_grad`` (closed-form unit gradients)
run the same formulas compiled, point by point (:mod:`colgnn_core.geometry.sdf_kernels`:
a few microseconds a call, where the array code spent 40-350), equal to
``sdf_torch`` to rounding. Meshes are inscribed tessellations (vertices on
the ideal surface), watertight, faces outward.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.tetmesh import check_closed_surface, surface_edges, surface_volume
from colgnn_core.geometry.sdf_kernels import SHAPE_IDS, kernel_params, sdf_world
from colgnn_core.geometry.transforms import quat_to_matrix, transform_points

TOOL_SHAPES = ("sphere", "cylinder", "cone", "blade")
RESOLUTIONS = ("full", "ci")

# Added under every square root: keeps gradients finite where a length is 0
# (sphere centre, cylinder axis, knife edge) and changes values by < 1e-12 m.
_EPS2 = 1e-24

_REQUIRED = {
    "sphere": ("radius",),
    "cylinder": ("radius", "height"),
    "cone": ("radius", "height"),
    "blade": ("length", "height", "thickness", "bevel"),
}


# --------------------------------------------------------------------------------------
# Backend-neutral helpers: ``x`` is a numpy array or a torch tensor.
# --------------------------------------------------------------------------------------
def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _sqrt(x):
    if _is_torch(x):
        import torch  # lazy: torch is heavy; the numpy path (solver, dataset workers) must not load it

        return torch.sqrt(x + _EPS2)
    return np.sqrt(x + _EPS2)


def _relu(x):
    return x.clamp(min=0.0) if _is_torch(x) else np.maximum(x, 0.0)


def _negpart(x):
    return x.clamp(max=0.0) if _is_torch(x) else np.minimum(x, 0.0)


def _maximum(a, b):
    if _is_torch(a):
        import torch  # lazy: torch is heavy; the numpy path (solver, dataset workers) must not load it

        return torch.maximum(a, b)
    return np.maximum(a, b)


def _minimum(a, b):
    if _is_torch(a):
        import torch  # lazy: torch is heavy; the numpy path (solver, dataset workers) must not load it

        return torch.minimum(a, b)
    return np.minimum(a, b)


def _where(c, a, b):
    if _is_torch(a):
        import torch  # lazy: torch is heavy; the numpy path (solver, dataset workers) must not load it

        return torch.where(c, a, b)
    return np.where(c, a, b)


def _clip01(x):
    return x.clamp(0.0, 1.0) if _is_torch(x) else np.clip(x, 0.0, 1.0)


def _abs(x):
    return x.abs() if _is_torch(x) else np.abs(x)


# --------------------------------------------------------------------------------------
# Exact SDFs in the tool frame. p: [N,3]; return [N].
# --------------------------------------------------------------------------------------
def _round_box_2d(dx, dy):
    """Combine two per-axis excesses (dx, dy) into an exact distance (iq's box/extrusion rule)."""
    return _negpart(_maximum(dx, dy)) + _sqrt(_relu(dx) ** 2 + _relu(dy) ** 2)


def sdf_sphere(p, radius: float):
    return _sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + p[:, 2] ** 2) - radius


def sdf_cylinder(p, radius: float, height: float):
    """Capped cylinder, axis z, centred (iq's sdCappedCylinder)."""
    dx = _sqrt(p[:, 0] ** 2 + p[:, 1] ** 2) - radius
    dy = _abs(p[:, 2]) - 0.5 * height
    return _round_box_2d(dx, dy)


def sdf_cone(p, radius: float, height: float, tip_radius: float = 0.0):
    """Exact capped cone: radius ``tip_radius`` at z=0, ``radius`` at z=height (iq's sdCappedCone)."""
    hh = 0.5 * height
    r1, r2 = tip_radius, radius
    qx = _sqrt(p[:, 0] ** 2 + p[:, 1] ** 2)
    qy = p[:, 2] - hh
    rsel = _where(qy < 0, qx * 0 + r1, qx * 0 + r2)
    cax = qx - _minimum(qx, rsel)
    cay = _abs(qy) - hh
    k1x, k1y = r2, hh
    k2x, k2y = r2 - r1, 2.0 * hh
    t = _clip01(((k1x - qx) * k2x + (k1y - qy) * k2y) / (k2x * k2x + k2y * k2y))
    cbx = qx - k1x + k2x * t
    cby = qy - k1y + k2y * t
    inside = (cbx < 0) & (cay < 0)
    d = _sqrt(_minimum(cax * cax + cay * cay, cbx * cbx + cby * cby))
    return _where(inside, -d, d)


def blade_section(height: float, thickness: float, bevel: float) -> np.ndarray:
    """Convex cross-section [5,2] of the knife in (y, z), counter-clockwise, edge first."""
    h = 0.5 * thickness
    return np.array([[0.0, 0.0], [h, bevel], [h, height], [-h, height], [-h, bevel]])


def _segment_distance(u, v, ax: float, ay: float, bx: float, by: float):
    """Distance [N] from 2D points (u, v) to the segment (ax, ay)-(bx, by)."""
    ex, ey = bx - ax, by - ay
    t = _clip01(((u - ax) * ex + (v - ay) * ey) / (ex * ex + ey * ey))
    du, dv = u - ax - t * ex, v - ay - t * ey
    return _sqrt(du * du + dv * dv)


def _blade_section_sdf(u, v, height: float, thickness: float, bevel: float):
    """Exact SDF of the knife's section at folded points (u = |y| >= 0, v = z).

    The section is symmetric in y, so only its right half matters: the bevel
    A(0,0)-B(h,bevel), the flat B-C(h,height) and the spine C-D(0,height).
    """
    h = 0.5 * thickness
    nlen = float(np.hypot(bevel, h))
    # Signed distances to the three edge lines (outward normals): inside iff all <= 0.
    l_bevel = (u * bevel - v * h) / nlen
    l_flat = u - h
    l_spine = v - height
    lmax = _maximum(_maximum(l_bevel, l_flat), l_spine)
    s1 = _segment_distance(u, v, 0.0, 0.0, h, bevel)
    s2 = _segment_distance(u, v, h, bevel, h, height)
    s3 = _segment_distance(u, v, h, height, 0.0, height)
    return _where(lmax > 0, _minimum(_minimum(s1, s2), s3), lmax)


def sdf_blade(p, length: float, height: float, thickness: float, bevel: float):
    """Knife: the convex section of :func:`blade_section` (exact) extruded over |x| <= length/2."""
    d2 = _blade_section_sdf(_abs(p[:, 1]), p[:, 2], height, thickness, bevel)
    return _round_box_2d(d2, _abs(p[:, 0]) - 0.5 * length)


def tool_sdf_local(shape: str, params: dict[str, float], p):
    """SDF [N] of tool ``shape`` at tool-frame points p [N,3] (numpy or torch)."""
    if shape == "sphere":
        return sdf_sphere(p, params["radius"])
    if shape == "cylinder":
        return sdf_cylinder(p, params["radius"], params["height"])
    if shape == "cone":
        return sdf_cone(p, params["radius"], params["height"], params.get("tip_radius", 0.0))
    if shape == "blade":
        return sdf_blade(p, params["length"], params["height"], params["thickness"], params["bevel"])
    raise InputError(f"unknown tool shape {shape!r}; valid: {', '.join(TOOL_SHAPES)}")


def quat_to_matrix_torch(q):
    """Unit quaternions [...,4] (xyzw) tensor to rotation matrices [...,3,3], differentiable."""
    import torch  # lazy: torch is heavy; the numpy path (solver, dataset workers) must not load it

    x, y, z, w = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


# --------------------------------------------------------------------------------------
# Procedural tool meshes (tool frame, outward, watertight).
# --------------------------------------------------------------------------------------
def _ring(radius: float, z: float, n: int) -> np.ndarray:
    a = 2 * np.pi * np.arange(n) / n
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, z)], axis=1)


def _tube_faces(first: int, n_around: int, n_rings: int) -> np.ndarray:
    """Quads between consecutive rings (each ``n_around`` vertices, stored contiguously)."""
    i = np.arange(n_around)
    j = (i + 1) % n_around
    faces = []
    for k in range(n_rings - 1):
        a = first + k * n_around
        b = a + n_around
        faces.append(np.stack([a + i, a + j, b + j], axis=1))
        faces.append(np.stack([a + i, b + j, b + i], axis=1))
    return np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)


def _fan(center: int, ring_first: int, n: int, flip: bool) -> np.ndarray:
    i = np.arange(n)
    f = np.stack([np.full(n, center), ring_first + i, ring_first + (i + 1) % n], axis=1)
    return f[:, ::-1] if flip else f


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip all faces if the closed surface encloses negative volume."""
    return faces if surface_volume(vertices, faces) > 0 else faces[:, ::-1].copy()


def _mesh_sphere(radius: float, subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # lazy: trimesh is slow to import and only the sphere tool's mesh needs it

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def _mesh_cylinder(radius: float, height: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    # Side rings ~1.5x as far apart as the vertices around: rigid tools need no
    # isotropic triangles, and fewer tool vertices keep contact queries cheap.
    n_rings = max(2, int(round(height / (1.5 * 2 * np.pi * radius / n))) + 1)
    zs = np.linspace(-0.5 * height, 0.5 * height, n_rings)
    v = np.concatenate([_ring(radius, z, n) for z in zs] + [[[0, 0, zs[0]]], [[0, 0, zs[-1]]]])
    c0, c1 = len(v) - 2, len(v) - 1
    f = np.concatenate([
        _tube_faces(0, n, n_rings),
        _fan(c0, 0, n, flip=True),
        _fan(c1, (n_rings - 1) * n, n, flip=False),
    ])
    return v, _outward(v, f)


def _mesh_cone(radius: float, height: float, tip_radius: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    slant = float(np.hypot(radius - tip_radius, height))
    n_rings = max(2, int(round(slant / (1.5 * 2 * np.pi * radius / n))) + 1)
    s = np.linspace(0.0, 1.0, n_rings)
    if tip_radius > 0:
        rings = [_ring(tip_radius + (radius - tip_radius) * si, height * si, n) for si in s]
        v = np.concatenate(rings + [[[0, 0, 0.0]], [[0, 0, height]]])
        c0, c1 = len(v) - 2, len(v) - 1
        f = np.concatenate([_tube_faces(0, n, n_rings), _fan(c0, 0, n, True), _fan(c1, (n_rings - 1) * n, n, False)])
    else:
        rings = [_ring(radius * si, height * si, n) for si in s[1:]]
        v = np.concatenate([[[0.0, 0.0, 0.0]]] + rings + [[[0, 0, height]]])
        tip, base = 0, len(v) - 1
        f = np.concatenate([
            _fan(tip, 1, n, flip=True),
            _tube_faces(1, n, n_rings - 1),
            _fan(base, 1 + (n_rings - 2) * n, n, flip=False),
        ])
    return v, _outward(v, f)


def _mesh_blade(length: float, height: float, thickness: float, bevel: float,
                n_along: int) -> tuple[np.ndarray, np.ndarray]:
    section = blade_section(height, thickness, bevel)  # [5,2] (y,z)
    xs = np.linspace(-0.5 * length, 0.5 * length, n_along + 1)
    m = len(section)
    v = np.concatenate([np.column_stack([np.full(m, x), section[:, 0], section[:, 1]]) for x in xs])
    f = [_tube_faces(0, m, len(xs))]
    cap = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    f.append(cap[:, ::-1])  # x = -L/2 end, facing -x
    f.append(cap + (len(xs) - 1) * m)
    f = np.concatenate(f)
    return v, _outward(v, f)


# Mesh density per resolution: segments around (sphere: icosphere subdivisions).
_MESH_DENSITY = {
    "full": {"sphere": 3, "cylinder": 40, "cone": 40, "blade": 48},
    "ci": {"sphere": 2, "cylinder": 16, "cone": 16, "blade": 12},
}


_ORIGIN = np.zeros(3)
_IDENTITY = np.eye(3)


def _points(p: np.ndarray) -> np.ndarray:
    """Points as a C-contiguous float64 [N,3] array (what the compiled SDF takes)."""
    return np.ascontiguousarray(np.asarray(p, dtype=np.float64).reshape(-1, 3))


@dataclass
class Tool:
    """A rigid tool: analytic SDF + surface mesh, both in the tool frame.

    Attributes:
        shape: 'sphere' | 'cylinder' | 'cone' | 'blade'.
        params: shape parameters in metres (see the module docstring).
        vertices: [M,3] surface mesh vertices in the tool frame (m).
        faces: [G,3] int64 outward triangles (watertight).
        edges: [H,2] int64 unique edges (i<j).

    The arrays are read-only (scenes are cached); copy before editing.
    """

    shape: str
    params: dict[str, float]
    vertices: np.ndarray
    faces: np.ndarray
    edges: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.edges is None:
            self.edges = surface_edges(self.faces)
        # Read-only: tools live in cached scenes shared by every caller.
        for name in ("vertices", "faces", "edges"):
            a = np.ascontiguousarray(getattr(self, name), dtype=np.float64 if name == "vertices" else np.int64)
            a.setflags(write=False)
            setattr(self, name, a)
        self._kernel = (SHAPE_IDS[self.shape], kernel_params(self.shape, self.params))  # for sdf_world

    # ---- SDF ---------------------------------------------------------------------------
    def sdf_local(self, p: np.ndarray) -> np.ndarray:
        """Signed distance [N] (m, < 0 inside) of tool-frame points p [N,3]."""
        return sdf_world(_points(p), _ORIGIN, _IDENTITY, *self._kernel, False)[0]

    def sdf(self, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Signed distance [N] (m) of world points [N,3] to the tool at ``pose`` [7]."""
        pose = np.asarray(pose, dtype=np.float64)
        return sdf_world(_points(points), pose[:3].copy(), quat_to_matrix(pose[3:]), *self._kernel, False)[0]

    def sdf_grad(self, points: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d [N], unit outward gradient [N,3] in world) at world points [N,3].

        Analytic. At kinks of the SDF (sphere centre, cylinder axis, the
        knife's mid-plane, ...) a one-sided gradient is returned; it is always
        unit length.
        """
        pose = np.asarray(pose, dtype=np.float64)
        return sdf_world(_points(points), pose[:3].copy(), quat_to_matrix(pose[3:]), *self._kernel, True)

    def sdf_torch(self, points, pose):
        """Signed distance [N] of world points tensor [N,3] at pose tensor [7]; differentiable.

        Gradients flow to ``points`` and to ``pose`` (the quaternion is used as
        given; pass a unit quaternion).
        """
        import torch  # lazy: torch is heavy; the numpy path (solver, dataset workers) must not load it

        pose = torch.as_tensor(pose, dtype=points.dtype, device=points.device)
        r = quat_to_matrix_torch(pose[3:])
        local = (points - pose[:3]) @ r
        return tool_sdf_local(self.shape, self.params, local)

    # ---- mesh --------------------------------------------------------------------------
    def world_vertices(self, pose: np.ndarray) -> np.ndarray:
        """Tool mesh vertices [M,3] in world at ``pose`` [7]."""
        return transform_points(self.vertices, np.asarray(pose, dtype=np.float64))

    def bounding_radius(self) -> float:
        """Radius (m) of a ball about the tool-frame origin containing the tool."""
        return float(np.linalg.norm(self.vertices, axis=1).max())

    def validate(self) -> None:
        """ValueError unless the mesh is closed, outward and lies on/inside the ideal shape."""
        check_closed_surface(self.vertices, self.faces, f"{self.shape} tool mesh")
        d = self.sdf_local(self.vertices)
        scale = self.bounding_radius()
        if np.abs(d).max() > 1e-9 * max(scale, 1.0):
            raise ValueError(f"{self.shape} tool mesh vertices are off the analytic surface by {np.abs(d).max():.3e} m")


# The densest tool mesh that mesh_density may choose: icosphere subdivisions, or segments around.
_MAX_DENSITY = {"sphere": 5, "cylinder": 256, "cone": 256, "blade": 48}


def facet_depth(tool: Tool) -> float:
    """m: how far the tool mesh's faces dip inside the analytic shape (the deepest of each face's centroid and edge
    midpoints; 0 for a shape the mesh represents exactly, such as the blade's flat sides)."""
    tri = tool.vertices[tool.faces]                                                  # [G,3,3]
    points = np.concatenate([tri.mean(axis=1), 0.5 * (tri + np.roll(tri, 1, axis=1)).reshape(-1, 3)])
    return max(0.0, -float(tool.sdf_local(points).min()))


FACET_TILT_POINT = 0.9  # barycentric weight of a face's vertex at the points where facet_tilt compares normals


def facet_tilt(tool: Tool) -> float:
    """Radians: the largest angle between a face's normal and the analytic shape's normal (the SDF's gradient) near
    its corners (the points ``FACET_TILT_POINT`` of the way to each vertex, inside the face, so that a face at a
    sharp rim is compared with its own side); 0 for a shape the mesh represents exactly (the blade)."""
    tri = tool.vertices[tool.faces]                                                  # [G,3,3]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    w, o = FACET_TILT_POINT, 0.5 * (1.0 - FACET_TILT_POINT)
    # A point of an exact flat face (a cap, the blade's side) lies on the analytic surface, where the gradient's sign
    # is rounding noise: each point sits a thousandth of its face's shortest edge inside, along the face's normal.
    inset = 1e-3 * np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).min(axis=1)[:, None] * normal
    points = np.concatenate([w * tri[:, k] + o * (tri[:, (k + 1) % 3] + tri[:, (k + 2) % 3]) - inset
                             for k in range(3)])
    _, grad = tool.sdf_grad(points, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    cos = np.sum(np.tile(normal, (3, 1)) * grad, axis=1)
    return float(np.arccos(np.clip(cos, -1.0, 1.0)).max())


def mesh_density(shape: str, params: dict, max_depth: float, resolution: str = "full") -> int:
    """The coarsest tool mesh density (``segments``: icosphere subdivisions for the sphere, segments around for the
    others), no coarser than the resolution's default, whose facets dip at most ``max_depth`` (m) inside the
    analytic shape (:func:`facet_depth`); at most ``_MAX_DENSITY``.

    Why: the IPC ground truth presses with the tool's mesh, the model and the correction with its analytic SDF. Where
    the facets dip deeper than the barrier's reach dhat, the truth's contact force follows the facets (a 162-vertex
    sphere of radius 18 mm tilts it by up to 9 degrees, and the cow's ground truth changed by 0.12-0.68 relative
    displacement between 162 and 642 vertices), so the model is asked to learn the mesh, not the tool. The depth
    is not the whole story on a ridge: the 642-vertex sphere, within dhat of the cow's sphere, still turns the force
    by up to 4.6 degrees (:func:`facet_tilt`), and a press on the cow's spine then leans the body the other way (the
    sequence moved by 0.58 relative displacement from 642 to 40,962 tool vertices; 2,562 vertices, 2.3 degrees:
    0.10). A finer mesh costs the solver 1.7 times as much a sequence at 2,562 vertices, and the network 1.5 times as
    much a step (the graph carries every tool vertex), which a 30-minute fit could not afford (session 58).
    """
    params = {k: v for k, v in params.items() if k != "segments"}
    n = _MESH_DENSITY[resolution][shape]
    while n < _MAX_DENSITY[shape] and facet_depth(make_tool(shape, {**params, "segments": n}, resolution)) > max_depth:
        n = n + 1 if shape == "sphere" else int(np.ceil(1.25 * n / 4.0)) * 4
    return min(n, _MAX_DENSITY[shape])


def make_tool(shape: str, params: dict, resolution: str = "full") -> Tool:
    """Build a :class:`Tool` with a procedural mesh at ``resolution`` ('full' | 'ci').

    ``params`` may include ``segments`` (vertices around; icosphere subdivisions
    for the sphere) to override the resolution's default mesh density.
    """
    if shape not in TOOL_SHAPES:
        raise InputError(f"unknown tool shape {shape!r}; valid: {', '.join(TOOL_SHAPES)}")
    if resolution not in _MESH_DENSITY:
        raise InputError(f"unknown resolution {resolution!r}; valid: {', '.join(_MESH_DENSITY)}")
    missing = [k for k in _REQUIRED[shape] if k not in params]
    if missing:
        raise InputError(f"tool {shape!r} needs parameters {', '.join(missing)}")
    p = {k: float(v) for k, v in params.items() if k != "segments"}
    if any(p[k] <= 0 for k in _REQUIRED[shape]):
        raise InputError(f"tool {shape!r} parameters must be positive, got {p}")
    n = int(params.get("segments", _MESH_DENSITY[resolution][shape]))
    if shape == "sphere":
        v, f = _mesh_sphere(p["radius"], n)
    elif shape == "cylinder":
        v, f = _mesh_cylinder(p["radius"], p["height"], n)
    elif shape == "cone":
        p.setdefault("tip_radius", 0.0)
        v, f = _mesh_cone(p["radius"], p["height"], p["tip_radius"], n)
    else:
        if p["bevel"] >= p["height"]:
            raise InputError("blade bevel must be smaller than its height")
        v, f = _mesh_blade(p["length"], p["height"], p["thickness"], p["bevel"], n)
    tool = Tool(shape=shape, params=p, vertices=np.ascontiguousarray(v, dtype=np.float64),
                faces=np.ascontiguousarray(f, dtype=np.int64))
    tool.validate()
    return tool
