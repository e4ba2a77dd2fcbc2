import numpy as np
import pytest
import torch

from colgnn_core.learn.graph import (NODE_OBJECT, NODE_PINNED, NODE_TOOL, build_graph, face_edges, find_world_edges,
                                     lift_to_mesh, make_template, tet_edges)
from tests.helpers.learn_meshes import box_and_sphere, box_tet_mesh, sphere_points, sphere_sdf

torch.set_num_threads(1)


def brute_force_pairs(obj, tool, r):
    d = np.linalg.norm(obj[:, None, :] - tool[None, :, :], axis=2)
    i, j = np.nonzero(d <= r)
    return i, j  # np.nonzero is row-major: sorted by object id then tool id


def frame(verts, tool_local, centre, step=(0.0, 0.0, -0.004), seed=0):
    rng = np.random.default_rng(seed)
    x_prev = verts + rng.normal(scale=1e-3, size=verts.shape)
    x_t = verts + rng.normal(scale=1e-3, size=verts.shape)
    pose_next = np.array([*centre, 0, 0, 0, 1.0])
    tool_next = tool_local + pose_next[:3]
    tool_t = tool_next - np.asarray(step)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))
    return t(x_prev), t(x_t), t(tool_t), t(tool_next), pose_next


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("use_sdf", [False, True])
def test_world_edges_match_brute_force(seed, use_sdf):
    rng = np.random.default_rng(seed)
    obj = rng.uniform(0, 0.1, size=(400, 3))
    tool_r = 0.03
    centre = rng.uniform(0.02, 0.08, size=3)
    tool = sphere_points(80, tool_r, seed) + centre
    pose = np.array([*centre, 0, 0, 0, 1.0])
    r = 0.012
    i, j = find_world_edges(obj, tool, r, sphere_sdf(tool_r) if use_sdf else None, pose, 0.0)
    bi, bj = brute_force_pairs(obj, tool, r)
    assert len(bi) > 10
    np.testing.assert_array_equal(i, bi)
    np.testing.assert_array_equal(j, bj)


def test_sdf_culling_margin_covers_tessellation_error():
    # Tool vertices off the ideal surface by up to 2 mm: culling with the measured margin stays exact.
    rng = np.random.default_rng(3)
    tool_local = sphere_points(100, 0.03, 3) * rng.uniform(0.94, 1.0, size=(100, 1))
    margin = float(np.abs(np.linalg.norm(tool_local, axis=1) - 0.03).max())
    centre = np.array([0.05, 0.05, 0.05])
    obj = rng.uniform(0, 0.1, size=(500, 3))
    r = 0.01
    i, j = find_world_edges(obj, tool_local + centre, r, sphere_sdf(0.03), np.array([*centre, 0, 0, 0, 1.0]), margin)
    bi, bj = brute_force_pairs(obj, tool_local + centre, r)
    assert len(bi) > 0
    np.testing.assert_array_equal(i, bi)
    np.testing.assert_array_equal(j, bj)


def test_zero_world_edges_when_tool_is_far():
    tpl, verts, tool = box_and_sphere()
    x_prev, x_t, tool_t, tool_next, pose = frame(verts, tool, centre=(5.0, 5.0, 5.0))
    g = build_graph(tpl, x_t, x_prev, tool_t, tool_next, pose)
    assert g.world.features.shape == (0, 4) and g.world.senders.shape == (0,) and g.num_world_pairs == 0
    assert torch.isfinite(g.node_features).all() and torch.isfinite(g.mesh.features).all()
    i, j = find_world_edges(x_t.numpy(), tool_next.numpy(), 0.03)  # no culling either
    assert i.shape == j.shape == (0,)


def test_feature_shapes_and_values():
    tpl, verts, tool = box_and_sphere()
    n, m = verts.shape[0], tool.shape[0]
    x_prev, x_t, tool_t, tool_next, pose = frame(verts, tool, centre=(0.05, 0.05, 0.1))
    g = build_graph(tpl, x_t, x_prev, tool_t, tool_next, pose)
    assert g.num_object_nodes == n
    assert g.node_features.shape == (n + m, 3 + 2) and g.node_features.dtype == torch.float64
    torch.testing.assert_close(g.node_features[:n, :3], x_t - x_prev)
    torch.testing.assert_close(g.node_features[n:, :3], tool_next - tool_t)
    assert (g.node_features[:n, 3 + NODE_OBJECT] == 1).all() and (g.node_features[n:, 3 + NODE_TOOL] == 1).all()
    assert g.node_features[:, 3:].sum(1).eq(1).all()

    # tet edges of the 3x3x2 box, both directions, 8 features
    und = tet_edges(box_tet_mesh()[1])
    assert g.mesh.features.shape == (2 * len(und), 8)
    s, r = g.mesh.senders.numpy(), g.mesh.receivers.numpy()
    assert set(zip(s, r)) == set(map(tuple, und)) | set(map(tuple, und[:, ::-1]))
    d = x_t.numpy()[s] - x_t.numpy()[r]
    dr = verts[s] - verts[r]
    expect = np.concatenate([d, np.linalg.norm(d, axis=1)[:, None], dr, np.linalg.norm(dr, axis=1)[:, None]], 1)
    np.testing.assert_allclose(g.mesh.features.numpy(), expect, rtol=1e-12)

    # world edges: tool -> object then object -> tool, tool placed at t+1
    w = g.num_world_pairs
    assert w > 0 and g.world.features.shape == (2 * w, 4)
    ws, wr = g.world.senders.numpy(), g.world.receivers.numpy()
    assert (ws[:w] >= n).all() and (wr[:w] < n).all()
    np.testing.assert_array_equal(ws[w:], wr[:w])
    np.testing.assert_array_equal(wr[w:], ws[:w])
    pos = np.concatenate([x_t.numpy(), tool_next.numpy()])
    dw = pos[ws] - pos[wr]
    np.testing.assert_allclose(g.world.features.numpy(), np.c_[dw, np.linalg.norm(dw, axis=1)], rtol=1e-12)
    assert (g.world.features[:, 3] <= tpl.world_radius).all()


