"""Tet meshes: orientation, boundary extraction, validation, loading, procedural generators."""

import numpy as np
import pytest

from colgnn_core.geometry import TetMesh, boundary_faces, load_msh, load_npz
from colgnn_core.geometry.procedural import banana_mesh, graded_disk, mat_mesh, sweep_prisms, torus_mesh
from colgnn_core.geometry.tetmesh import check_closed_surface, surface_edges, tet_signed_volumes
from colgnn_core.scenes.scene import MESH_DIR, surface_height

UNIT_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def _normals(v, f):
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def test_single_tet_faces_point_outward():
    faces = boundary_faces(np.array([[0, 1, 2, 3]]))
    assert faces.shape == (4, 3)
    centroid = UNIT_TET.mean(0)
    n = _normals(UNIT_TET, faces)
    to_face = UNIT_TET[faces].mean(1) - centroid
    assert np.all((n * to_face).sum(1) > 0)
    m = TetMesh.from_tets(UNIT_TET, [[0, 1, 2, 3]])
    m.validate()
    assert np.isclose(m.volumes()[0], 1 / 6)
    assert m.surface_vertices.tolist() == [0, 1, 2, 3]
    assert m.edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]


def test_two_tets_share_an_interior_face():
    v = np.concatenate([UNIT_TET, [[1.0, 1, 1]]])
    m = TetMesh.from_tets(v, [[0, 1, 2, 3], [1, 3, 2, 4]], orient=True)
    m.validate()
    assert len(m.faces) == 6  # 8 tet faces - 2 copies of the shared one
    assert not any(sorted(f) == [1, 2, 3] for f in m.faces.tolist())


def test_validate_names_problems():
    with pytest.raises(ValueError, match="inverted"):
        TetMesh.from_tets(UNIT_TET, [[0, 2, 1, 3]]).validate()
    flat = UNIT_TET.copy()
    flat[3] = [0.3, 0.3, 0.0]
    with pytest.raises(ValueError, match="inverted or flat"):
        TetMesh.from_tets(flat, [[0, 1, 2, 3]]).validate()
    m = TetMesh.from_tets(UNIT_TET, [[0, 1, 2, 3]])
    with pytest.raises(ValueError, match="boundary"):
        TetMesh(vertices=m.vertices, tets=m.tets, faces=m.faces[:3]).validate()
    with pytest.raises(ValueError, match="inward"):
        TetMesh(vertices=m.vertices, tets=m.tets, faces=m.faces[:, ::-1]).validate()
    with pytest.raises(ValueError, match="not used"):
        TetMesh.from_tets(np.concatenate([UNIT_TET, [[5.0, 5, 5]]]), [[0, 1, 2, 3]]).validate()
    # A sliver 1e-9 below the base of the unit tet: positive but degenerate.
    sliver = TetMesh.from_tets(np.concatenate([UNIT_TET, [[0.2, 0.2, -1e-9]]]), [[0, 1, 2, 3], [0, 2, 1, 4]],
                               orient=True)
    with pytest.raises(ValueError, match="degenerate"):
        sliver.validate()


def test_check_closed_surface_rejects_open_and_flipped():
    m = TetMesh.from_tets(UNIT_TET, [[0, 1, 2, 3]])
    check_closed_surface(m.vertices, m.faces)
    with pytest.raises(ValueError, match="open|unmatched"):
        check_closed_surface(m.vertices, m.faces[:3])
    flipped = m.faces.copy()
    flipped[0] = flipped[0, ::-1]
    with pytest.raises(ValueError, match="orient|twice"):
        check_closed_surface(m.vertices, flipped)
    with pytest.raises(ValueError, match="inward"):
        check_closed_surface(m.vertices, m.faces[:, ::-1])


def test_fingerprint_and_readonly():
    m = torus_mesh(0.1, 0.04, 8, 12)
    assert m.fingerprint() == torus_mesh(0.1, 0.04, 8, 12).fingerprint()
    assert len(m.fingerprint()) == 64
    moved = m.transformed(translation=[1e-6, 0, 0])
    assert moved.fingerprint() != m.fingerprint()
    with pytest.raises(ValueError):
        m.vertices[0, 0] = 1.0


def test_transformed_keeps_validity_and_rejects_reflection():
    m = mat_mesh(0.1, 0.1, 0.01, 3, 3, 1)
    r = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    m.transformed(rotation=r, scale=2.0, translation=[1, 2, 3]).validate()
    with pytest.raises(ValueError, match="det"):
        m.transformed(rotation=np.diag([1.0, 1, -1]))


def test_graded_disk():
    pts, tri, boundary = graded_disk(24)
    assert np.allclose(np.linalg.norm(pts[boundary], axis=1), 1.0)
    assert np.all(np.linalg.norm(pts, axis=1) <= 1 + 1e-12)
    # ccw and covers the polygon's area
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    area = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    assert np.all(area > 0)
    assert np.isclose(area.sum(), 0.5 * 24 * np.sin(2 * np.pi / 24))


