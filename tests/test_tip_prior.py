"""The tip prior (sim.tip_prior): linear elasticity with the sharp tool's tip carrying a surface point."""

import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import Frame, ModelConfig, Simulator
from colgnn_core.scenes import load_scene
from colgnn_core.sim.elasticity import StableNeoHookean
from colgnn_core.sim.contact_prior import multipliers
from colgnn_core.sim.tip_prior import AHEAD_GAPS, KAPPA, TipPrior, TipSidePrior


@pytest.fixture(scope="module")
def bunny():
    scene = load_scene("cone_bunny", "ci")
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    return scene, rest, TipPrior(scene, rest, np.arange(rest.shape[0]))


def _pose(tip) -> np.ndarray:
    return np.array([*tip, 0.0, 0.0, 0.0, 1.0])  # tip down, axis +z


def _surface_z(prior: TipPrior, xy) -> float:
    """Height of the bunny's top surface above ``xy``."""
    hit = prior.first_hit(np.array([xy[0], xy[1], 1.0]), np.array([0.0, 0.0, -1.0]))
    return 1.0 - hit[1]


def test_the_tip_carries_the_surface_point_it_entered_and_glued_vertices_stay(bunny):
    scene, rest, prior = bunny
    z = _surface_z(prior, (0.03, -0.02))
    poses = np.stack([_pose((0.03, -0.02, z + 0.01)), _pose((0.03, -0.02, z - 0.008))])
    u = prior.rollout(poses)
    assert np.all(u[0] == 0.0)  # out of contact: nothing moves
    contact = prior.contact(None, poses[0, :3], poses[1])
    carried = np.asarray(contact.bary) @ (rest + u[1])[scene.object.faces[contact.face]]
    np.testing.assert_allclose(carried, poses[1, :3], atol=1e-9)  # the entry point sits on the tip
    entry = np.asarray(contact.bary) @ rest[scene.object.faces[contact.face]]
    np.testing.assert_allclose(entry, [0.03, -0.02, z], atol=1e-9)  # it entered straight above
    assert np.abs(u[1][np.asarray(scene.pinned)]).max() == 0.0
    # a dent of 8 mm spreads through the body: the bunny bends, not only the touched face (whose vertices move
    # somewhat more than the point between them)
    moved = np.linalg.norm(u[1], axis=1)
    assert 0.008 <= moved.max() <= 0.012 and (moved > 0.0008).mean() > 0.2


def test_the_response_is_the_linear_elastic_minimiser_of_the_constraint(bunny):
    scene, rest, prior = bunny
    z = _surface_z(prior, (0.0, -0.03))
    pose = _pose((0.0, -0.03, z - 0.006))
    contact = prior.contact(None, pose[:3] + [0.0, 0.0, 0.02], pose)
    u = prior.displacement(contact, pose)
    # K u is a force on the carried face's three vertices only (the Lagrange multiplier), zero elsewhere
    k = StableNeoHookean(scene.object, scene.material).hessian(rest).tocsr()
    force = (k @ u.reshape(-1)).reshape(-1, 3)
    free = np.ones(rest.shape[0], dtype=bool)
    free[np.asarray(scene.pinned)] = False
    free[scene.object.faces[contact.face]] = False
    assert np.abs(force[free]).max() < 1e-8 * np.abs(force).max()


def test_a_drag_carries_the_pocket_until_it_is_too_far_from_the_tip(bunny):
    _, _, prior = bunny
    z = _surface_z(prior, (0.03, -0.02))
    depth = 0.006
    start = prior.contact(None, np.array([0.03, -0.02, z + 0.01]), _pose((0.03, -0.02, z - depth)))
    near = prior.contact(start, np.array([0.03, -0.02, z - depth]), _pose((0.033, -0.02, z - depth)))
    assert near == start  # 3 mm sideways at 6 mm depth: the same material point
    far_tip = (0.03 + 4 * KAPPA * depth, -0.02)
    far_pose = _pose((*far_tip, _surface_z(prior, far_tip) - depth))
    far = prior.contact(start, np.array([0.03, -0.02, z - depth]), far_pose)
    carried = prior.point(far)
    axis_point = np.array([*far_tip, _surface_z(prior, far_tip)])
    assert far != start and np.linalg.norm(carried - axis_point) <= KAPPA * depth * 1.2


