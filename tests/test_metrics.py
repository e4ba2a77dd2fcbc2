"""Collision metrics on hand-built cases with values computed by hand, plus the file-level API."""

import numpy as np
import pytest

from colgnn_core.collision import exact
from colgnn_core.collision.metrics import (file_metrics, frame_penetrations, pair_metrics, sequence_metrics,
                                           step_crossings, triangle_pairs_intersecting)
from colgnn_core.errors import InputError
from colgnn_core.io import Sequence, save_sequence


def tet_faces(V):
    """Outward faces of the tetrahedron V [4,3]."""
    F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    c = V.mean(axis=0)
    out = []
    for f in F:
        n = np.cross(V[f[1]] - V[f[0]], V[f[2]] - V[f[0]])
        out.append(f if n @ (V[f[0]] - c) > 0 else f[[0, 2, 1]])
    return np.array(out)


# Case 1: an object tetrahedron's lowest vertex goes through the top face (z = 0) of the tool.
TOOL1 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.25, 0.25, -1]])
OBJ1 = np.array([[0.25, 0.25, 0.1], [0.2, 0.2, 0.5], [0.35, 0.2, 0.5], [0.2, 0.35, 0.5]])
DOWN1 = np.array([0, 0, -0.3])

# Case 2: two ridges cross: the object's bottom edge (along y) passes the tool's top edge (along x).
TOOL2 = np.array([[-1.0, 0, 0], [1, 0, 0], [0, 1, -1], [0, -1, -1]])


def obj2(z):
    return np.array([[0.0, -1, z], [0, 1, z], [1, 0, z + 1], [-1, 0, z + 1]])


def test_one_vertex_through_one_face():
    r = step_crossings(OBJ1, OBJ1 + DOWN1, tet_faces(OBJ1), TOOL1, TOOL1, tet_faces(TOOL1))
    assert r == {"N_vf": 1, "d_vf_mean": pytest.approx(0.2), "d_vf_max": pytest.approx(0.2),
                 "N_ee": 0, "d_ee_mean": 0.0, "d_ee_max": 0.0}
    fast = step_crossings(OBJ1, OBJ1 + DOWN1, tet_faces(OBJ1), TOOL1, TOOL1, tet_faces(TOOL1), exact=False)
    assert fast["N_vf"] == 1 and fast["d_vf_max"] == pytest.approx(0.2) and fast["N_ee"] == 0
    p = frame_penetrations(OBJ1 + DOWN1, tet_faces(OBJ1), TOOL1, tet_faces(TOOL1))
    # The three object faces around the vertex cut the tool's top face.
    assert p == {"object_vertices_inside": 1, "tool_vertices_inside": 0, "intersecting_triangle_pairs": 3}
    assert exact.has_intersections(OBJ1 + DOWN1, tet_faces(OBJ1), TOOL1, tet_faces(TOOL1))
    assert not exact.is_step_collision_free(OBJ1, OBJ1 + DOWN1, tet_faces(OBJ1), TOOL1, TOOL1, tet_faces(TOOL1))


def test_tool_moving_instead_of_object_gives_the_same_crossing():
    # Relative motion is what matters: the tool moves up by 0.3 instead.
    r = step_crossings(OBJ1, OBJ1, tet_faces(OBJ1), TOOL1, TOOL1 - DOWN1, tet_faces(TOOL1))
    assert r["N_vf"] == 1 and r["d_vf_max"] == pytest.approx(0.2) and r["N_ee"] == 0


def test_two_crossing_edges():
    r = step_crossings(obj2(0.5), obj2(-0.2), tet_faces(obj2(0.5)), TOOL2, TOOL2, tet_faces(TOOL2))
    # Perpendicular ridges 0.2 apart at t+1, on the wrong side.
    assert r == {"N_vf": 0, "d_vf_mean": 0.0, "d_vf_max": 0.0,
                 "N_ee": 1, "d_ee_mean": pytest.approx(0.2), "d_ee_max": pytest.approx(0.2)}
    p = frame_penetrations(obj2(-0.2), tet_faces(obj2(0.5)), TOOL2, tet_faces(TOOL2))
    # No vertex is inside; the two faces at each ridge cut each other: 2 x 2 pairs.
    assert p == {"object_vertices_inside": 0, "tool_vertices_inside": 0, "intersecting_triangle_pairs": 4}
    assert exact.has_intersections(obj2(-0.2), tet_faces(obj2(0.5)), TOOL2, tet_faces(TOOL2))
    # Stopping just above the ridge: nothing.
    r = step_crossings(obj2(0.5), obj2(0.01), tet_faces(obj2(0.5)), TOOL2, TOOL2, tet_faces(TOOL2))
    assert r["N_vf"] == 0 and r["N_ee"] == 0


