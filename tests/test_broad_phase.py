"""Broad phase: box join, surface topology, SDF culling conservativeness, pipeline wiring."""

import numba
import numpy as np
import pytest

from colgnn_core.collision import exact
from colgnn_core.collision.broad_phase import (CandidatePairs, Surface, ToolSDFBound, active_ring, box_pairs,
                                               mesh_edges, step_candidates)
from colgnn_core.collision.clearance import clearance_pairs
from colgnn_core.collision.kernels import (box_join, changed_rows, grid_join, grid_join_apart, grid_self_join,
                                          grid_self_join_apart, use_kernel_threads)
from colgnn_core.collision.pipeline import CollisionDetector, pair_points
from colgnn_core.errors import InputError
from colgnn_core.geometry.tools import make_tool
from colgnn_core.geometry.transforms import axis_angle_quat

TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def brute_box_pairs(lo_a, hi_a, lo_b, hi_b):
    ov = np.all((lo_a[:, None] <= hi_b[None]) & (lo_b[None] <= hi_a[:, None]), axis=2)
    return set(map(tuple, np.argwhere(ov)))


@pytest.mark.parametrize("na, nb, size", [(0, 5, 0.1), (7, 0, 0.1), (50, 80, 0.05), (300, 200, 0.2), (40, 40, 0.0),
                                                (150, 100, 0.0), (2000, 3, 0.01)])
def test_box_pairs_matches_brute_force(na, nb, size):
    rng = np.random.default_rng(na + nb)
    lo_a = rng.uniform(0, 1, (na, 3))
    lo_b = rng.uniform(0, 1, (nb, 3))
    hi_a = lo_a + rng.uniform(0, size, (na, 3))
    hi_b = lo_b + rng.uniform(0, size, (nb, 3))
    if size == 0.0:  # touching degenerate boxes: identical points
        lo_b[:10] = lo_a[:10]
        hi_b[:10] = hi_a[:10]
    got = box_pairs(lo_a, hi_a, lo_b, hi_b)
    assert got.shape[1] == 2
    assert set(map(tuple, got)) == brute_box_pairs(lo_a, hi_a, lo_b, hi_b)
    assert len(got) == len(set(map(tuple, got)))  # no duplicates


@pytest.mark.parametrize("na, nb, size", [(0, 5, 0.1), (7, 0, 0.1), (50, 80, 0.05), (300, 200, 0.2), (40, 40, 0.0),
                                                (150, 100, 0.0), (2000, 3, 0.01), (500, 500, 0.5)])
def test_grid_joins_match_brute_force(na, nb, size):
    rng = np.random.default_rng(na + nb)
    lo_a, lo_b = rng.uniform(0, 1, (na, 3)), rng.uniform(0, 1, (nb, 3))
    hi_a, hi_b = lo_a + rng.uniform(0, size, (na, 3)), lo_b + rng.uniform(0, size, (nb, 3))
    if size == 0.0:  # touching degenerate boxes: identical points
        lo_b[:10], hi_b[:10] = lo_a[:10], hi_a[:10]
    hi_a[:3] += 0.9  # a few boxes far larger than the rest: they span many cells
    got = grid_join(lo_a, hi_a, lo_b, hi_b)
    assert set(map(tuple, got)) == brute_box_pairs(lo_a, hi_a, lo_b, hi_b)
    assert len(got) == len(set(map(tuple, got)))
    own = grid_self_join(lo_a, hi_a)
    assert set(map(tuple, own)) == {(i, j) for i, j in brute_box_pairs(lo_a, hi_a, lo_a, hi_a) if i < j}
    assert len(own) == len(set(map(tuple, own)))


