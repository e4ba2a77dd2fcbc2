"""Procedural tet meshes: swept prisms split conformingly into tets.

A 2D triangulation (a graded disk or a rectangle grid) is swept through a
sequence of layers (around a torus, along a banana's centreline, up through a
mat's thickness). Each triangle between two layers is a prism, split into 3 tets
with the classic rule "each quad's diagonal starts at the bottom copy of its
lower-index vertex": two prisms sharing a quad choose the same diagonal, so the
mesh is conforming without any global search. Deterministic, numpy only.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from colgnn_core.geometry.tetmesh import TetMesh, tet_signed_volumes


def graded_disk(n_boundary: int, growth: float = 1.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate the unit disk with ``n_boundary`` points on the circle.

    Rings get coarser toward the centre by ``growth`` per ring (fewer interior
    nodes for the same surface density). Returns (points [P,2], triangles [T,3]
    counter-clockwise, boundary ids [n_boundary] in angular order).
    """
    if n_boundary < 6:
        raise ValueError("n_boundary must be >= 6")
    h = 2 * np.pi / n_boundary
    radii, counts = [1.0], [n_boundary]
    r, s = 1.0, h
    while True:
        s *= growth
        r -= s
        if r < 0.6 * s:
            break
        radii.append(r)
        counts.append(max(5, int(round(2 * np.pi * r / s))))
    pts, angles, first = [], [], [0]
    for k, (rad, n) in enumerate(zip(radii, counts)):
        a = 2 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n  # stagger rings: no aligned quads
        pts.append(np.stack([rad * np.cos(a), rad * np.sin(a)], axis=1))
        angles.append(a)
        first.append(first[-1] + n)
    centre = first[-1]
    pts = np.concatenate(pts + [np.zeros((1, 2))])
    # Stitch consecutive rings by walking both in angle (no Delaunay: the result
    # does not depend on a Qhull version, so meshes and fingerprints are stable).
    tris = []
    for k in range(len(radii) - 1):
        tris.append(_stitch_rings(first[k + 1], angles[k + 1], first[k], angles[k]))
    n_in = counts[-1]
    i = np.arange(n_in)
    tris.append(np.stack([np.full(n_in, centre), first[-2] + i, first[-2] + (i + 1) % n_in], axis=1))
    tri = _ccw(pts, np.concatenate(tris).astype(np.int64))
    return pts, tri, np.arange(n_boundary, dtype=np.int64)


def _stitch_rings(inner0: int, inner_angles: np.ndarray, outer0: int, outer_angles: np.ndarray) -> np.ndarray:
    """Triangles [n_in + n_out, 3] filling the annulus between two rings of points (ids start at inner0/outer0).

    Angles are ascending in [0, 2 pi). Walks both rings, always advancing the
    one whose next point comes first in angle.
    """
    ni, no = len(inner_angles), len(outer_angles)
    ti = np.concatenate([inner_angles, inner_angles[:1] + 2 * np.pi])
    to = np.concatenate([outer_angles, outer_angles[:1] + 2 * np.pi])
    i = j = 0
    out = []
    while i < ni or j < no:
        if j < no and (i >= ni or to[j + 1] <= ti[i + 1]):
            out.append((inner0 + i % ni, outer0 + j % no, outer0 + (j + 1) % no))
            j += 1
        else:
            out.append((inner0 + i % ni, outer0 + j % no, inner0 + (i + 1) % ni))
            i += 1
    return np.array(out, dtype=np.int64)


