"""The rest compliance the contact prior reads (sim.compliance), its non-negative dual (contact_prior.nonnegative_qp)
and its vertex constraints (ContactPrior points="vertices")."""

import numpy as np
import pytest
from scipy import sparse
from scipy.optimize import nnls

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import ModelConfig, Simulator
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.hard_cases import press_pose
from colgnn_core.sim.compliance import ExactCompliance, ModalCompliance, coordinates
from colgnn_core.sim.contact_prior import ContactPrior, nonnegative_qp
from colgnn_core.sim.prior import physics_prior
from colgnn_core.sim.rest_stiffness import RestStiffness


@pytest.fixture(scope="module")
def banana():
    scene = load_scene("cylinder_banana", "ci")
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    stiffness = RestStiffness(scene, rest)
    surface = np.unique(np.asarray(scene.object.faces))
    return scene, rest, stiffness, surface[stiffness.free_index[surface] >= 0]


def _rows(stiffness, vertices, k, seed=0):
    """M [3U,k]: k random unit rows, each on one of ``vertices`` (as the contact prior's vertex constraints)."""
    rng = np.random.default_rng(seed)
    which = rng.integers(0, len(vertices), size=k)
    normal = rng.normal(size=(k, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    rows = (3 * which[:, None] + np.arange(3)).reshape(-1)
    return sparse.csc_matrix((normal.reshape(-1), (rows, np.repeat(np.arange(k), 3))), shape=(3 * len(vertices), k))


def test_modal_compliance_with_every_surface_pair_near_is_exact_on_the_surface(banana, tmp_path):
    scene, rest, stiffness, surface = banana
    exact = ExactCompliance(stiffness)
    # a near field that reaches every pair (the banana is 20 cm long): exact minus modal everywhere on the surface
    modal = ModalCompliance(stiffness, surface, modes=12, radius=1.0, cache=tmp_path)
    vertices = surface[::7]
    m = _rows(stiffness, vertices, 25)
    want = exact.dual(vertices, m)
    assert np.allclose(modal.dual(vertices, m), want, rtol=1e-7, atol=1e-9 * np.abs(want).max())
    w = np.random.default_rng(1).normal(size=3 * len(vertices))
    assert np.allclose(modal.response(vertices, w), exact.response(vertices, w), rtol=1e-9, atol=1e-15)
    # the modes are K's lowest: K phi = lambda phi
    k_phi = stiffness.hessian @ modal.phi
    assert np.allclose(k_phi, modal.phi / modal.inv_lam, rtol=1e-6, atol=1e-8 * np.abs(k_phi).max())
    assert np.all(np.diff(1.0 / modal.inv_lam) >= 0.0)


def test_modal_compliance_without_a_near_field_is_only_the_modes(banana):
    scene, rest, stiffness, surface = banana
    modal = ModalCompliance(stiffness, surface, modes=12, radius=1e-9)   # each vertex with itself only
    vertices = surface[::5]
    own = coordinates(stiffness, vertices)
    m = _rows(stiffness, vertices, 10, seed=2)
    dense = m.toarray()
    far = dense.T @ (modal.phi[own] * modal.inv_lam) @ modal.phi[own].T @ dense
    near = modal.near_block(vertices)
    assert np.count_nonzero(near) <= 9 * len(vertices)   # each vertex with itself: 3x3 blocks
    assert np.allclose(modal.dual(vertices, m), far + dense.T @ near @ dense, rtol=1e-9)
    # 12 modes alone are far from exact: the near field is what makes the dent
    exact = ExactCompliance(stiffness).dual(vertices, m)
    assert np.abs(np.diag(far) - np.diag(exact)).max() > 0.3 * np.abs(np.diag(exact)).max()


def test_the_set_up_is_kept_on_disk_and_read_back(banana, tmp_path):
    scene, rest, stiffness, surface = banana
    first = ModalCompliance(stiffness, surface, modes=8, radius=0.02, cache=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and stiffness.fingerprint in files[0].name
    again = ModalCompliance(stiffness, surface, modes=8, radius=0.02, cache=tmp_path)
    assert np.array_equal(again.phi, first.phi) and np.array_equal(again.inv_lam, first.inv_lam)
    assert (again.near != first.near).nnz == 0
    ModalCompliance(stiffness, surface, modes=9, radius=0.02, cache=tmp_path)   # other settings: another file
    assert len(list(tmp_path.glob("*.npz"))) == 2


def test_a_response_read_from_the_modes_and_the_near_field_is_exact_at_the_forces_and_reads_0_inside(banana):
    scene, rest, stiffness, surface = banana
    modal = ModalCompliance.for_surface(stiffness, scene.object.faces, read=surface)
    exact = ExactCompliance(stiffness)
    rows = coordinates(stiffness, surface)
    inside = np.setdiff1d(np.arange(3 * stiffness.n_free), rows)
    assert inside.size > 0
    rng = np.random.default_rng(4)
    for centre in rng.choice(surface, size=3, replace=False):
        patch = surface[np.argsort(np.linalg.norm(rest[surface] - rest[centre], axis=1))[:6]]   # a tool's dent
        w = np.tile(rng.normal(size=3), len(patch))
        got, want = modal.response(patch, w), exact.response(patch, w)
        own = coordinates(stiffness, patch)
        # where the forces act the near field is exact (float32 modes: 1e-7); over the surface the far field is
        # the modes' (measured 0.4-5% at ci); nothing is read inside
        assert np.linalg.norm(got[own] - want[own]) < 1e-5 * np.linalg.norm(want[own])
        assert np.linalg.norm(got[rows] - want[rows]) < 0.1 * np.linalg.norm(want[rows])
        assert not got[inside].any() and want[inside].any()


def test_nonnegative_qp_matches_nnls_including_nearly_dependent_rows():
    rng = np.random.default_rng(3)
    for k in (1, 3, 40, 200):
        for trial in range(6):
            a = rng.normal(size=(k + 2, k))
            if trial % 2 and k > 2:
                a[:, 1] = a[:, 0] + 1e-6 * rng.normal(size=k + 2)   # two faces sharing their vertices
            s = a.T @ a + 1e-9 * np.eye(k)
            t = rng.normal(size=k) + (0.5 if trial < 3 else -0.5)
            x = nonnegative_qp(s, t)
            chol = np.linalg.cholesky(s)
            want, _ = nnls(chol.T, np.linalg.solve(chol, t), maxiter=50 * k)
            assert np.all(x >= 0.0)
            # the same optimum (the objective; x itself is not unique where rows are dependent)
            objective = [0.5 * z @ s @ z - t @ z for z in (x, want)]
            assert objective[0] <= objective[1] + 1e-9 * max(1.0, abs(objective[1]))
            y = s @ x - t
            assert np.all(y >= -1e-7 * np.abs(t).max()) and abs(x @ y) <= 1e-6 * max(1.0, np.abs(t).max() ** 2)


def _press(scene, depth: float) -> np.ndarray:
    """The roller ``depth`` (m) below touching the banana (the middle of its workspace's reach)."""
    pose = press_pose(scene, 0.0)
    pose[2] -= depth
    return pose


def test_vertex_constraints_hold_every_surface_vertex_out_of_the_tool(banana):
    scene, rest, stiffness, surface = banana
    pose = _press(scene, 0.004)
    assert scene.tool.sdf(rest, pose).min() == pytest.approx(-0.004, abs=5e-4)
    prior = ContactPrior(scene, rest, np.arange(len(rest)), stiffness=stiffness, points="vertices")
    u = prior.displacement(pose)
    sdf = scene.tool.sdf((rest + u)[prior.surface], pose)
    # each surface vertex on or outside the gap, to 10% of the press (the roller's curvature is linearised)
    assert sdf.min() > prior.gap - 0.1 * (0.004 + prior.gap)
    assert 0.8 * (0.004 + prior.gap) < np.linalg.norm(u, axis=1).max() < 1.5 * (0.004 + prior.gap)
    # face constraints hold the faces' interiors too (their samples include the corners): a stiffer answer, and at
    # ci (9 mm faces under a 20 mm roller dip 0.5 mm, more than the gap) a clearly different one
    faces = ContactPrior(scene, rest, np.arange(len(rest)), stiffness=stiffness).displacement(pose)
    free = stiffness.free_index >= 0
    energy = [float(v[free].reshape(-1) @ stiffness.hessian @ v[free].reshape(-1)) for v in (u, faces)]
    assert energy[0] <= 1.01 * energy[1]
    assert np.linalg.norm(u - faces) > 0.1 * np.linalg.norm(faces)
    with pytest.raises(InputError, match="unknown contact points 'edges'"):
        ContactPrior(scene, rest, np.arange(len(rest)), stiffness=stiffness, points="edges")


def test_the_modal_prior_is_built_by_name_and_only_for_a_contact_or_edge_prior_on_its_own_mesh(banana, tmp_path,
                                                                                              monkeypatch):
    scene, rest, stiffness, surface = banana
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    prior = physics_prior("contact", scene, rest, np.arange(len(rest)), compliance="modal")
    assert isinstance(prior.compliance, ModalCompliance) and prior.points == "vertices"
    assert list((tmp_path / "colgnn" / "compliance").glob("*.npz"))
    pose = _press(scene, 0.004)
    exact = ContactPrior(scene, rest, np.arange(len(rest)), stiffness=stiffness, points="vertices")
    # at ci the near field (4 mean edges, 36 mm) reaches most of the roller's contact: close to exact
    assert np.linalg.norm(prior.displacement(pose) - exact.displacement(pose)) < 0.05 * np.linalg.norm(
        exact.displacement(pose))
    with pytest.raises(InputError, match="modal compliance is for the contact or edge prior"):
        physics_prior("tip", scene, rest, np.arange(len(rest)), compliance="modal")
    with pytest.raises(InputError, match="unknown prior compliance 'dense': choose one of .*'modal_response'"):
        physics_prior("contact", scene, rest, np.arange(len(rest)), compliance="dense")
    # the response from the modes too, read at the nodes and the surface: the far field is the modes' (measured:
    # 11% of the exact displacement's norm at ci, the largest difference 4% of the largest displacement)
    nodes = surface[::2]
    fast = physics_prior("contact", scene, rest, nodes, compliance="modal_response").displacement(pose)
    want = exact.displacement(pose)[nodes]
    assert np.linalg.norm(fast - want) < 0.15 * np.linalg.norm(want)
    assert np.abs(fast - want).max() < 0.06 * np.abs(want).max()
    template = template_from_scene(scene)
    with pytest.raises(InputError, match="prior_compliance needs contact_prior"):
        Simulator(template, ModelConfig(order=0, quasi_static=True, prior_compliance="modal"))