def test_apart_joins_leave_out_exactly_the_pairs_that_share_a_vertex():
    # Edges and triangles of a real surface (a grid's), with boxes grown so that every adjacent pair overlaps.
    n = 12
    ids = np.arange(n * n).reshape(n, n)
    faces = np.concatenate([np.stack([ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel()], 1),
                            np.stack([ids[:-1, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()], 1)])
    edges = mesh_edges(faces)
    X = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2) * 1.0
    X = np.concatenate([X, np.zeros((n * n, 1))], 1)

    def boxes(prims, grow):
        P = X[prims]
        return P.min(1) - grow, P.max(1) + grow

    def shares(a, b):
        return len(set(a) & set(b)) > 0

    elo, ehi = boxes(edges, 0.3)
    flo, fhi = boxes(faces, 0.3)
    verts = np.arange(n * n)[:, None]
    vlo, vhi = boxes(verts, 0.3)
    own = set(map(tuple, grid_self_join(elo, ehi)))
    apart = grid_self_join_apart(elo, ehi, edges)
    assert set(map(tuple, apart)) == {(i, j) for i, j in own if not shares(edges[i], edges[j])}
    assert len(apart) == len(set(map(tuple, apart))) and len(apart) < len(own) / 2  # most overlaps are neighbours
    vf = set(map(tuple, grid_join(vlo, vhi, flo, fhi)))
    vf_apart = grid_join_apart(vlo, vhi, verts, flo, fhi, faces)
    assert set(map(tuple, vf_apart)) == {(v, f) for v, f in vf if v not in faces[f]}
    assert 0 < len(vf_apart) < len(vf)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="one core: numba runs one thread")
def test_parallel_kernels_give_the_serial_result_at_any_thread_count():
    rng = np.random.default_rng(7)
    lo_a, lo_b = rng.uniform(0, 1, (3000, 3)), rng.uniform(0, 1, (2500, 3))
    hi_a, hi_b = lo_a + rng.uniform(0, 0.1, (3000, 3)), lo_b + rng.uniform(0, 0.1, (2500, 3))
    X0 = rng.uniform(0, 1, (400, 3))
    X1 = X0 + rng.normal(0, 0.02, X0.shape)
    faces = rng.integers(0, 400, (300, 3))
    edges = rng.integers(0, 400, (500, 2))
    vf, fv, ee = (np.stack([rng.integers(0, 400, 2000), rng.integers(0, n, 2000)], 1) for n in (300, 300, 500))

    def run():
        out = [box_join(lo_a, hi_a, lo_b, hi_b), grid_join(lo_a, hi_a, lo_b, hi_b), grid_self_join(lo_a, hi_a)]
        out += list(clearance_pairs(X0, X1, X0[::-1].copy(), X1[::-1].copy(), vf, fv, ee, faces, edges, faces, edges,
                                    5e-3, 0.4, 64))
        return out

    try:
        assert use_kernel_threads(1) == 1
        serial = run()
        assert use_kernel_threads(2) == 2
        parallel = run()
    finally:
        use_kernel_threads(numba.config.NUMBA_NUM_THREADS)
    assert len(serial[0]) > 1000 and len(serial[2]) > 1000 and not serial[3].all() and serial[3].any()
    for a, b in zip(serial, parallel):
        np.testing.assert_array_equal(a, b)  # the same rows in the same order: results never depend on threads


def test_surface_topology():
    s = Surface.from_faces(TET_F, 5)
    assert len(s.edges) == 6 and s.vertices.tolist() == [0, 1, 2, 3] and s.n_vertices == 5
    np.testing.assert_array_equal(s.edges, mesh_edges(TET_F))
    for f, fe in zip(s.faces, s.face_edges):  # face_edges index the face's own edges
        assert {tuple(sorted(e)) for e in s.edges[fe]} == {tuple(sorted((f[i], f[(i + 1) % 3]))) for i in range(3)}
    assert s.incident(s.vertex_faces, np.array([3])).tolist() == [1, 2, 3]
    assert len(s.incident(s.vertex_edges, np.array([0]))) == 3
    with pytest.raises(InputError):
        Surface.from_faces(TET_F, 3)
    with pytest.raises(InputError):
        Surface.from_faces(np.zeros((0, 3), dtype=int))


