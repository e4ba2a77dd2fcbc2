"""A physics prior solved on a coarser mesh of the same object (sim.coarse_prior), carried onto the model's nodes."""

from dataclasses import replace

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import ModelConfig, Simulator
from colgnn_core.scenes import load_scene
from colgnn_core.sim.coarse_prior import CoarsePrior, TetEmbedding
from colgnn_core.sim.contact_prior import ContactPrior
from colgnn_core.sim.prior import physics_prior


@pytest.fixture(scope="module")
def banana():
    """The full banana (3,578 surface vertices) with an assumed settled rest 0.1 mm below its mesh, and its ci mesh."""
    full, ci = load_scene("cylinder_banana", "full"), load_scene("cylinder_banana", "ci")
    rest = np.asarray(full.object.vertices) + np.array([0.0, 0.0, -1e-4])
    return full, ci, rest


def _press(scene, rest, depth: float, xy=(0.02, -0.01)) -> np.ndarray:
    """The roller's pose ``depth`` (m) below touching the banana's top, its axis across the banana."""
    z = rest[:, 2].max() + scene.tool.params["radius"] - depth
    return np.concatenate([[xy[0], xy[1], z], scene.tool_rest_pose[3:]])


def test_an_embedding_carries_an_affine_field_exactly_inside_and_just_outside_the_mesh():
    mesh = load_scene("cylinder_banana", "ci").object
    v = np.asarray(mesh.vertices)
    rng = np.random.default_rng(0)
    lo, hi = v.min(axis=0), v.max(axis=0)
    points = np.vstack([v, rng.uniform(lo, hi, size=(200, 3)), v[mesh.surface_vertices] * 1.01])
    emb = TetEmbedding.of(v, mesh.tets, points)
    a, b = rng.normal(size=(3, 3)), rng.normal(size=3)
    np.testing.assert_allclose(emb.apply(v @ a.T + b), points @ a.T + b, atol=1e-10)
    np.testing.assert_allclose(emb.weights.sum(axis=1), 1.0, atol=1e-12)
    # a vertex is held by a tet that has it as a corner, with weight 1 there
    np.testing.assert_allclose(emb.weights[:len(v)].max(axis=1), 1.0, atol=1e-9)
    assert np.all(emb.corners[np.arange(len(v)), emb.weights[:len(v)].argmax(axis=1)] == np.arange(len(v)))
    with pytest.raises(InputError, match=r"finite \[P,3\]"):
        TetEmbedding.of(v, mesh.tets, np.full((2, 3), np.nan))


def test_the_ci_contact_prior_starts_from_the_full_settled_rest_and_follows_the_full_prior(banana):
    full, ci, rest = banana
    nodes = np.asarray(full.object.surface_vertices)
    coarse = physics_prior("contact", full, rest, nodes, mesh="ci")
    assert isinstance(coarse, CoarsePrior) and isinstance(coarse.inner, ContactPrior)
    # the fine mesh's settle (here 0.1 mm down everywhere) is carried onto the ci mesh
    np.testing.assert_allclose(coarse.coarse_rest - np.asarray(ci.object.vertices),
                               np.tile([0.0, 0.0, -1e-4], (len(ci.object.vertices), 1)), atol=1e-12)
    pose = _press(full, rest, 0.008)
    state, u = coarse.step(None, pose, pose)
    expect = physics_prior("contact", full, rest, nodes).displacement(pose)
    assert state is None and u.shape == (nodes.size, 3)
    # the same dent and body motion, 20% apart (measured 0.20): the ci mesh's faces are 4x longer
    assert np.linalg.norm(u - expect) < 0.3 * np.linalg.norm(expect)
    assert np.linalg.norm(u, axis=1).max() == pytest.approx(np.linalg.norm(expect, axis=1).max(), rel=0.15)
    np.testing.assert_allclose(coarse.rollout(np.stack([pose, _press(full, rest, -0.01)])), np.stack([u, 0 * u]))


def test_a_model_whose_prior_is_solved_on_the_ci_mesh_gets_it_behind_the_stepper(banana):
    from colgnn_core.runtime.models import PriorModel
    from colgnn_core.runtime.stepper import RawStepper

    full, _, rest = banana
    template = template_from_scene(full, surface_only=True)
    config = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                         contact_prior=True, prior_mesh="ci")
    assert ModelConfig.from_dict(config.to_dict()) == config
    stepper = RawStepper(PriorModel(template, rest[template.object_nodes], config), full, rest_mesh=rest)
    poses = np.stack([_press(full, rest, d) for d in (-0.01, 0.004, 0.009, 0.002)])
    stepper.reset(rest[template.object_nodes], poses[0])
    expect = physics_prior("contact", full, rest, template.object_nodes, mesh="ci").rollout(poses)
    for t in range(1, len(poses)):
        np.testing.assert_allclose(stepper.step(poses[t]) - rest[template.object_nodes], expect[t], atol=1e-12)
    assert np.abs(expect[2]).max() > 0.008


def test_a_coarse_prior_refuses_bad_settings(banana):
    full, ci, rest = banana
    nodes = np.arange(10)
    with pytest.raises(InputError, match="unknown prior mesh 'coarse'"):
        physics_prior("contact", full, rest, nodes, mesh="coarse")
    with pytest.raises(InputError, match="same object"):
        CoarsePrior(ContactPrior, load_scene("sphere_mat", "ci"), full, rest, nodes)
    with pytest.raises(InputError, match=r"rest must be \[5978,3\]"):
        CoarsePrior(ContactPrior, ci, full, rest[:-1], nodes)
    template = template_from_scene(ci, surface_only=True)
    plain = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True)
    with pytest.raises(InputError, match="prior_mesh needs a physics prior"):
        Simulator(template, replace(plain, prior_mesh="ci"))
    # its own resolution is the plain prior
    assert isinstance(physics_prior("contact", ci, np.asarray(ci.object.vertices), nodes, mesh="ci"), ContactPrior)
