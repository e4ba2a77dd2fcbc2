"""The edge prior (sim.edge_prior): linear elasticity with the blade's edge carrying the surface above it."""

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import ModelConfig, Simulator
from colgnn_core.scenes import load_scene
from colgnn_core.sim.edge_prior import EdgePrior
from colgnn_core.sim.prior import physics_prior


@pytest.fixture(scope="module")
def torus():
    scene = load_scene("knife_torus", "ci")
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    return scene, rest, EdgePrior(scene, rest, np.arange(rest.shape[0]))


def _cut(rest, depth: float, x: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """The blade's pose with its edge ``depth`` (m) below the top of the tube at (0.1, 0), slid ``x`` (m) along
    itself, turned ``yaw_deg`` about the vertical."""
    half = np.radians(yaw_deg) / 2
    return np.array([0.1 + x * np.cos(2 * half), x * np.sin(2 * half), rest[:, 2].max() - depth,
                     0.0, 0.0, np.sin(half), np.cos(half)])


def _material(prior: EdgePrior, faces: np.ndarray, bary: np.ndarray, u: np.ndarray) -> np.ndarray:
    """[k,3] where the material points (rows of the prior's faces, weights [k,3]) are after the displacement u."""
    verts = prior.faces[faces]
    return np.einsum("kj,kjd->kd", bary, prior.rest[verts] + u[verts])


def test_the_edge_carries_the_surface_above_it_down_to_itself_and_nothing_moves_outside(torus):
    scene, rest, prior = torus
    pose = _cut(rest, 0.01)
    faces, bary, samples = prior.carried(pose)
    # the tube is 8 cm across and the blade 12 cm long; at ci the edge is sampled every mean edge length (~1.6 cm)
    assert 3 <= len(faces) < prior.edge_x.size
    assert np.all(np.abs(samples[:, 0] - 0.1) < 0.04)                       # inside the tube only
    start = _material(prior, faces, bary, np.zeros_like(rest))
    assert np.allclose(start[:, :2], samples[:, :2], atol=1e-12)            # straight above each sample
    assert np.all(start[:, 2] > samples[:, 2])
    assert (start[:, 2] - samples[:, 2]).max() == pytest.approx(0.01 + prior.gap)   # the tube's top
    u = prior.displacement(pose)
    moved = _material(prior, faces, bary, u)
    # in the blade's plane (y) and at the edge less the gap (z), exactly; along the edge (x) it may slide
    np.testing.assert_allclose(moved[:, 1:], samples[:, 1:], atol=1e-9)
    assert samples[0, 2] == pytest.approx(rest[:, 2].max() - 0.01 - prior.gap)
    assert np.abs(u[np.asarray(scene.pinned)]).max() == 0.0
    assert 0.01 < np.linalg.norm(u, axis=1).max() < 0.02
    # the edge 1 mm farther above the tube than the solver's gap, or beside the tube, moves nothing
    assert prior.displacement(_cut(rest, -prior.gap + 0.0005)).any()
    assert not prior.displacement(_cut(rest, -prior.gap - 0.001)).any()
    assert not prior.displacement(_cut(rest, 0.01) + np.array([0.0, 0.0, 0.2, 0, 0, 0, 0])).any()


def test_the_prior_has_no_state_and_a_deeper_or_turned_cut_moves_the_material_above_the_new_edge(torus):
    scene, rest, prior = torus
    pose = _cut(rest, 0.015, yaw_deg=20.0)
    u = prior.displacement(pose)
    state, again = prior.step(None, _cut(rest, 0.002), pose)
    assert state is None and np.array_equal(again, u)                        # the path does not matter
    faces, bary, samples = prior.carried(pose)
    np.testing.assert_allclose(_material(prior, faces, bary, u)[:, 2], samples[:, 2], atol=1e-9)
    shallow = prior.displacement(_cut(rest, 0.005, yaw_deg=20.0))
    assert np.linalg.norm(u, axis=1).max() > 2.0 * np.linalg.norm(shallow, axis=1).max()
    # a frictionless edge that slides along itself carries the material above it at its new place
    slid = _cut(rest, 0.015, x=0.01, yaw_deg=20.0)
    faces2, bary2, samples2 = prior.carried(slid)
    np.testing.assert_allclose(_material(prior, faces2, bary2, prior.displacement(slid))[:, 2], samples2[:, 2],
                               atol=1e-9)
    assert not np.array_equal(faces2, faces)


def test_the_edge_prior_needs_a_blade_and_is_one_prior_among_the_others():
    banana = load_scene("cylinder_banana", "ci")
    rest = np.asarray(banana.object.vertices, dtype=np.float64)
    with pytest.raises(InputError, match="the edge prior needs a blade, not a cylinder"):
        physics_prior("edge", banana, rest, np.arange(rest.shape[0]))
    template = template_from_scene(load_scene("knife_torus", "ci"))
    assert ModelConfig(order=0, quasi_static=True, edge_prior=True).prior_kind == "edge"
    with pytest.raises(InputError, match="tip_prior, contact_prior and edge_prior exclude each other"):
        Simulator(template, ModelConfig(order=0, quasi_static=True, edge_prior=True, contact_prior=True))
    with pytest.raises(InputError, match="edge_prior needs quasi_static"):
        Simulator(template, ModelConfig(order=0, edge_prior=True))