def _object_and_tool():
    obj = make_tool("sphere", {"radius": 0.03}, "ci")  # a closed mesh used as the deformable object
    tool = make_tool("cone", {"radius": 0.012, "height": 0.04, "tip_radius": 0.0}, "ci")
    return obj.vertices, obj.faces, tool


def _random_step(rng, V, tool):
    """Object V wobbles, tool (tip down) moves towards / into it with a random tilt."""
    n = len(V)
    obj0 = V + rng.normal(scale=5e-4, size=(n, 3))
    obj1 = obj0 + rng.normal(scale=1e-3, size=(n, 3)) + rng.normal(scale=2e-3, size=3)
    q = axis_angle_quat(rng.normal(size=3), rng.uniform(0, 0.4))
    start = np.r_[rng.normal(scale=0.01, size=2), rng.uniform(0.028, 0.04)]
    pose0 = np.r_[start, q]
    pose1 = np.r_[start + np.r_[rng.normal(scale=2e-3, size=2), -rng.uniform(0.0, 0.012)], q]
    return obj0, obj1, tool.world_vertices(pose0), tool.world_vertices(pose1), pose0, pose1


def _exact_hits(det, X):
    """Pairs that really collide: no-SDF candidates -> filter -> ipctk CCD (all stages conservative)."""
    res = det.detect(*X)
    hits = {}
    for kind in ("vf", "fv", "ee"):
        pairs = getattr(res.survivors, kind)
        fn = exact.ccd_edge_edge if kind == "ee" else exact.ccd_vertex_face
        h = fn(*pair_points(kind, pairs, *X, det.object_surface, det.tool_surface))[0] if len(pairs) else []
        hits[kind] = set(map(tuple, pairs[np.asarray(h, dtype=bool)])) if len(pairs) else set()
    return hits, res


def test_no_sdf_candidates_equal_brute_force_boxes():
    rng = np.random.default_rng(0)
    V, F, tool = _object_and_tool()
    X = _random_step(rng, V, tool)[:4]
    so, st = Surface.from_faces(F, len(V)), Surface.from_faces(tool.faces, len(tool.vertices))
    cand = step_candidates(*X[:2], so, *X[2:], st)

    def boxes(X0, X1, prims):
        P = np.concatenate([X0[prims], X1[prims]], axis=1)
        return P.min(1), P.max(1)

    vlo, vhi = np.minimum(X[0], X[1]), np.maximum(X[0], X[1])
    assert set(map(tuple, cand.vf)) == brute_box_pairs(vlo, vhi, *boxes(X[2], X[3], st.faces))
    tlo, thi = np.minimum(X[2], X[3]), np.maximum(X[2], X[3])
    assert set(map(tuple, cand.fv)) == brute_box_pairs(tlo, thi, *boxes(X[0], X[1], so.faces))
    assert set(map(tuple, cand.ee)) == brute_box_pairs(*boxes(X[0], X[1], so.edges), *boxes(X[2], X[3], st.edges))


