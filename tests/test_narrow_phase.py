"""Narrow phase: crossing test, time of impact, depth at t+1 (numpy) and differentiable depths (torch)."""

import numpy as np
import pytest
import torch

from colgnn_core.collision import exact
from colgnn_core.collision.narrow_phase import (cubic_roots_01, edge_edge_depth_torch, edge_edge_narrow,
                                                sdf_depth_torch, vertex_face_depth_torch, vertex_face_narrow)
from colgnn_core.errors import InputError
from tests.helpers import collision_cases as cc

A, B, C = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])


def cols(q):
    return [q[:, i] for i in range(8)]


def test_vertex_through_face_hand_values():
    # p goes from z=1 to z=-0.5 through (0.2, 0.2, 0): crossing at t = 2/3, 0.5 m behind the face.
    r = vertex_face_narrow(np.array([[0.2, 0.2, 1.0]]), A, B, C, np.array([[0.2, 0.2, -0.5]]), A, B, C)
    assert r.hit.tolist() == [True] and not r.degenerate[0]
    assert r.toi[0] == pytest.approx(2 / 3, abs=1e-12)
    assert r.depth[0] == pytest.approx(0.5, abs=1e-12)


def test_vertex_beside_face_is_not_a_crossing():
    # Crosses the plane z = 0 at (2, 2, 0): outside the triangle.
    r = vertex_face_narrow(np.array([[2.0, 2.0, 1.0]]), A, B, C, np.array([[2.0, 2.0, -1.0]]), A, B, C)
    assert r.hit.tolist() == [False] and r.depth[0] == 0.0 and np.isinf(r.toi[0])


def test_moving_face_hits_static_vertex():
    p = np.array([[0.25, 0.25, 0.0]])
    up = np.array([[0.0, 0.0, 0.4]])
    r = vertex_face_narrow(p, A - up, B - up, C - up, p, A + up, B + up, C + up)
    assert r.hit[0] and r.toi[0] == pytest.approx(0.5, abs=1e-12) and r.depth[0] == pytest.approx(0.4)


def test_edge_edge_crossing_hand_values():
    ea0, ea1 = np.array([[-1.0, 0, 1]]), np.array([[1.0, 0, 1]])
    eb0, eb1 = np.array([[0.0, -1, 0]]), np.array([[0.0, 1, 0]])
    d = np.array([[0.0, 0, -1.25]])
    r = edge_edge_narrow(ea0, ea1, eb0, eb1, ea0 + d, ea1 + d, eb0, eb1)
    assert r.hit[0] and r.toi[0] == pytest.approx(0.8, abs=1e-12) and r.depth[0] == pytest.approx(0.25)
    # Shifted sideways: the lines cross but the segments miss.
    s = np.array([[3.0, 0, 0]])
    r = edge_edge_narrow(ea0 + s, ea1 + s, eb0, eb1, ea0 + s + d, ea1 + s + d, eb0, eb1)
    assert not r.hit[0]


def test_agrees_with_ipctk_on_generated_pairs():
    rng = np.random.default_rng(1)
    for kind, gen, ours, oracle in (("vf", cc.colliding_vf, vertex_face_narrow, exact.ccd_vertex_face),
                                     ("ee", cc.colliding_ee, edge_edge_narrow, exact.ccd_edge_edge)):
        hit_q = gen(rng, 100)
        miss_q = cc.random_pairs(rng, 400)
        q = np.concatenate([hit_q, miss_q])
        r = ours(*cols(q))
        h, toi = oracle(*cols(q))
        assert r.hit[:100].all(), kind
        # Away from grazing contacts the two must agree on (nearly) every pair.
        assert (r.hit == h).mean() > 0.99, kind
        both = r.hit & h
        # Tight-Inclusion reports a conservative (earlier) time within its tolerance.
        assert np.all(r.toi[both] >= toi[both] - 1e-9)
        np.testing.assert_allclose(r.toi[both], toi[both], atol=2e-4)


def test_toi_matches_constructed_contact_time():
    # A vertex inside the triangle at t* = 0.37 (all points move linearly through their t* positions).
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(200, 3, 3))
    p = tri.mean(axis=1)
    v = rng.normal(size=(200, 4, 3))
    x = np.concatenate([p[:, None], tri], axis=1)
    q = np.concatenate([x - 0.37 * v, x + 0.63 * v], axis=1)
    r = vertex_face_narrow(*cols(q))
    assert r.hit.all()
    assert np.all(r.toi <= 0.37 + 1e-9)  # an earlier contact is possible, a later one is not
    assert np.mean(np.abs(r.toi - 0.37) < 1e-9) > 0.5


def test_cubic_roots_match_numpy():
    rng = np.random.default_rng(4)
    b = rng.normal(size=(500, 4))
    roots = cubic_roots_01(b)
    for i in range(500):
        bb = b[i]
        c = [bb[3] - 3 * bb[2] + 3 * bb[1] - bb[0], 3 * (bb[0] - 2 * bb[1] + bb[2]), 3 * (bb[1] - bb[0]), bb[0]]
        ref = np.sort([z.real for z in np.roots(c) if abs(z.imag) < 1e-9 and -1e-12 <= z.real <= 1 + 1e-12])
        got = roots[i][~np.isnan(roots[i])]
        # Double roots without a sign change may be skipped; simple roots never.
        if len(ref) and np.min(np.abs(np.diff(np.r_[ref, 2.0]))) > 1e-6:
            np.testing.assert_allclose(np.sort(got), ref, atol=1e-9)


