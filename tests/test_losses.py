"""Collision-aware losses against hand-computed values on tiny cases."""

import numpy as np
import pytest
import torch

from colgnn_core.collision import CollisionDetector
from colgnn_core.learn.losses import loss_ccd, reduce_depths, sdf_violation, xi_random
from colgnn_core.scenes import load_scene

torch.set_num_threads(1)

# Object: a small tet whose apex (vertex 3) points down; tool: a big flat tet whose top face is z = 0.
OBJ_REST = np.array([[0.0, 0.0, 0.01], [0.01, 0.0, 0.01], [0.0, 0.01, 0.01], [0.003, 0.003, 0.001]])
OBJ_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]])  # outward (apex below the base)
TOOL = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
TOOL_FACES = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])


def _ccd_depths(apex_z1: float, dz_all: float = 0.0):
    det = CollisionDetector(OBJ_FACES, TOOL_FACES, 4, 4)
    x0 = torch.from_numpy(OBJ_REST.copy())
    x1 = x0.clone()
    x1[:, 2] += dz_all
    x1[3, 2] = apex_z1
    x1.requires_grad_(True)
    tool = torch.from_numpy(TOOL)
    return det.crossing_depths_torch(x0, x1, tool, tool), x1


def test_vertex_pushed_through_face_gives_its_depth():
    depths, x1 = _ccd_depths(-0.002)  # apex from z = 1 mm to -2 mm, through the tool's top face
    assert depths["vertex_face"].shape == (1,) and depths["edge_edge"].numel() == 0
    loss, vf, ee = loss_ccd(depths, "max", scale=1e-3)
    assert float(vf.detach()) == pytest.approx(2.0, rel=1e-9)  # 2 mm in units of 1 mm
    assert float(ee.detach()) == 0.0 and float(loss.detach()) == pytest.approx(2.0, rel=1e-9)
    loss.backward()
    g = x1.grad.numpy()
    # d(depth)/d(apex z) = -1 (moving it up reduces the depth); nothing else moves the loss
    np.testing.assert_allclose(g[3], [0.0, 0.0, -1e3], atol=1e-9)
    np.testing.assert_allclose(g[:3], 0.0, atol=1e-12)


def test_smooth_forms_on_the_same_case():
    depths, _ = _ccd_depths(-0.002)
    assert float(loss_ccd(depths, "mean", 1e-3)[0].detach()) == pytest.approx(2.0)
    assert float(loss_ccd(depths, "sum_squares", 1e-3, num_nodes=4)[0].detach()) == pytest.approx(4.0 / 4)


def test_no_contact_gives_zero_and_zero_gradient():
    depths, x1 = _ccd_depths(0.0005)  # apex stays above the tool
    assert depths["vertex_face"].numel() == 0 and depths["edge_edge"].numel() == 0
    for form in ("max", "mean", "sum_squares"):
        loss, vf, ee = loss_ccd(depths, form)
        assert float(loss.detach()) == 0.0
        (loss + (x1 * 0.0).sum()).backward()
        assert torch.count_nonzero(x1.grad) == 0
        x1.grad = None


def test_reductions_by_hand():
    d = torch.tensor([1e-3, 3e-3, 2e-3])
    assert float(reduce_depths(d, "max", 1e-3)) == pytest.approx(3.0)
    assert float(reduce_depths(d, "mean", 1e-3)) == pytest.approx(2.0)
    assert float(reduce_depths(d, "sum_squares", 1e-3, num_nodes=7)) == pytest.approx((1 + 9 + 4) / 7)
    two = {"vertex_face": torch.tensor([1e-3, 4e-3]), "edge_edge": torch.tensor([2e-3])}
    loss, vf, ee = loss_ccd(two, "max", 1e-3)
    assert (float(loss.detach()), float(vf.detach()), float(ee.detach())) == pytest.approx((6.0, 4.0, 2.0))
    with pytest.raises(ValueError):
        reduce_depths(d, "softmax")