def test_sdf_culling_keeps_every_colliding_pair():
    rng = np.random.default_rng(1)
    V, F, tool = _object_and_tool()
    plain = CollisionDetector(F, tool.faces, len(V), len(tool.vertices))
    sdf = CollisionDetector(F, tool.faces, len(V), len(tool.vertices), tool=tool)
    total_hits = 0
    for _ in range(12):
        X = _random_step(rng, V, tool)
        hits, res_plain = _exact_hits(plain, X[:4])
        res = sdf.detect(*X)
        for kind in ("vf", "fv", "ee"):
            assert hits[kind] <= set(map(tuple, getattr(res.candidates, kind))), kind
            assert hits[kind] <= set(map(tuple, getattr(res.survivors, kind))), kind
            # The fast narrow phase finds the same crossings as ipctk here.
            ours = set(map(tuple, getattr(res.survivors, kind)[getattr(res, kind).hit]))
            assert len(ours ^ hits[kind]) <= max(1, len(hits[kind]) // 50)
            total_hits += len(hits[kind])
        assert res.candidates.total() <= res_plain.candidates.total()
    assert total_hits > 20  # the steps really collide


def test_active_candidates_are_the_full_candidates_of_the_active_primitives():
    """``step_candidates(active=...)``, with and without SDF culling, gives exactly the pairs of the full call whose
    object primitive has an active vertex; the ring holds every vertex of those primitives."""
    rng = np.random.default_rng(4)
    V, F, tool = _object_and_tool()
    so, st = Surface.from_faces(F, len(V)), Surface.from_faces(tool.faces, len(tool.vertices))
    prims = {"vf": lambda i: [i], "fv": lambda f: so.faces[f], "ee": lambda e: so.edges[e]}
    kept = 0
    for trial in range(8):
        X = _random_step(rng, V, tool)
        active = rng.random(len(V)) < (0.02 if trial % 2 else 0.3)
        ring = active_ring(active, so)
        for f in range(len(F)):
            if active[F[f]].any():
                assert np.isin(F[f], ring).all()
        for bound in (None, ToolSDFBound(tool)):
            kw = dict(tool_bound=bound, tool_pose_t0=X[4], tool_pose_t1=X[5], cache={})
            full = step_candidates(*X[:2], so, *X[2:4], st, **kw)
            part = step_candidates(*X[:2], so, *X[2:4], st, active=active, **kw)
            for kind in ("vf", "fv", "ee"):
                col = 0 if kind != "fv" else 1
                want = {tuple(r) for r in getattr(full, kind) if active[prims[kind](r[col])].any()}
                assert {tuple(r) for r in getattr(part, kind)} == want, kind
                kept += len(want)
    assert kept > 50


def test_changed_rows_matches_numpy():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(500, 3))
    B = A.copy()
    B[rng.random(500) < 0.1, rng.integers(0, 3)] += 1e-12
    assert np.array_equal(changed_rows(A, B), np.any(A != B, axis=1))
    assert 20 < changed_rows(A, B).sum() < 100


def test_tool_bounds_for_every_shape_and_lipschitz_sdf():
    rng = np.random.default_rng(2)
    shapes = {"sphere": {"radius": 0.05}, "cylinder": {"radius": 0.02, "height": 0.1},
              "cone": {"radius": 0.02, "height": 0.07, "tip_radius": 0.0},
              "blade": {"length": 0.1, "height": 0.03, "thickness": 0.004, "bevel": 0.01}}
    for shape, params in shapes.items():
        tool = make_tool(shape, params, "ci")
        b = ToolSDFBound(tool)
        assert b.usable, shape
        assert 0 <= b.margin < 1e-6, shape
        # Culling relies on the SDF being 1-Lipschitz and exact outside.
        x = rng.normal(scale=0.06, size=(4000, 3))
        y = x + rng.normal(scale=0.01, size=(4000, 3))
        dx, dy = tool.sdf_local(x), tool.sdf_local(y)
        assert np.all(np.abs(dx - dy) <= np.linalg.norm(x - y, axis=1) * (1 + 1e-9) + 1e-12), shape
        # ... and a lower bound of the distance to the mesh (+ margin) at every mesh vertex.
        assert np.all(tool.sdf_local(tool.vertices) <= b.margin)


def test_non_convex_tool_disables_sdf_culling():
    tool = make_tool("cone", {"radius": 0.02, "height": 0.07, "tip_radius": 0.0}, "ci")
    V = tool.vertices.copy()
    V[np.argmax(V[:, 2])] -= [0, 0, 0.06]  # push the base centre inwards: a dent
    dented = type(tool)(shape=tool.shape, params=tool.params, vertices=V, faces=tool.faces)
    assert not ToolSDFBound(dented).usable


