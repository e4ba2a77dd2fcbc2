"""The contact prior (sim.contact_prior): linear elasticity with every face the tool reaches held on its surface."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import PRIOR_FEATURES, Frame, ModelConfig, Simulator
from colgnn_core.scenes import load_scene
from colgnn_core.sim.contact_prior import ContactPrior
from colgnn_core.sim.elasticity import StableNeoHookean
from colgnn_core.sim.prior import physics_prior


@pytest.fixture(scope="module")
def mat():
    scene = load_scene("sphere_mat", "ci")
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    return scene, rest, ContactPrior(scene, rest, np.arange(rest.shape[0]))


def _press(scene, rest, depth: float, xy=(0.01, 0.005)) -> np.ndarray:
    """The sphere's pose ``depth`` (m) below touching the mat's top at ``xy``."""
    z = rest[:, 2].max() + scene.tool.params["radius"] - depth
    return np.array([xy[0], xy[1], z, 0.0, 0.0, 0.0, 1.0])


def _deepest(scene, x: np.ndarray, pose: np.ndarray, level: int = 8) -> float:
    """The lowest tool SDF (m) over a finer barycentric grid of every surface face at positions ``x``."""
    n = level + 1
    bary = np.array([(i, j, level - i - j) for i in range(n) for j in range(n - i)], dtype=np.float64) / level
    points = np.einsum("sk,fkd->fsd", bary, x[np.asarray(scene.object.faces)])
    return float(scene.tool.sdf(points.reshape(-1, 3), pose).min())


def test_a_press_holds_the_faces_on_the_sphere_with_pushing_forces_only(mat):
    scene, rest, prior = mat
    pose = _press(scene, rest, 0.004)
    assert _deepest(scene, rest, pose) < -0.0039  # the rest shape reaches 4 mm into the sphere
    u = prior.displacement(pose)
    # out of it, at the solver's gap (dmin + dhat/2), to 15% of the push: the sphere's curvature between the
    # samples and across the mat's 25 mm faces is linearised
    assert prior.gap == pytest.approx(4.5 * scene.dhat)
    assert _deepest(scene, rest + u, pose) > prior.gap - 0.15 * (0.004 + prior.gap)
    assert np.abs(u[np.asarray(scene.pinned)]).max() == 0.0
    assert 0.9 * (0.004 + prior.gap) < np.linalg.norm(u, axis=1).max() < 1.3 * (0.004 + prior.gap)
    # K u is the contact force on the free vertices: only on faces the sphere reaches, and pressing the mat down
    force = (StableNeoHookean(scene.object, scene.material).hessian(rest).tocsr() @ u.reshape(-1)).reshape(-1, 3)
    free = np.ones(rest.shape[0], dtype=bool)
    free[np.asarray(scene.pinned)] = False
    pushed = free & (np.linalg.norm(force, axis=1) > 1e-6 * np.abs(force).max())
    touched = np.unique(np.asarray(scene.object.faces)[scene.tool.sdf(rest, pose)[scene.object.faces].min(axis=1)
                                                       < 0.03])
    assert 0 < pushed.sum() and set(np.flatnonzero(pushed)) <= set(touched)
    assert force[free].sum(axis=0)[2] < 0.0
    # out of contact nothing moves
    assert np.all(prior.displacement(_press(scene, rest, -prior.gap - 0.001)) == 0.0)


def test_the_prior_is_a_function_of_the_pose_and_deeper_moves_more(mat):
    scene, rest, prior = mat
    shallow, deep = (prior.displacement(_press(scene, rest, d)) for d in (0.002, 0.006))
    assert np.linalg.norm(deep, axis=1).max() > 2.0 * np.linalg.norm(shallow, axis=1).max()
    state, again = prior.step(None, _press(scene, rest, 0.006), _press(scene, rest, 0.002))
    assert state is None and np.array_equal(again, shallow)   # no state: the path does not matter
    np.testing.assert_array_equal(prior.rollout(np.stack([_press(scene, rest, 0.002)] * 2))[1], shallow)


@pytest.mark.parametrize("compliance", ["", "modal"])
def test_a_contact_prior_model_runs_the_prior_behind_the_stepper_as_in_training(mat, compliance, tmp_path,
                                                                                monkeypatch):
    from colgnn_core.runtime.models import PriorModel
    from colgnn_core.runtime.stepper import RawStepper

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))   # the modal set-up's disk cache
    scene, rest, _ = mat
    template = template_from_scene(scene, surface_only=True)
    config = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                         contact_prior=True, prior_compliance=compliance)
    assert config.prior_kind == "contact"
    stepper = RawStepper(PriorModel(template, rest[template.object_nodes], config), scene, rest_mesh=rest)
    poses = np.stack([_press(scene, rest, d, (0.02, -0.01)) for d in (-0.01, 0.0, 0.003, 0.006, -0.01)])
    stepper.reset(rest[template.object_nodes], poses[0])
    expect = physics_prior("contact", scene, rest, template.object_nodes, compliance=compliance).rollout(poses)
    for t in range(1, len(poses)):
        np.testing.assert_allclose(stepper.step(poses[t]) - rest[template.object_nodes], expect[t], atol=1e-12)
    assert np.abs(expect[3]).max() > 0.004
    # every node sees the prior (PRIOR_FEATURES), and the output is added to rest + prior
    x = template.rest.to(torch.float64)
    tool = torch.from_numpy(scene.tool.world_vertices(poses[3]))
    prior = torch.from_numpy(expect[3])
    sim = Simulator(template, config)
    plain = Simulator(template, replace(config, contact_prior=False, prior_compliance=""))
    widths = [s.build_graph(Frame(x, x, tool, tool, poses[3], prior)).node_features.shape[1] for s in (sim, plain)]
    assert widths[0] == widths[1] + PRIOR_FEATURES
    pred, _ = sim.network(sim.build_graph(Frame(x, x, tool, tool, poses[3], prior)))
    free = ~template.pinned
    torch.testing.assert_close((sim.integrate(pred, x, x, prior) - sim.integrate(pred, x, x, 0 * prior))[free],
                               prior[free])


def test_the_priors_refuse_bad_settings(mat):
    scene, rest, _ = mat
    template = template_from_scene(scene, surface_only=True)
    with pytest.raises(InputError, match="exclude each other"):
        Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                                        tip_prior=True, contact_prior=True))
    with pytest.raises(InputError, match="contact_prior needs quasi_static"):
        Simulator(template, ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, contact_prior=True))
    with pytest.raises(InputError, match="unknown physics prior 'spring'"):
        physics_prior("spring", scene, rest, np.arange(3))
    with pytest.raises(InputError, match="finite"):
        ContactPrior(scene, rest[:-1], np.arange(3))


def test_a_model_that_does_not_see_its_prior_solves_it_beside_the_network_with_the_same_output(mat):
    import os
    import signal
    import time

    from colgnn_core.runtime.stepper import RawStepper

    scene, rest, _ = mat
    template = template_from_scene(scene, surface_only=True)
    config = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                         contact_prior=True, prior_input=False)
    torch.manual_seed(0)
    sim = Simulator(template, config).eval()
    plain = Simulator(template, replace(config, contact_prior=False, prior_input=True))
    x = template.rest.to(torch.float64)
    poses = np.stack([_press(scene, rest, d, (0.02, -0.01)) for d in (-0.01, 0.0, 0.003, 0.006, 0.004, -0.01)])
    tool = torch.from_numpy(scene.tool.world_vertices(poses[3]))
    # the nodes do not see the prior: no PRIOR_FEATURES, and the graph is built without one
    widths = [s.build_graph(Frame(x, x, tool, tool, poses[3], None)).node_features.shape[1] for s in (sim, plain)]
    assert widths[0] == widths[1]
    here = RawStepper(sim, scene, rest_mesh=rest, prior_beside=False)
    beside = RawStepper(sim, scene, rest_mesh=rest)
    assert beside.prior_beside and not here.prior_beside and beside.prior_worker.alive
    expect = physics_prior("contact", scene, rest, template.object_nodes).rollout(poses)
    nodes = rest[template.object_nodes]
    try:
        for stepper in (here, beside):
            stepper.reset(nodes, poses[0])
        for t in range(1, 4):
            a, b = here.step(poses[t]), beside.step(poses[t])
            np.testing.assert_array_equal(a, b)   # the same prior, the same float64 arithmetic, another process
        # the output is the network's plus the prior: the pose's prior moves the nodes millimetres
        tool_t = torch.from_numpy(scene.tool.world_vertices(poses[2]))
        with torch.no_grad():
            pred, _ = sim.network(sim.build_graph(Frame(x, x, tool_t, tool, poses[3], None)))
            net_only = sim.integrate(pred, x, x, torch.zeros_like(x)).numpy()
        assert np.abs(expect[3]).max() > 0.004
        np.testing.assert_allclose(a - net_only, expect[3], atol=1e-12)
        # the prior's process dies: the stepper says so, solves the prior itself, and the output does not change
        os.kill(beside.prior_worker.pid, signal.SIGKILL)
        for _ in range(500):   # the kill lands within milliseconds
            if not beside.prior_worker.alive:
                break
            time.sleep(0.01)
        with pytest.warns(RuntimeWarning, match="prior's process"):
            b = beside.step(poses[4])
        np.testing.assert_array_equal(here.step(poses[4]), b)
        assert not beside.prior_beside and "prior" in beside.prior_failure
        np.testing.assert_array_equal(here.step(poses[5]), beside.step(poses[5]))
    finally:
        beside.close()
    with pytest.raises(InputError, match="prior_input false needs a physics prior"):
        Simulator(template, replace(config, contact_prior=False))