def test_xi_random_against_the_sphere_sdf():
    tool = load_scene("sphere_mat", "ci").tool
    r = tool.params["radius"]
    pose = np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0])
    delta = 1e-3
    # point 0: 2 mm inside; point 1: 0.5 mm outside (within delta); point 2: far (no violation)
    pts = torch.tensor([[0.0, 0.0, 0.1 - r + 0.002], [r + 0.0005, 0.0, 0.1], [0.3, 0.0, 0.1]],
                       dtype=torch.float64, requires_grad=True)
    v = sdf_violation(tool, pts, pose, delta)
    np.testing.assert_allclose(v.detach().numpy(), [delta + 0.002, delta - 0.0005, 0.0], atol=1e-12)
    loss = xi_random(tool, pts, pose, delta, "max", scale=1e-3)
    assert float(loss.detach()) == pytest.approx(3.0)
    loss.backward()
    # gradient of -sdf at the bottom point: +z (pushing it up, towards the centre, deepens it)
    np.testing.assert_allclose(pts.grad[0].numpy(), [0.0, 0.0, 1e3], atol=1e-6)
    np.testing.assert_allclose(pts.grad[1:].numpy(), 0.0, atol=1e-12)
    mean = xi_random(tool, pts.detach(), pose, delta, "mean", scale=1e-3)
    assert float(mean.detach()) == pytest.approx((3.0 + 0.5) / 2)
    sq = xi_random(tool, pts.detach(), pose, delta, "sum_squares", scale=1e-3)
    assert float(sq.detach()) == pytest.approx((9.0 + 0.25) / 3)


def test_xi_random_zero_and_zero_gradient_away_from_the_tool():
    tool = load_scene("sphere_mat", "ci").tool
    pose = np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0])
    pts = torch.tensor([[0.2, 0.0, 0.1], [0.0, 0.2, 0.1]], dtype=torch.float64, requires_grad=True)
    for form in ("max", "mean", "sum_squares"):
        loss = xi_random(tool, pts, pose, 1e-3, form, mask=torch.tensor([True, True]))
        assert float(loss.detach()) == 0.0
        loss.backward()
        assert torch.count_nonzero(pts.grad) == 0
        pts.grad = None


def _tet_surface():
    X = torch.tensor(OBJ_REST, dtype=torch.float64)
    faces = torch.tensor(OBJ_FACES)
    return X, faces


def test_flip_hinge_by_hand():
    """L_valid is 0 at rest and under a rigid turn (aligned), and (min_cos - cos) for a tilted or flipped face."""
    from colgnn_core.learn.losses import SurfaceRest, flip_hinge, unit_normals

    X, faces = _tet_surface()
    rest_n = unit_normals(X, faces)
    eye = torch.eye(3, dtype=torch.float64)
    assert float(flip_hinge(X, faces, rest_n, eye, 0.1)) == 0.0
    # the apex pushed up through the base to z = 0.019: faces 1-3 flip; the base face (0) keeps its normal
    Y = X.clone()
    Y[3, 2] = 0.019
    n = unit_normals(Y, faces)
    cos = (n * rest_n).sum(1)
    assert float(cos[0]) == pytest.approx(1.0) and bool((cos[1:] < 0).all())
    assert float(flip_hinge(Y, faces, rest_n, eye, 0.1)) == pytest.approx(float((0.1 - cos[1:]).sum()))
    # face 1 (z = 0.001 apex, base edge along x): cos by hand from its two edges
    a, b, c = OBJ_REST[0], OBJ_REST[1], np.array([0.003, 0.003, 0.019])
    m = np.cross(b - a, c - a)
    a0, b0, c0 = OBJ_REST[0], OBJ_REST[1], OBJ_REST[3]
    m0 = np.cross(b0 - a0, c0 - a0)
    assert float(cos[1]) == pytest.approx(m @ m0 / np.linalg.norm(m) / np.linalg.norm(m0))
    # the gradient pushes the apex back down (it lowers the loss)
    Y.requires_grad_(True)
    flip_hinge(Y, faces, rest_n, eye, 0.1).backward()
    assert float(Y.grad[3, 2]) > 0.0
    # a rigid turn of the whole tet costs nothing once aligned by the target's rotation (SurfaceRest.loss)
    t = 2.0
    R = torch.tensor([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    turned = X @ R.T + 0.05
    rest = SurfaceRest.of(OBJ_FACES, OBJ_REST)
    assert float(flip_hinge(turned, faces, rest_n, eye, 0.1)) > 0.0  # unaligned, the turn looks like flips
    assert float(rest.loss(turned, turned, 0.1)) == pytest.approx(0.0, abs=1e-12)
    assert float(rest.loss(Y.detach() @ R.T, turned, 0.1)) == pytest.approx(float((0.1 - cos[1:]).sum()))