def test_cone_bunny_contact_step_keeps_every_exact_hit():
    from colgnn_core.evaluation.collision_speed import contact_step
    from colgnn_core.scenes import load_scene

    scene = load_scene("cone_bunny", "ci")
    step = contact_step(scene.object.vertices, scene.object.faces, scene.tool, scene.tool_rest_pose,
                        press=0.016)
    X = (step["object_t0"], step["object_t1"], step["tool_t0"], step["tool_t1"])
    n, m = len(X[0]), len(X[2])
    hits, _ = _exact_hits(CollisionDetector(scene.object.faces, scene.tool.faces, n, m), X)
    res = CollisionDetector(scene.object.faces, scene.tool.faces, n, m, tool=scene.tool).detect(
        *X, step["tool_pose_t0"], step["tool_pose_t1"])
    for kind in ("vf", "fv", "ee"):
        assert hits[kind] <= set(map(tuple, getattr(res.survivors, kind)))
    assert sum(len(h) for h in hits.values()) > 0


def test_bad_positions_raise():
    V, F, tool = _object_and_tool()
    det = CollisionDetector(F, tool.faces, len(V), len(tool.vertices))
    T = tool.vertices
    bad = V.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        det.detect(V, bad, T, T)
    with pytest.raises(InputError, match="object_t1"):
        det.detect(V, V[:-1], T, T)
    with pytest.raises(InputError):
        CollisionDetector(F, tool.faces, len(V), len(tool.vertices) + 1, tool=tool)
    assert CandidatePairs().total() == 0


def test_real_contact_step_culls_at_least_95_percent():
    """Solver ground truth (tests/data/cone_bunny_full_contact.npz): cone pressed into the bunny."""
    from pathlib import Path

    # The cone the data was generated with (cone_bunny.toml at the time), checked against the data.
    tool = make_tool("cone", {"radius": 0.018, "height": 0.07, "tip_radius": 0.0}, "full")
    with np.load(Path(__file__).parent / "data" / "cone_bunny_full_contact.npz") as d:
        X = [d[k][i].astype(np.float64) for k, i in (("object_positions", 1), ("object_positions", 2),
                                                       ("tool_positions", 1), ("tool_positions", 2))]
        poses, of, tf = d["tool_poses"][1:3], d["object_faces"], d["tool_faces"]
    np.testing.assert_allclose(tool.world_vertices(poses[0]), X[2], atol=1e-6)
    det = CollisionDetector(of, tf, len(X[0]), len(X[2]), tool=tool)
    res = det.detect(*X, *poses)
    n_c, n_s = res.candidates.total(), res.survivors.total()
    assert len(det.object_surface.vertices) > 3000 and n_c > 300
    assert 1 - n_s / n_c >= 0.95
    assert res.summary()["N_vf"] == 0 and res.summary()["N_ee"] == 0


def test_tool_positions_must_match_the_posed_tool():
    rng = np.random.default_rng(5)
    V, F, tool = _object_and_tool()
    X = list(_random_step(rng, V, tool))
    det = CollisionDetector(F, tool.faces, len(V), len(tool.vertices), tool=tool)
    X[3] = X[3] + 0.01  # tool positions do not belong to pose t1
    with pytest.raises(InputError, match="differ from the tool mesh"):
        det.detect(*X)
    X[3] = X[3] - 0.01 + 1e-9  # float32-like noise: accepted, margin widened
    det.detect(*X)


def test_filter_pairs_matches_detector_survivors():
    from colgnn_core.collision.pipeline import filter_pairs

    rng = np.random.default_rng(6)
    V, F, tool = _object_and_tool()
    X = _random_step(rng, V, tool)
    det = CollisionDetector(F, tool.faces, len(V), len(tool.vertices), tool=tool)
    res = det.detect(*X)
    for kind in ("vf", "fv", "ee"):
        pairs = getattr(res.candidates, kind)
        keep = filter_pairs(kind, pairs, *X[:4], det.object_surface, det.tool_surface)
        np.testing.assert_array_equal(pairs[keep], getattr(res.survivors, kind))