def test_tool_fully_inside_the_object():
    big = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    small = np.array([[1.0, 1, 1], [2, 1, 1], [1, 2, 1], [1, 1, 2]])
    p = frame_penetrations(big, tet_faces(big), small, tet_faces(small))
    assert p == {"object_vertices_inside": 0, "tool_vertices_inside": 4, "intersecting_triangle_pairs": 0}
    assert not exact.has_intersections(big, tet_faces(big), small, tet_faces(small))
    r = step_crossings(big, big, tet_faces(big), small, small, tet_faces(small))
    assert r["N_vf"] == 0 and r["N_ee"] == 0
    # Object inside the tool: every object vertex counts.
    p = frame_penetrations(small, tet_faces(small), big, tet_faces(big))
    assert p["object_vertices_inside"] == 4 and p["tool_vertices_inside"] == 0


def test_analytic_sdf_option():
    from colgnn_core.geometry.tools import make_tool

    tool = make_tool("sphere", {"radius": 0.1}, "ci")
    pose = np.array([0.0, 0, 0, 0, 0, 0, 1])
    V = np.array([[0.0, 0, 0.05], [0.3, 0, 0], [0.3, 0.1, 0], [0.3, 0, 0.1]])
    p = frame_penetrations(V, tet_faces(V), tool.world_vertices(pose), tool.faces, tool=tool, tool_pose=pose)
    assert p["object_vertices_inside"] == 1


def test_triangle_pairs_match_ipctk_edge_triangle_test():
    import ipctk

    rng = np.random.default_rng(0)
    for _ in range(30):
        A = rng.normal(size=(4, 3))
        B = rng.normal(size=(4, 3)) * 0.8 + rng.normal(size=3) * 0.5
        FA, FB = tet_faces(A), tet_faces(B)
        ours = set(map(tuple, triangle_pairs_intersecting(A, FA, B, FB)))
        ref = set()
        for i, fa in enumerate(FA):
            for j, fb in enumerate(FB):
                hit = any(ipctk.is_edge_intersecting_triangle(A[fa[k]], A[fa[(k + 1) % 3]], *B[fb]) for k in range(3)) \
                    or any(ipctk.is_edge_intersecting_triangle(B[fb[k]], B[fb[(k + 1) % 3]], *A[fa]) for k in range(3))
                if hit:
                    ref.add((i, j))
        assert ours == ref
        assert bool(ours) == exact.has_intersections(A, FA, B, FB)


def _sequence(obj_frames, tool_frames, obj_faces, tool_faces):
    T = len(obj_frames)
    poses = np.tile([0.0, 0, 0, 0, 0, 0, 1], (T, 1))
    return Sequence(np.asarray(obj_frames), obj_faces, np.asarray(tool_frames), tool_faces, poses, 0.04)


