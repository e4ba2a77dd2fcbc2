"""Rigid tools: meshes are closed and outward, analytic SDFs match a mesh SDF, gradients, torch."""

import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.geometry.tetmesh import check_closed_surface
from colgnn_core.geometry.tools import TOOL_SHAPES, facet_depth, make_tool, mesh_density
from colgnn_core.geometry.transforms import axis_angle_quat, transform_points

PARAMS = {
    "sphere": {"radius": 0.04},
    "cylinder": {"radius": 0.02, "height": 0.1},
    "cone": {"radius": 0.018, "height": 0.07},
    "cone_blunt": {"radius": 0.018, "height": 0.07, "tip_radius": 0.004},
    "blade": {"length": 0.12, "height": 0.05, "thickness": 0.003, "bevel": 0.012},
}


def _tool(key: str, resolution: str = "ci"):
    return make_tool(key.split("_")[0], PARAMS[key], resolution)


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact distances [N,G] from points [N,3] to triangles [G,3,3] (Ericson's region tests)."""
    a, b, c = (tri[None, :, i, :] for i in range(3))
    p = p[:, None, :]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = vb / denom
        w = vc / denom
        q = a + ab * v[..., None] + ac * w[..., None]  # interior
        t_ab = np.clip(d1 / (d1 - d3), 0, 1)
        t_ac = np.clip(d2 / (d2 - d6), 0, 1)
        t_bc = np.clip((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0, 1)
    candidates = [
        (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (d6 >= 0) & (d5 <= d6),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    points = [a, b, c, a + ab * t_ab[..., None], a + ac * t_ac[..., None], b + (c - b) * t_bc[..., None]]
    for cond, pt in zip(candidates[::-1], points[::-1]):
        q = np.where(cond[..., None], np.broadcast_to(pt, q.shape), q)
    return np.linalg.norm(p - q, axis=-1)


def _winding_number(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Generalised winding number [N] of points [N,3] w.r.t. a closed triangle mesh [G,3,3]."""
    a, b, c = (tri[None, :, i, :] - p[:, None, :] for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = (a * np.cross(b, c)).sum(-1)
    den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
    return (2 * np.arctan2(det, den)).sum(axis=1) / (4 * np.pi)


def _mesh_sdf(tool, p: np.ndarray) -> np.ndarray:
    tri = tool.vertices[tool.faces]
    d = _point_triangle_distance(p, tri).min(axis=1)
    return np.where(_winding_number(p, tri) > 0.5, -d, d)


@pytest.mark.parametrize("key", list(PARAMS))
@pytest.mark.parametrize("resolution", ["ci", "full"])
def test_tool_mesh_closed_outward_on_surface(key, resolution):
    tool = _tool(key, resolution)
    check_closed_surface(tool.vertices, tool.faces)
    import trimesh

    m = trimesh.Trimesh(tool.vertices, tool.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert np.abs(tool.sdf_local(tool.vertices)).max() < 1e-9  # inscribed: vertices on the ideal surface
    assert tool.edges.shape[1] == 2 and np.all(tool.edges[:, 0] < tool.edges[:, 1])
    # Euler characteristic of a sphere-like closed surface: V - E + F = 2.
    assert len(tool.vertices) - len(tool.edges) + len(tool.faces) == 2


@pytest.mark.parametrize("key", list(PARAMS))
def test_analytic_sdf_matches_mesh_sdf(key):
    tool = _tool(key, "ci")
    rng = np.random.default_rng(1)
    lo, hi = tool.vertices.min(0), tool.vertices.max(0)
    pad = 0.3 * (hi - lo).max()
    p = rng.uniform(lo - pad, hi + pad, size=(400, 3))
    p = np.concatenate([p, tool.vertices[:50] * 0.9, tool.vertices[:50] * 1.1])  # near the surface too
    analytic = tool.sdf_local(p)
    mesh = _mesh_sdf(tool, p)
    # Allowed error: how far the tessellation strays from the ideal surface (face centroids, edge midpoints).
    x = tool.vertices[tool.faces]
    probes = np.concatenate([x.mean(1), 0.5 * (x[:, 0] + x[:, 1]), 0.5 * (x[:, 1] + x[:, 2]), 0.5 * (x[:, 2] + x[:,
                                                                                                                 0])])
    tess = np.abs(tool.sdf_local(probes)).max()
    assert np.abs(analytic - mesh).max() <= 2 * tess + 1e-9
    clear = np.abs(analytic) > 2 * tess + 1e-9
    assert np.all(np.sign(analytic[clear]) == np.sign(mesh[clear]))
    if key == "blade":  # flat faces: the mesh *is* the ideal shape
        assert np.abs(analytic - mesh).max() < 1e-9


def test_sdf_known_values():
    sphere = _tool("sphere")
    assert np.allclose(sphere.sdf_local(np.array([[0.1, 0, 0], [0, 0, 0]])), [0.06, -0.04], atol=1e-10)
    cyl = _tool("cylinder")
    # Beside the side wall, above the cap, and diagonally off the rim.
    assert np.allclose(cyl.sdf_local(np.array([[0.03, 0, 0], [0, 0, 0.06], [0.023, 0, 0.054]])), [0.01, 0.01, 0.005],
                       atol=1e-10)
    cone = _tool("cone")
    # Straight below the tip, and beside the base rim.
    assert np.allclose(cone.sdf_local(np.array([[0, 0, -0.01], [0.028, 0, 0.07]])), [0.01, 0.01], atol=1e-10)
    # Inside on the axis: distance to the slanted side = z * sin(half angle).
    half = np.arctan2(0.018, 0.07)
    assert np.isclose(cone.sdf_local(np.array([[0, 0, 0.035]]))[0], -0.035 * np.sin(half), atol=1e-10)
    blade = _tool("blade")
    # Under the edge; beside the flat; at the spine.
    assert np.allclose(blade.sdf_local(np.array([[0, 0, -0.005], [0, 0.0035, 0.03], [0, 0, 0.06]])), [0.005, 0.002,
                                                                                                      0.01], atol=1e-10)


def _random_pose(rng):
    q = axis_angle_quat(rng.normal(size=3), rng.uniform(0, np.pi))
    return np.concatenate([rng.uniform(-0.1, 0.1, 3), q])


@pytest.mark.parametrize("key", list(PARAMS))
def test_world_sdf_and_gradient(key):
    tool = _tool(key)
    rng = np.random.default_rng(2)
    pose = _random_pose(rng)
    local = rng.uniform(-0.08, 0.08, size=(200, 3))
    world = transform_points(local, pose)
    assert np.allclose(tool.sdf(world, pose), tool.sdf_local(local), atol=1e-12)
    assert np.abs(tool.sdf(tool.world_vertices(pose), pose)).max() < 1e-9
    d, g = tool.sdf_grad(world, pose)
    assert np.allclose(d, tool.sdf_local(local), atol=1e-12)
    assert np.allclose(np.linalg.norm(g, axis=1), 1.0)
    h = 1e-7
    fd = np.stack([(tool.sdf(world + h * e, pose) - tool.sdf(world - h * e, pose)) / (2 * h) for e in np.eye(3)],
                  axis=1)
    # Central differences are exact to O(h^2) except within h of a kink (measure-zero set).
    close = np.linalg.norm(fd - g, axis=1) < 1e-5
    assert close.mean() > 0.98


@pytest.mark.parametrize("key", list(PARAMS))
def test_torch_sdf_matches_numpy_and_gradchecks(key):
    tool = _tool(key)
    rng = np.random.default_rng(3)
    pose = _random_pose(rng)
    world = rng.uniform(-0.15, 0.15, size=(300, 3))
    pt = torch.tensor(world, dtype=torch.float64, requires_grad=True)
    d = tool.sdf_torch(pt, torch.tensor(pose))
    assert np.allclose(d.detach().numpy(), tool.sdf(world, pose), atol=1e-12)
    (g,) = torch.autograd.grad(d.sum(), pt)
    assert np.allclose(g.numpy(), tool.sdf_grad(world, pose)[1], atol=1e-8)
    few = torch.tensor(world[:6], dtype=torch.float64, requires_grad=True)
    pose_t = torch.tensor(pose, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, q: tool.sdf_torch(x, q), (few, pose_t), eps=1e-7, atol=1e-5)
    # float32 works too (the learner may run in single precision).
    d32 = tool.sdf_torch(pt.detach().float(), torch.tensor(pose, dtype=torch.float32))
    assert np.allclose(d32.numpy(), d.detach().numpy(), atol=1e-5)


def test_gradient_defined_at_singular_points():
    sphere = _tool("sphere")
    d, g = sphere.sdf_grad(np.zeros((1, 3)), np.array([0, 0, 0, 0, 0, 0, 1.0]))
    assert np.isclose(d[0], -0.04) and np.all(np.isfinite(g)) and np.isclose(np.linalg.norm(g), 1)
    cone = _tool("cone")
    d, g = cone.sdf_grad(np.array([[0.0, 0.0, -0.01]]), np.array([0, 0, 0, 0, 0, 0, 1.0]))
    assert np.allclose(g, [[0, 0, -1]], atol=1e-9)  # below the sharp tip: straight down
    blade = _tool("blade")
    d, g = blade.sdf_grad(np.array([[0.0, 0.0, -0.01]]), np.array([0, 0, 0, 0, 0, 0, 1.0]))
    assert np.allclose(g, [[0, 0, -1]], atol=1e-9)  # below the edge


def test_make_tool_bad_input():
    with pytest.raises(InputError, match="valid"):
        make_tool("hammer", {}, "ci")
    with pytest.raises(InputError, match="radius"):
        make_tool("sphere", {}, "ci")
    with pytest.raises(InputError, match="resolution"):
        make_tool("sphere", {"radius": 0.1}, "huge")
    with pytest.raises(InputError, match="positive"):
        make_tool("cylinder", {"radius": -0.1, "height": 0.1}, "ci")
    assert set(TOOL_SHAPES) == {"sphere", "cylinder", "cone", "blade"}


@pytest.mark.parametrize("key", list(PARAMS))
def test_analytic_gradient_matches_autograd_near_surface(key):
    # Points hugging the surface (around tips, rims and edges, where the case analysis lives).
    tool = _tool(key, "full")
    rng = np.random.default_rng(4)
    p = np.repeat(tool.vertices, 3, axis=0) + rng.normal(scale=0.002, size=(3 * len(tool.vertices), 3))
    pose = np.array([0.0, 0, 0, 0, 0, 0, 1])
    d, g = tool.sdf_grad(p, pose)
    pt = torch.tensor(p, requires_grad=True)
    (ga,) = torch.autograd.grad(tool.sdf_torch(pt, torch.tensor(pose)).sum(), pt)
    agree = np.linalg.norm(g - ga.numpy(), axis=1) < 1e-6
    assert agree.mean() > 0.99
    assert np.allclose(np.linalg.norm(g, axis=1), 1.0)


def test_facet_depth_is_the_chord_sagitta_and_mesh_density_bounds_it():
    # A cylinder of n segments: its rim chords' midpoints lie R (1 - cos(pi/n)) inside the circle, the deepest point.
    r = 0.02
    cyl = make_tool("cylinder", {"radius": r, "height": 0.05, "segments": 16}, "ci")
    assert facet_depth(cyl) == pytest.approx(r * (1 - np.cos(np.pi / 16)), rel=1e-9)
    assert facet_depth(make_tool("blade", {"length": 0.05, "height": 0.02, "thickness": 0.002, "bevel": 0.005})) == 0
    # The 162-vertex icosphere dips 0.018 R; each subdivision divides that by about 4.
    depths = [facet_depth(make_tool("sphere", {"radius": 1.0, "segments": s}, "ci")) for s in (2, 3, 4)]
    assert depths[0] == pytest.approx(0.0178, abs=5e-4) and depths[1] < depths[0] / 3.5 and depths[2] < depths[1] / 3.5
    for shape, params in (("sphere", {"radius": 0.018}), ("cylinder", {"radius": 0.01, "height": 0.05}),
                          ("cone", {"radius": 0.01, "height": 0.04})):
        for bound in (2e-4, 5e-5):
            n = mesh_density(shape, params, bound, "ci")
            assert facet_depth(make_tool(shape, {**params, "segments": n}, "ci")) <= bound
    # The coarsest that meets the bound, never below the resolution's default (2 subdivisions at ci).
    assert mesh_density("sphere", {"radius": 1.0}, 0.005, "ci") == 3
    assert mesh_density("sphere", {"radius": 1.0}, 0.1, "ci") == 2 and mesh_density("sphere", {"radius": 1.0}, 0.1) == 3


def test_facet_tilt_halves_with_each_subdivision():
    from colgnn_core.geometry.tools import facet_tilt

    # A cylinder of n segments: a side face's normal points at its middle, pi/n from the radial normal at its edges
    # (measured 10% inside the face: a little less).
    cyl = make_tool("cylinder", {"radius": 0.02, "height": 0.05, "segments": 16}, "ci")
    assert np.degrees(facet_tilt(cyl)) == pytest.approx(0.9 * 180 / 16, rel=0.03)
    assert facet_tilt(make_tool("blade", {"length": 0.05, "height": 0.02, "thickness": 0.002, "bevel": 0.005})) < 1e-6
    # The icosphere: 9.2, 4.6 and 2.3 degrees at 2, 3 and 4 subdivisions, whatever the radius.
    tilts = [np.degrees(facet_tilt(make_tool("sphere", {"radius": r, "segments": s}, "ci")))
             for r, s in ((1.0, 2), (0.018, 3), (1.0, 4))]
    assert tilts == pytest.approx([9.22, 4.64, 2.32], abs=0.02)
    # a cone's side like the cylinder's; its flat cap is exact
    for n in (16, 40):
        cone = make_tool("cone", {"radius": 0.01, "height": 0.04, "segments": n})
        assert np.degrees(facet_tilt(cone)) == pytest.approx(0.9 * 180 / n, rel=0.03)


@pytest.mark.parametrize("key", list(PARAMS))
def test_sdf_lies_above_its_tangent_planes(key):
    """The correction's sliding certificate rests on the SDF being convex with the analytic gradient a subgradient:
    sdf(y) >= sdf(a) + g(a) . (y - a) for every pair, inside, outside and across kinks (medial axis, rims, the
    knife's edge), within the SDFs' 1e-12 m sqrt guard."""
    tool = _tool(key, "ci")
    rng = np.random.default_rng(7)
    centre = np.array([0.0, 0.0, 0.5 * PARAMS[key].get("height", 0.0)])
    for scale in (0.004, 0.03, 0.1):
        a = centre + rng.normal(scale=scale, size=(20000, 3))
        y = a + rng.normal(scale=scale, size=a.shape) * rng.uniform(0, 1, (len(a), 1))
        fa = tool.sdf_local(a)
        _, g = tool.sdf_grad(a, np.array([0.0, 0, 0, 0, 0, 0, 1]))
        gap = tool.sdf_local(y) - fa - (g * (y - a)).sum(axis=1)
        assert gap.min() > -2e-12, (key, scale, gap.min())
    # A concave-looking case a non-convex SDF would fail: through the cylinder's axis / the knife's mid-plane.
    if key in ("cylinder", "blade"):
        a = np.array([[0.0, 1e-4, 0.02]])
        y = np.array([[0.0, -1e-3, 0.02]])
        _, g = tool.sdf_grad(a, np.array([0.0, 0, 0, 0, 0, 0, 1]))
        assert tool.sdf_local(y)[0] >= tool.sdf_local(a)[0] + (g * (y - a)).sum() - 1e-12