def rectangle_grid(nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate [0,1]^2 with an (nx+1) x (ny+1) grid; returns (points [P,2], triangles [T,3] ccw).

    Diagonals alternate in a checkerboard ("union jack") so the grid has no
    preferred shear direction.
    """
    xs, ys = np.linspace(0, 1, nx + 1), np.linspace(0, 1, ny + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    i, j = i.ravel(), j.ravel()
    v00 = i * (ny + 1) + j
    v10 = (i + 1) * (ny + 1) + j
    v01 = v00 + 1
    v11 = v10 + 1
    even = (i + j) % 2 == 0
    t1 = np.where(even[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
    t2 = np.where(even[:, None], np.stack([v00, v11, v01], 1), np.stack([v10, v11, v01], 1))
    tri = np.concatenate([t1, t2]).astype(np.int64)
    return pts, _ccw(pts, tri)


def _ccw(pts: np.ndarray, tri: np.ndarray) -> np.ndarray:
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tri = tri.copy()
    neg = cross < 0
    tri[neg, 1], tri[neg, 2] = tri[neg, 2].copy(), tri[neg, 1].copy()
    return tri


def sweep_prisms(
    points2d: np.ndarray,
    triangles: np.ndarray,
    n_layers: int,
    embed: Callable[[np.ndarray, np.ndarray], np.ndarray],
    periodic: bool = False,
) -> TetMesh:
    """Sweep a 2D triangulation through layers and split the prisms into tets.

    Args:
        points2d: [P,2] section points.
        triangles: [T,3] section triangles.
        n_layers: number of vertex layers (>= 2); with ``periodic`` the last layer
            connects back to the first (a closed ring, e.g. a torus).
        embed: f(layer_index [L], points2d [P,2]) -> [L,P,3] world positions.
        periodic: close the sweep.
    Returns a valid TetMesh with positive tets (all flipped together if the
    embedding is orientation-reversing).
    """
    p = len(points2d)
    layers = np.arange(n_layers)
    x = embed(layers, points2d).reshape(-1, 3)
    # Sort each triangle's vertices by section index: a < b < c.
    tri = np.sort(triangles, axis=1)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n_seg = n_layers if periodic else n_layers - 1
    k = np.arange(n_seg)[:, None]
    lo = k * p
    hi = ((k + 1) % n_layers) * p
    # Prism (a,b,c | a',b',c') with diagonals a-b', b-c', a-c'.
    t1 = np.stack([lo + a, lo + b, lo + c, hi + c], axis=-1)
    t2 = np.stack([lo + a, lo + b, hi + c, hi + b], axis=-1)
    t3 = np.stack([lo + a, hi + a, hi + b, hi + c], axis=-1)
    # Sorting may have turned a ccw triangle cw, which mirrors its 3 tets: swap
    # two vertices of those tets so all share the sign of the embedding.
    q = points2d
    cross = (q[b, 0] - q[a, 0]) * (q[c, 1] - q[a, 1]) - (q[b, 1] - q[a, 1]) * (q[c, 0] - q[a, 0])
    cw = np.broadcast_to(cross < 0, (n_seg, len(tri))).reshape(-1)
    tets = np.concatenate([t1.reshape(-1, 4), t2.reshape(-1, 4), t3.reshape(-1, 4)])
    cw = np.concatenate([cw, cw, cw])
    tets[cw] = tets[cw][:, [0, 1, 3, 2]]
    vol = tet_signed_volumes(x, tets)
    if np.sum(vol < 0) > len(vol) / 2:
        tets = tets[:, [0, 1, 3, 2]]
    return TetMesh.from_tets(x, tets)


def torus_mesh(major_radius: float, minor_radius: float, around: int, segments: int, growth: float = 1.25) -> TetMesh:
    """Solid torus lying flat (axis z, centre at the origin).

    ``around``: surface vertices around the tube; ``segments``: vertex layers
    around the ring. Surface vertices = around * segments. ``growth``: interior
    coarsening per ring of the section (see :func:`graded_disk`).
    """
    pts, tri, _ = graded_disk(around, growth)

    def embed(layers: np.ndarray, q: np.ndarray) -> np.ndarray:
        u = 2 * np.pi * layers[:, None] / segments
        rho = major_radius + minor_radius * q[None, :, 0]  # [1,P]
        z = np.broadcast_to(minor_radius * q[None, :, 1], (len(layers), len(q)))
        return np.stack([rho * np.cos(u), rho * np.sin(u), z], axis=-1)

    return sweep_prisms(pts, tri, segments, embed, periodic=True)


def mat_mesh(size_x: float, size_y: float, thickness: float, nx: int, ny: int, nz: int) -> TetMesh:
    """Box mat [-sx/2, sx/2] x [-sy/2, sy/2] x [0, thickness] with nx*ny*nz prism cells."""
    pts, tri = rectangle_grid(nx, ny)

    def embed(layers: np.ndarray, q: np.ndarray) -> np.ndarray:
        z = thickness * layers / nz
        xy = (q - 0.5) * np.array([size_x, size_y])
        return np.concatenate([np.broadcast_to(xy, (len(layers),) + xy.shape),
                               np.broadcast_to(z[:, None, None], (len(layers), len(q), 1))], axis=-1)

    return sweep_prisms(pts, tri, nz + 1, embed)


def banana_mesh(
    length: float,
    radius: float,
    bend: float,
    end_radius_ratio: float,
    around: int,
    segments: int,
    growth: float = 1.25,
) -> TetMesh:
    """A banana: a tube curved in the x-y plane, tapered toward flat caps, lying along x.

    Args:
        length: chord length (m) between the two end caps (along x).
        radius: tube radius at the middle (m).
        bend: sagitta (m) of the centreline arc, bulging toward -y.
        end_radius_ratio: radius at the caps / middle radius.
        around: surface vertices around the tube; segments: number of cross-sections.
        growth: interior coarsening per ring of the section (see :func:`graded_disk`).
    The lowest point of every cross-section is at z = 0 (the banana lies along
    its whole length on the xy plane); the mesh is centred in x.
    """
    pts, tri, _ = graded_disk(around, growth)
    # Arc through (-L/2, 0), (0, -bend), (L/2, 0): radius of curvature R.
    half = 0.5 * length
    rc = (half * half + bend * bend) / (2 * bend)
    theta0 = np.arcsin(half / rc)
    def profile(t: np.ndarray) -> np.ndarray:
        # Taper: r = radius * (e + (1-e) * (1 - (2t-1)^2)): a parabolic bulge with finite slope at the blunt ends.
        return radius * (end_radius_ratio + (1 - end_radius_ratio) * (1 - (2 * t - 1) ** 2))

    # Sections spaced in proportion to the local radius (uniform in the integral
    # of 1/r), so thin ends get as well-shaped tets as the thick middle.
    fine = np.linspace(0.0, 1.0, 4001)
    u = np.concatenate([[0.0], np.cumsum(0.5 * (1 / profile(fine[1:]) + 1 / profile(fine[:-1])) * np.diff(fine))])
    s = np.interp(np.linspace(0.0, u[-1], segments), u, fine)
    theta = -theta0 + 2 * theta0 * s
    r = profile(s)
    cx = rc * np.sin(theta)
    cy = -bend + rc * (1 - np.cos(theta))
    cz = r  # bottom of each section touches z = 0 (section plane is vertical)
    # Frame: tangent in xy (the section plane stays vertical), up = +z.
    tx, ty = np.cos(theta), np.sin(theta)
    side = np.stack([-ty, tx, np.zeros_like(tx)], axis=1)  # horizontal normal in the section plane

    def embed(layers: np.ndarray, q: np.ndarray) -> np.ndarray:
        c = np.stack([cx, cy, cz], axis=1)[layers]  # [L,3]
        rr = r[layers][:, None, None]
        return c[:, None, :] + rr * (q[None, :, 0:1] * side[layers][:, None, :]
                                     + q[None, :, 1:2] * np.array([0.0, 0.0, 1.0]))

    return sweep_prisms(pts, tri, segments, embed)