def test_sequence_and_files(tmp_path):
    F1, G1 = tet_faces(OBJ1), tet_faces(TOOL1)
    # Ground truth stops above the face; the rollout goes through it.
    gt = _sequence([OBJ1, OBJ1 + DOWN1 / 4, OBJ1 + DOWN1 / 3], [TOOL1] * 3, F1, G1)
    ro = _sequence([OBJ1, OBJ1 + DOWN1 / 4, OBJ1 + DOWN1], [TOOL1] * 3, F1, G1)
    m = sequence_metrics(gt)
    assert m["steps"]["N_vf"] == [0, 0] and m["frames"]["object_vertices_inside"] == [0, 0, 0]
    assert all(v == 0 for v in m["summary"].values())
    save_sequence(tmp_path / "gt.npz", gt)
    save_sequence(tmp_path / "ro.npz", ro)
    r = file_metrics(tmp_path / "ro.npz")
    assert r["steps"]["N_vf"] == [0, 1] and r["steps"]["d_vf_max"][1] == pytest.approx(0.2)
    assert r["frames"]["object_vertices_inside"] == [0, 0, 1]
    assert r["summary"]["N_vf"] == pytest.approx(0.5) and r["summary"]["N_vf_max"] == 1
    assert r["summary"]["d_vf_max"] == pytest.approx(0.2) and r["summary"]["d_vf_pooled_mean"] == pytest.approx(0.2)
    assert r["summary"]["d_vf_mean"] == pytest.approx(0.1)  # mean over the two steps (0 and 0.2)
    both = pair_metrics(tmp_path / "gt.npz", tmp_path / "ro.npz")
    assert both["ground_truth"]["summary"]["N_vf"] == 0 and both["rollout"]["summary"]["N_vf_total"] == 1
    other = _sequence([obj2(0.5)] * 3, [TOOL2] * 3, tet_faces(obj2(0.5))[::-1], tet_faces(TOOL2))
    save_sequence(tmp_path / "other.npz", other)
    with pytest.raises(InputError, match="different object meshes"):
        pair_metrics(tmp_path / "gt.npz", tmp_path / "other.npz")


def test_bad_input_raises():
    F, G = tet_faces(OBJ1), tet_faces(TOOL1)
    with pytest.raises(InputError, match="non-empty"):
        step_crossings(np.zeros((0, 3)), np.zeros((0, 3)), F, TOOL1, TOOL1, G)
    bad = OBJ1.copy()
    bad[2, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        step_crossings(OBJ1, bad, F, TOOL1, TOOL1, G)
    with pytest.raises(InputError, match="NaN"):
        frame_penetrations(bad, F, TOOL1, G)
    with pytest.raises(InputError, match="expected 4"):
        step_crossings(OBJ1, OBJ1[:3], F, TOOL1, TOOL1, G)
    with pytest.raises(InputError, match="index out of range"):
        step_crossings(OBJ1[:3], OBJ1[:3], F, TOOL1, TOOL1, G)
    with pytest.raises(InputError, match="faces"):
        frame_penetrations(OBJ1, np.zeros((0, 3), dtype=int), TOOL1, G)
    with pytest.raises(InputError):
        file_metrics("/nonexistent/seq.npz")


def load_gt_contact():
    from pathlib import Path

    with np.load(Path(__file__).parent / "data" / "cone_bunny_full_contact.npz") as d:
        return Sequence(d["object_positions"].astype(np.float64), d["object_faces"].astype(np.int64),
                        d["tool_positions"].astype(np.float64), d["tool_faces"].astype(np.int64),
                        d["tool_poses"], float(d["dt"]))


def test_ground_truth_solver_frames_report_zero_everywhere():
    seq = load_gt_contact()
    for exact_mode in (True, False):
        m = sequence_metrics(seq, exact=exact_mode)
        assert all(v == 0 for v in m["summary"].values()), m["summary"]
        assert len(m["steps"]["N_vf"]) == 2 and len(m["frames"]["object_vertices_inside"]) == 3
    for t in range(2):
        assert exact.is_step_collision_free(seq.object_positions[t], seq.object_positions[t + 1], seq.object_faces,
                                            seq.tool_positions[t], seq.tool_positions[t + 1], seq.tool_faces)


def test_points_inside_mesh_matches_winding_numbers():
    from colgnn_core.geometry.tools import make_tool

    rng = np.random.default_rng(1)
    for shape, params in (("cylinder", {"radius": 0.02, "height": 0.1}), ("sphere", {"radius": 0.05}),
                          ("blade", {"length": 0.1, "height": 0.03, "thickness": 0.004, "bevel": 0.01})):
        t = make_tool(shape, params, "ci")
        lo, hi = t.vertices.min(0), t.vertices.max(0)
        P = rng.uniform(lo - 0.01, hi + 0.01, size=(1500, 3))
        k = min(100, len(t.vertices))
        P[:k] = t.vertices[:k]  # on the surface: ambiguous, resolved by the winding number
        ref = exact.winding_numbers(t.vertices, t.faces, P) > 0.5
        np.testing.assert_array_equal(exact.points_inside_mesh(t.vertices, t.faces, P), ref)
