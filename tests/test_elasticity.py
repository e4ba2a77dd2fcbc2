"""Stable Neo-Hookean energy: rest state, finite differences, PSD projection, lumped mass."""

from types import SimpleNamespace

import numpy as np
import pytest

from colgnn_core.geometry.transforms import axis_angle_quat, quat_to_matrix
from colgnn_core.sim.elasticity import HJ_BASIS, StableNeoHookean, lame_parameters, lumped_mass
from tests.helpers.sim_scenes import box_tet_mesh

RUBBER = SimpleNamespace(youngs_modulus=1e5, poisson_ratio=0.4, density=1000.0)


@pytest.fixture(scope="module")
def mesh():
    return box_tet_mesh([0, 0, 0], [0.1, 0.05, 0.03], (3, 2, 2))


def deformed(mesh, scale=0.004, seed=0):
    """A smooth stretch + shear + random jiggle that keeps every tet positive."""
    rng = np.random.default_rng(seed)
    x = mesh.vertices @ np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.15], [0.05, 0.0, 1.1]]).T
    return x + rng.normal(scale=scale, size=x.shape)


def test_rest_state_has_zero_energy_and_gradient(mesh):
    e = StableNeoHookean(mesh, RUBBER)
    assert abs(e.energy(mesh.vertices)) < 1e-12
    assert np.abs(e.gradient(mesh.vertices)).max() < 1e-9
    # Rigid motions too: the energy is rotation invariant.
    r = quat_to_matrix(axis_angle_quat([1.0, 2.0, 3.0], 0.7))
    x = mesh.vertices @ r.T + [0.3, -0.1, 2.0]
    assert abs(e.energy(x)) < 1e-12
    assert np.abs(e.gradient(x)).max() < 1e-9


def test_gradient_matches_finite_differences(mesh):
    e = StableNeoHookean(mesh, RUBBER)
    x = deformed(mesh)
    assert e.jacobians(x).min() > 0.2
    g = e.gradient(x)
    h = 1e-7
    fd = np.zeros_like(x)
    for i in range(len(x)):
        for d in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, d] += h
            xm[i, d] -= h
            fd[i, d] = (e.energy(xp) - e.energy(xm)) / (2 * h)
    assert np.abs(g - fd).max() < 1e-6 * np.abs(g).max()
    assert np.abs(g).max() > 1.0  # a real, non-trivial gradient (N)


def test_hessian_matches_finite_differences(mesh):
    e = StableNeoHookean(mesh, RUBBER)
    x = deformed(mesh)
    hmat = e.hessian(x, project_psd=False).toarray()
    h = 1e-6
    fd = np.zeros_like(hmat)
    flat = x.reshape(-1)
    for c in range(len(flat)):
        xp, xm = flat.copy(), flat.copy()
        xp[c] += h
        xm[c] -= h
        fd[:, c] = (e.gradient(xp.reshape(-1, 3)) - e.gradient(xm.reshape(-1, 3))).reshape(-1) / (2 * h)
    assert np.abs(hmat - fd).max() < 1e-6 * np.abs(hmat).max()
    assert np.abs(hmat - hmat.T).max() < 1e-9 * np.abs(hmat).max()


def test_projected_hessian_is_psd_and_unprojected_is_not(mesh):
    e = StableNeoHookean(mesh, RUBBER)
    # Strong compression: the λ(J−α)·∂²J term makes the exact Hessian indefinite.
    x = deformed(mesh) * np.array([1.0, 1.0, 0.45])
    assert e.jacobians(x).min() > 0
    exact = np.linalg.eigvalsh(e.hessian(x, project_psd=False).toarray())
    proj = np.linalg.eigvalsh(e.hessian(x, project_psd=True).toarray())
    assert exact.min() < -1e-3 * exact.max()
    assert proj.min() > -1e-9 * proj.max()


def test_rest_hessian_matches_linear_elasticity_moduli():
    """At rest, SNH's Lamé re-parameterisation reproduces linear elasticity (Smith et al. 2018, §3.4)."""
    mesh = box_tet_mesh([0, 0, 0], [0.02, 0.02, 0.02], (1, 1, 1))
    e = StableNeoHookean(mesh, RUBBER)
    mu, lam = lame_parameters(RUBBER.youngs_modulus, RUBBER.poisson_ratio)
    # Uniform strain ε: energy ≈ V (μ ε:ε + λ/2 tr(ε)²) for small ε.
    eps = 1e-5 * np.array([[1.0, 0.3, 0.0], [0.3, -0.5, 0.2], [0.0, 0.2, 0.7]])
    x = mesh.vertices + mesh.vertices @ eps.T
    expected = 0.02**3 * (mu * np.sum(eps * eps) + 0.5 * lam * np.trace(eps) ** 2)
    assert e.energy(x) == pytest.approx(expected, rel=1e-3)


def test_lumped_mass_sums_to_total_mass(mesh):
    m = lumped_mass(mesh, 1000.0)
    assert m.shape == (len(mesh.vertices),)
    assert m.sum() == pytest.approx(1000.0 * 0.1 * 0.05 * 0.03, rel=1e-12)
    assert np.all(m > 0)


def test_invalid_material_raises():
    with pytest.raises(ValueError):
        lame_parameters(1e5, 0.5)