def test_single_cube_tet_edges():
    verts, tets, faces = box_tet_mesh(1, 1, 1)
    assert len(tets) == 6
    assert len(tet_edges(tets)) == 19  # 12 cube edges + 6 face diagonals + 1 body diagonal
    assert len(face_edges(faces)) == 18


def test_surface_only_graph_and_lift():
    tpl, verts, tool = box_and_sphere(surface_only=True)
    _, tets, faces = box_tet_mesh()
    assert np.array_equal(tpl.object_nodes, np.unique(faces))
    assert len(tpl.interior_ids) == 4  # the 2x2x1 interior grid points of a 3x3x2 box
    assert tpl.mesh_senders.shape[0] == 2 * len(face_edges(faces))
    assert tpl.surface_faces.max() < tpl.num_object_nodes
    # rigid translation of the surface moves interior vertices the same way
    shift = np.array([0.01, -0.02, 0.03])
    full = lift_to_mesh(tpl, tpl.rest.numpy() + shift)
    np.testing.assert_allclose(full, verts + shift, atol=1e-15)
    x = torch.from_numpy(tpl.rest.numpy().copy())
    tl = torch.from_numpy(tool + [0.05, 0.05, 0.11])
    g = build_graph(tpl, x, x, tl, tl, None)
    assert g.node_features.shape[0] == tpl.num_object_nodes + tool.shape[0]


def test_pinned_nodes_get_their_own_type():
    verts, _, _ = box_tet_mesh()
    pinned = np.flatnonzero(verts[:, 2] == 0)
    tpl, verts, tool = box_and_sphere(pinned=pinned)
    assert tpl.num_node_types == 3 and tpl.node_feature_size == 6
    types = tpl.node_one_hot.argmax(1).numpy()
    np.testing.assert_array_equal(np.flatnonzero(types[: len(verts)] == NODE_PINNED), pinned)


def test_builder_is_deterministic():
    tpl, verts, tool = box_and_sphere()
    args = frame(verts, tool, centre=(0.05, 0.05, 0.1), seed=5)
    a = build_graph(tpl, args[1], args[0], *args[2:])
    b = build_graph(tpl, args[1], args[0], *args[2:])
    assert a.num_world_pairs > 0
    for x, y in [(a.node_features, b.node_features), (a.mesh.features, b.mesh.features),
                 (a.world.features, b.world.features), (a.world.senders, b.world.senders)]:
        assert torch.equal(x, y)


def test_wrong_sizes_are_rejected():
    tpl, verts, tool = box_and_sphere()
    x = torch.from_numpy(verts)
    with pytest.raises(ValueError, match="tool nodes"):
        build_graph(tpl, x, x, torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="world_radius"):
        make_template(verts, box_tet_mesh()[1], box_tet_mesh()[2], num_tool_nodes=3, world_radius=0.0)


@pytest.mark.parametrize("name", ["cone_bunny", "knife_torus"])
def test_world_edges_with_scene_tool_sdf_match_brute_force(name):
    from colgnn_core.geometry.transforms import axis_angle_quat
    from colgnn_core.learn.graph import template_from_scene
    from colgnn_core.scenes import load_scene

    scene = load_scene(name, "ci")
    tpl = template_from_scene(scene)
    rng = np.random.default_rng(0)
    x = tpl.rest.numpy() + rng.normal(scale=5e-4, size=tpl.rest.shape)
    lo, hi = scene.object_bbox()
    total = 0
    for _ in range(4):
        pose = np.concatenate([rng.uniform(lo, hi), axis_angle_quat(rng.normal(size=3), rng.uniform(0, 0.6))])
        tool = scene.tool.world_vertices(pose)
        i, j = find_world_edges(x, tool, tpl.world_radius, tpl.tool_sdf, pose, tpl.sdf_margin)
        bi, bj = brute_force_pairs(x, tool, tpl.world_radius)
        np.testing.assert_array_equal(i, bi)
        np.testing.assert_array_equal(j, bj)
        total += len(i)
    assert total > 0