def _deepest(scene, x: np.ndarray, pose: np.ndarray, level: int = 8) -> float:
    """The lowest tool SDF (m) over a barycentric grid of every surface face at positions ``x``."""
    n = level + 1
    bary = np.array([(i, j, level - i - j) for i in range(n) for j in range(n - i)], dtype=np.float64) / level
    points = np.einsum("sk,fkd->fsd", bary, x[np.asarray(scene.object.faces)])
    return float(scene.tool.sdf(points.reshape(-1, 3), pose).min())


@pytest.mark.parametrize("depth", [0.004, 0.008])
def test_the_side_prior_widens_the_pocket_to_the_cone_and_holds_the_tip_point_ahead(bunny, depth):
    """The tip prior's pocket is narrower than the cone: faces around it lie inside the cone. The side prior holds
    every face outside it, and the carried point AHEAD_GAPS solver gaps ahead of the tip."""
    scene, rest, tip = bunny
    side = TipSidePrior(scene, rest, np.arange(rest.shape[0]))
    xy = (-0.02, 0.0)
    z = _surface_z(tip, xy)
    poses = np.stack([_pose((*xy, z + 0.01)), _pose((*xy, z - depth))])
    assert _deepest(scene, rest + tip.rollout(poses)[1], poses[1]) < -0.0003  # 0.4-1 mm inside the cone
    u = side.rollout(poses)[1]
    assert _deepest(scene, rest + u, poses[1]) > 0.5 * side.side.gap
    contact = side.contact(None, poses[0], poses[1])
    carried = np.asarray(contact.bary) @ (rest + u)[scene.object.faces[contact.face]]
    np.testing.assert_allclose(carried, poses[1, :3] - [0.0, 0.0, AHEAD_GAPS * side.side.gap], atol=1e-9)
    assert np.abs(u[np.asarray(scene.pinned)]).max() == 0.0