def test_torch_depths_match_numpy_and_have_gradients():
    rng = np.random.default_rng(2)
    q = cc.colliding_vf(rng, 50)
    r = vertex_face_narrow(*cols(q))
    t = [torch.tensor(x, requires_grad=True) for x in cols(q)]
    d = vertex_face_depth_torch(*t)
    np.testing.assert_allclose(d.detach().numpy()[r.hit], r.depth[r.hit], rtol=1e-10, atol=1e-14)
    d.sum().backward()
    assert t[4].grad is not None and torch.isfinite(t[4].grad).all()

    q = cc.colliding_ee(rng, 50)
    r = edge_edge_narrow(*cols(q))
    t = [torch.tensor(x) for x in cols(q)]
    d = edge_edge_depth_torch(*t)
    np.testing.assert_allclose(d.numpy()[r.hit], r.depth[r.hit], rtol=1e-10, atol=1e-14)


def test_torch_depth_gradcheck():
    p0 = torch.tensor([[0.2, 0.2, 1.0]], dtype=torch.float64)
    a, b, c = (torch.tensor(x, dtype=torch.float64) for x in (A, B, C))

    def f(p1, a1, b1, c1):
        return vertex_face_depth_torch(p0, a, b, c, p1, a1, b1, c1)

    inputs = (torch.tensor([[0.25, 0.2, -0.3]], dtype=torch.float64, requires_grad=True),
              torch.tensor([[0.0, 0.05, 0.01]], dtype=torch.float64, requires_grad=True),
              torch.tensor([[1.0, 0.0, -0.02]], dtype=torch.float64, requires_grad=True),
              torch.tensor([[0.1, 1.0, 0.03]], dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(f, inputs)
    # Moving the vertex further through the face increases the depth one-for-one.
    p1 = inputs[0].detach().clone().requires_grad_(True)
    vertex_face_depth_torch(p0, a, b, c, p1, a, b, c).sum().backward()
    np.testing.assert_allclose(p1.grad.numpy(), [[0.0, 0.0, -1.0]], atol=1e-12)

    ea0 = torch.tensor([[-1.0, 0, 1]], dtype=torch.float64)
    ea1 = torch.tensor([[1.0, 0, 1]], dtype=torch.float64)
    eb0 = torch.tensor([[0.0, -1, 0]], dtype=torch.float64)
    eb1 = torch.tensor([[0.0, 1, 0]], dtype=torch.float64)

    def g(u1, v1):
        return edge_edge_depth_torch(ea0, ea1, eb0, eb1, u1, v1, eb0, eb1)

    assert torch.autograd.gradcheck(g, (torch.tensor([[-1.0, 0.1, -0.25]], dtype=torch.float64, requires_grad=True),
                                        torch.tensor([[1.0, -0.05, -0.2]], dtype=torch.float64, requires_grad=True)))


def test_sdf_depth_torch_with_a_tool():
    from colgnn_core.geometry.tools import make_tool

    tool = make_tool("sphere", {"radius": 0.1}, "ci")
    pose = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    pts = torch.tensor([[0.0, 0.0, 0.05], [0.0, 0.3, 0.0]], dtype=torch.float64, requires_grad=True)
    d = sdf_depth_torch(tool, pts, pose)
    np.testing.assert_allclose(d.detach().numpy(), [0.05, 0.0], atol=1e-12)
    d.sum().backward()
    np.testing.assert_allclose(pts.grad.numpy(), [[0, 0, -1.0], [0, 0, 0]], atol=1e-9)


def test_degenerate_pairs_are_flagged_not_hit():
    # Everything in the plane z = 0 for the whole step: f == 0, flagged as degenerate.
    p0, p1 = np.array([[0.2, 0.2, 0.0]]), np.array([[0.3, 0.2, 0.0]])
    r = vertex_face_narrow(p0, A, B, C, p1, A, B, C)
    assert r.degenerate[0] and not r.hit[0]


def test_bad_shapes_raise():
    with pytest.raises(InputError):
        vertex_face_narrow(np.zeros((2, 3)), A, B, C, A, A, B, C)
    with pytest.raises(InputError):
        edge_edge_narrow(*([np.zeros((1, 2))] * 8))
    with pytest.raises(InputError):
        sdf_depth_torch(None, np.zeros((2, 3)), np.zeros(7))


def test_detector_crossing_depths_torch_for_the_loss():
    from colgnn_core.collision.pipeline import CollisionDetector

    tool = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.25, 0.25, -1]])
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    obj = np.array([[0.25, 0.25, 0.1], [0.2, 0.2, 0.5], [0.35, 0.2, 0.5], [0.2, 0.35, 0.5]])
    of = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    det = CollisionDetector(of, tf, 4, 4)
    x1 = torch.tensor(obj + [0, 0, -0.3], requires_grad=True)
    d = det.crossing_depths_torch(obj, x1, tool, tool)
    assert d["vertex_face"].shape == (1,) and d["edge_edge"].shape == (0,)
    assert d["vertex_face"].item() == pytest.approx(0.2)
    loss = d["vertex_face"].max() + (d["edge_edge"].max() if len(d["edge_edge"]) else 0.0)
    loss.backward()
    np.testing.assert_allclose(x1.grad.numpy()[0], [0, 0, -1.0], atol=1e-12)
    assert np.all(x1.grad.numpy()[1:] == 0)