def test_inversion_barrier_derivatives_and_blow_up():
    """Below J = 0.1 the inversion barrier is active: FD-consistent, and the energy is +inf at J <= 0."""
    mesh = box_tet_mesh([0, 0, 0], [0.02, 0.02, 0.02], (1, 1, 1))
    e = StableNeoHookean(mesh, RUBBER)
    rng = np.random.default_rng(1)
    x = mesh.vertices * np.array([1.0, 1.0, 0.06]) + rng.normal(scale=2e-5, size=mesh.vertices.shape)
    j = e.jacobians(x)
    assert 0 < j.min() < 0.1
    assert e.energy(x) > StableNeoHookean(mesh, RUBBER, j_hat=0.0).energy(x)
    g = e.gradient(x)
    flat = x.reshape(-1)
    hmat = e.hessian(x, project_psd=False).toarray()
    h = 1e-9
    fd_g = np.zeros_like(flat)
    fd_h = np.zeros_like(hmat)
    for c in range(len(flat)):
        xp, xm = flat.copy(), flat.copy()
        xp[c] += h
        xm[c] -= h
        fd_g[c] = (e.energy(xp.reshape(-1, 3)) - e.energy(xm.reshape(-1, 3))) / (2 * h)
        fd_h[:, c] = (e.gradient(xp.reshape(-1, 3)) - e.gradient(xm.reshape(-1, 3))).reshape(-1) / (2 * h)
    assert np.abs(g.reshape(-1) - fd_g).max() < 1e-5 * np.abs(g).max()
    assert np.abs(hmat - fd_h).max() < 1e-5 * np.abs(hmat).max()
    inverted = mesh.vertices * np.array([1.0, 1.0, -0.5])
    assert e.energy(inverted) == np.inf


def _clamped_numerically(e: StableNeoHookean, x: np.ndarray) -> np.ndarray:
    """[K,12,12]: each tet's exact 9x9 dPsi/dF2, eigen-decomposed by numpy and its negative eigenvalues set to 0,
    mapped to the 12 corner coordinates (H12 = V D^T H_F D)."""
    f = e.deformation_gradients(x)
    _, ic, _, cof, dpsi, d2psi = e._stress(f)
    s = 1.0 / (1.0 + ic)
    hf = np.einsum("kn,ijn->kij", f.reshape(-1, 9), HJ_BASIS) * dpsi[:, None, None]
    hf += (2 * e.mu * s * s)[:, None, None] * np.einsum("ki,kj->kij", f.reshape(-1, 9), f.reshape(-1, 9))
    hf += d2psi[:, None, None] * np.einsum("ki,kj->kij", cof.reshape(-1, 9), cof.reshape(-1, 9))
    hf[:, np.arange(9), np.arange(9)] += (e.mu * (1 - s))[:, None]
    exact = np.matmul(e.dfdx.transpose(0, 2, 1), np.matmul(hf, e.dfdx)) * e.volumes[:, None, None]
    assert np.allclose(exact, e.element_hessians(x, project_psd=False), rtol=1e-10, atol=1e-8 * np.abs(exact).max())
    w, q = np.linalg.eigh(hf)
    clamped = np.einsum("kij,kj,klj->kil", q, np.maximum(w, 0), q)
    return np.matmul(e.dfdx.transpose(0, 2, 1), np.matmul(clamped, e.dfdx)) * e.volumes[:, None, None], w.min()


@pytest.mark.parametrize("case", ["barrier active", "rotated rest", "inverted, no barrier", "nearly flat"])
def test_compiled_psd_projection_equals_eigen_clamping(case):
    """The compiled per-tet projection (analytic eigensystem, Jacobi SVD and eigh) equals clamping numpy's
    eigendecomposition of the exact dPsi/dF2: where projection matters, at repeated singular values (a rigidly
    turned rest), for an inverted tet (the sign carried by the last singular value) and a nearly flat one."""
    mesh = box_tet_mesh([0, 0, 0], [0.03, 0.02, 0.02], (2, 1, 1))
    rng = np.random.default_rng(5)
    e = StableNeoHookean(mesh, RUBBER, j_hat=0.0 if case.startswith("inverted") else 0.1)
    if case == "barrier active":
        x = mesh.vertices @ np.array([[1.3, 0.2, 0.0], [0.0, 0.5, 0.1], [0.1, 0.0, 0.12]]).T
        x = x + rng.normal(scale=1e-4, size=x.shape)
        assert 0 < e.jacobians(x).min() < 0.1
    elif case == "rotated rest":
        x = mesh.vertices @ quat_to_matrix(axis_angle_quat([1.0, 2.0, 3.0], 0.7)).T
    elif case == "inverted, no barrier":
        x = mesh.vertices * np.array([1.1, 0.9, -0.8]) + rng.normal(scale=1e-4, size=mesh.vertices.shape)
        assert e.jacobians(x).max() < 0
    else:
        x = mesh.vertices * np.array([1.0, 1.0, 1e-3]) + rng.normal(scale=1e-7, size=mesh.vertices.shape)
        assert 0 < e.jacobians(x).min() < 0.01
    numeric, w_min = _clamped_numerically(e, x)
    if case != "rotated rest":
        assert w_min < 0  # the case where projection matters
    compiled = e.element_hessians(x, project_psd=True)
    assert np.abs(compiled - numeric).max() < 1e-9 * np.abs(numeric).max()