@pytest.mark.parametrize(
    "make, surface",
    [
        (lambda: torus_mesh(0.1, 0.04, 12, 30), 360),
        (lambda: mat_mesh(0.3, 0.3, 0.02, 12, 12, 2), 2 * 13 * 13 + 48),
        (lambda: banana_mesh(0.2, 0.018, 0.03, 0.35, 12, 20), None),
    ],
)
def test_procedural_meshes_valid(make, surface):
    m = make()
    m.validate()
    assert m.quality()["min_quality"] > 0.05
    if surface is not None:
        assert len(m.surface_vertices) == surface
    # closed 2-manifold of genus g: V - E + F = 2 - 2g
    chi = len(m.surface_vertices) - len(m.edges) + len(m.faces)
    assert chi in (0, 2)


def test_torus_is_genus_one_and_banana_lies_flat():
    t = torus_mesh(0.1, 0.04, 12, 30)
    assert len(t.surface_vertices) - len(t.edges) + len(t.faces) == 0
    assert np.isclose(t.volumes().sum(), 2 * np.pi**2 * 0.1 * 0.04**2, rtol=0.1)
    b = banana_mesh(0.2, 0.018, 0.03, 0.35, 12, 20)
    lo, hi = b.bbox()
    assert np.isclose(lo[2], 0.0, atol=1e-12) and np.isclose(hi[0] - lo[0], 0.2, rtol=0.05)
    assert np.isclose(hi[2] - lo[2], 0.036, rtol=0.02)


def test_sweep_prisms_is_conforming_for_any_vertex_order():
    pts, tri, _ = graded_disk(10)
    perm = np.random.default_rng(0).permutation(len(pts))
    inv = np.argsort(perm)
    m = sweep_prisms(pts[perm], inv[tri], 4, lambda l, q: np.concatenate(
        [np.broadcast_to(q, (len(l),) + q.shape), np.broadcast_to(0.1 * l[:, None, None], (len(l), len(q),
                                                                                           1))], axis=-1))
    m.validate()
    assert np.all(tet_signed_volumes(m.vertices, m.tets) > 0)


def test_surface_height_on_mat():
    m = mat_mesh(0.3, 0.3, 0.02, 4, 4, 1)
    h = surface_height(m, np.array([[0.0, 0.0], [0.1, -0.05], [1.0, 1.0]]))
    assert np.allclose(h[:2], 0.02) and np.isnan(h[2])


def test_load_ipc_bunny_and_ci_bunny():
    m = load_msh(MESH_DIR / "bunny.msh")
    m.validate()
    assert m.num_vertices == 4670 and len(m.tets) == 19379
    assert len(m.surface_vertices) == 3135
    full = load_npz(MESH_DIR / "bunny-tets.npz")
    full.validate()
    assert len(full.surface_vertices) == 3012 and full.quality()["min_quality"] > 0.1
    small = load_npz(MESH_DIR / "small-bunny-tets.npz")
    small.validate()
    assert 200 <= len(small.surface_vertices) <= 500


def test_surface_edges_unique_sorted():
    f = np.array([[0, 1, 2], [2, 1, 3]])
    assert surface_edges(f).tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]


def test_first_hits_are_the_nearest_crossing_of_each_parallel_ray_or_none():
    from colgnn_core.geometry.rays import first_hits, ray_faces

    # two stacked unit triangles at z = 1 and z = 2 (the upper listed first), and one off to the side
    base = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    tri = np.stack([base + [0, 0, 2], base + [0, 0, 1], base + [5, 0, 1]])
    origins = np.array([[0.2, 0.3, 0.0], [0.2, 0.3, 1.5], [0.9, 0.9, 0.0], [0.2, 0.3, 3.0], [5.1, 0.1, -1.0]])
    face, t, bary = first_hits(tri, origins, np.array([0.0, 0.0, 1.0]))
    assert face.tolist() == [1, 0, -1, -1, 2]           # nearest first; outside the triangle, or behind: none
    np.testing.assert_allclose(t, [1.0, 0.5, np.inf, np.inf, 2.0])
    np.testing.assert_allclose(bary[0], [0.5, 0.2, 0.3], atol=1e-12)
    assert not bary[2].any()
    rng = np.random.default_rng(0)
    soup = rng.normal(size=(60, 3, 3))
    rays = rng.normal(size=(40, 3)) * 0.3
    d = np.array([0.3, -0.2, 1.0])
    face, t, bary = first_hits(soup, rays, d)
    assert (face >= 0).sum() >= 5
    for s in range(len(rays)):                           # the same as the nearest of ray_faces' hits
        hit, ts, b = ray_faces(soup, rays[s], d)
        if not hit.any():
            assert face[s] == -1
            continue
        i = int(np.flatnonzero(hit)[np.argmin(ts[hit])])
        assert face[s] == i and t[s] == ts[i] and np.allclose(bary[s], b[i])