def test_the_multipliers_meet_the_kkt_conditions_with_equality_rows():
    """multipliers(s, t, n_eq): equality rows met exactly, inequality rows met with non-negative multipliers that
    vanish where the row is slack (a random positive definite s, half the inequality targets out of reach)."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(9, 30))
    s = a @ a.T
    target = rng.normal(size=9)
    target[6:] -= 5.0                           # rows met with room to spare
    lam = multipliers(s, target, n_eq=3)
    slack = s @ lam - target                    # A u - target at u = K^-1 A^T lambda
    np.testing.assert_allclose(slack[:3], 0.0, atol=1e-7)  # the ridge (1e-9 of the mean diagonal)
    assert np.all(lam[3:] >= 0.0) and np.all(slack[3:] >= -1e-7)
    np.testing.assert_allclose(lam[3:] * slack[3:], 0.0, atol=1e-7)
    assert 0 < np.count_nonzero(lam[3:]) and np.all(lam[6:] == 0.0)   # some rows push, the easy ones are slack
    np.testing.assert_allclose(multipliers(s[:3, :3], target[:3], n_eq=3), np.linalg.solve(s[:3, :3], target[:3]))


def test_the_tip_prior_needs_a_sharp_cone():
    mat = load_scene("sphere_mat", "ci")
    with pytest.raises(InputError, match="sharp cone"):
        TipPrior(mat, mat.object.vertices, np.arange(3))


def test_a_tip_prior_model_adds_the_prior_and_refuses_a_frame_without_it(bunny):
    scene, rest, prior = bunny
    template = template_from_scene(scene, surface_only=True)
    sim = Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0,
                                          quasi_static=True, tip_prior=True))
    x = template.rest.to(torch.float64)
    tool = torch.from_numpy(scene.tool.world_vertices(scene.tool_rest_pose))
    p = torch.from_numpy(prior.rollout(np.stack([scene.tool_rest_pose] * 2))[1][template.object_nodes])
    bump = torch.full_like(x, 0.001)
    pred, _ = sim.network(sim.build_graph(Frame(x, x, tool, tool, scene.tool_rest_pose, p)))
    a = sim.integrate(pred, x, x, p)
    b = sim.integrate(pred, x, x, p + bump)
    free = ~template.pinned
    torch.testing.assert_close(b[free] - a[free], bump[free])
    with pytest.raises(InputError, match="physics prior"):
        sim.predict(Frame(x, x, tool, tool, scene.tool_rest_pose))
    with pytest.raises(InputError, match="tip_prior needs quasi_static"):
        Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, tip_prior=True))
    with pytest.raises(InputError, match="side_contact needs tip_prior"):
        Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                                        side_contact=True))


@pytest.mark.parametrize("side_contact", [False, True])
def test_the_prior_baseline_runs_the_prior_alone_behind_the_stepper(bunny, side_contact):
    """`prior + correction` in `colgnn evaluate`: the network replaced by its physics prior, computed by the stepper
    along the poses exactly as for the model."""
    from colgnn_core.runtime.models import PriorModel
    from colgnn_core.runtime.stepper import RawStepper

    scene, rest, prior = bunny
    template = template_from_scene(scene, surface_only=True)
    config = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True, tip_prior=True,
                         side_contact=side_contact)
    baseline = PriorModel(template, rest[template.object_nodes], config)
    stepper = RawStepper(baseline, scene, rest_mesh=rest)
    z = _surface_z(prior, (0.03, -0.02))
    poses = np.stack([_pose((0.03, -0.02, z + dz)) for dz in (0.01, 0.0, -0.004, -0.008, 0.01)])
    stepper.reset(rest[template.object_nodes], poses[0])
    expect = (TipSidePrior if side_contact else TipPrior)(scene, rest, template.object_nodes).rollout(poses)
    for t in range(1, len(poses)):
        np.testing.assert_allclose(stepper.step(poses[t]) - rest[template.object_nodes], expect[t], atol=1e-12)
    assert stepper.state.contact is None  # the tip left: nothing carried


def test_a_models_tip_kappa_reaches_its_prior_behind_the_stepper(bunny):
    """`tip_kappa` (ModelConfig) sets the slide rule of the prior that training and the stepper build: a drag's
    carried point then stays within tip_kappa x depth of the axis point, not KAPPA x depth."""
    from colgnn_core.runtime.models import PriorModel
    from colgnn_core.runtime.stepper import RawStepper
    from colgnn_core.sim.prior import physics_prior

    scene, rest, prior = bunny
    template = template_from_scene(scene, surface_only=True)
    config = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True, tip_prior=True,
                         tip_kappa=0.5)
    assert config.prior_options == {"kappa": 0.5}
    assert ModelConfig(order=0, quasi_static=True, tip_prior=True).prior_options == {}  # older checkpoints: KAPPA
    stepper = RawStepper(PriorModel(template, rest[template.object_nodes], config), scene, rest_mesh=rest)
    z = _surface_z(prior, (0.03, -0.02))
    depth = 0.006
    poses = np.stack([_pose((0.03, -0.02, z + 0.01))]
                     + [_pose((0.03 + dx, -0.02, _surface_z(prior, (0.03 + dx, -0.02)) - depth))
                        for dx in (0.0, 0.004, 0.008, 0.012)])
    stepper.reset(rest[template.object_nodes], poses[0])
    got = np.stack([stepper.step(p) - rest[template.object_nodes] for p in poses[1:]])
    nodes = template.object_nodes
    np.testing.assert_allclose(got, TipPrior(scene, rest, nodes, kappa=0.5).rollout(poses)[1:], atol=1e-12)
    np.testing.assert_allclose(got, physics_prior("tip", scene, rest, nodes, options={"kappa": 0.5}).rollout(poses)[1:],
                               atol=1e-12)
    # 12 mm of drag at 6 mm depth: KAPPA = 2 still carries the entry point, 0.5 has let it slide
    assert np.abs(got[-1] - TipPrior(scene, rest, nodes).rollout(poses)[-1]).max() > 1e-3
    with pytest.raises(InputError, match="no setting"):
        physics_prior("contact", load_scene("sphere_mat", "ci"), rest, nodes, options={"kappa": 1.0})
    with pytest.raises(InputError, match="tip_kappa needs tip_prior"):
        Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                                        tip_kappa=1.0))
    with pytest.raises(InputError, match="tip_kappa must be"):
        Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                                        tip_prior=True, tip_kappa=-1.0))
