"""Stable Neo-Hookean elasticity on linear tetrahedra (Smith, de Goes & Kim 2018).

Energy density (their eq. 14, Lamé parameters re-parameterised so that small
strains match linear elasticity, section 3.4)::

    Ψ(F) = μ/2 (I_C − 3) − μ/2 log(I_C + 1) + λ/2 (J − α)² − Ψ(I),
    α = 1 + 3μ/(4λ),  μ = 4/3 μ_lame,  λ = λ_lame + 5/6 μ_lame,

with I_C = ‖F‖²_F and J = det F. The constant Ψ(I) is subtracted so the rest
state has zero energy; its gradient there is zero by the choice of α.

Stable Neo-Hookean is finite at J ≤ 0 (that is its point), so a sharp tool tip can
crush an element flat and Newton then wants to invert it. The IPC solver must keep
every tet uninverted, so an *inversion barrier* is added below J = ``j_hat`` (default
0.1, i.e. only beyond 90% volume loss)::

    Ψ_inv(J) = (λ + μ) · b(J/ĵ),   b(r) = −(r − 1)² ln r  for r < 1, else 0,

the same C² clamped-log barrier IPC uses for contact. It makes the energy +∞ at J → 0⁺
and leaves the model untouched for J ≥ ĵ. ``j_hat=0`` disables it.

Everything is vectorised over tets. The Hessian is assembled into a CSR matrix
whose sparsity pattern (and the COO→CSR scatter map) is computed once, so an
assembly is one ``np.bincount``. Per-element PSD projection clamps the
eigenvalues of the 9×9 ∂²Ψ/∂F² (the 12×12 block is Dᵀ H_F D, so it is PSD
whenever H_F is), using the analytic eigensystem rather than a batched eigh.

Units: positions in m, E in Pa, density in kg/m³, energy in J.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

# Levi-Civita symbol ε_ijk, for the Hessian of det F.
_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0
# ∂²J/∂F_il ∂F_jm = Σ_kn ε_ijk ε_lmn F_kn; precontract the two symbols: [9, 9, 9] (row (i,l), col (j,m), (k,n)).
HJ_BASIS = np.einsum("ijk,lmn->iljmkn", _EPS, _EPS).reshape(9, 9, 9)


def lame_parameters(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """Classic Lamé (μ, λ) in Pa from Young's modulus (Pa) and Poisson's ratio."""
    e, nu = float(youngs_modulus), float(poisson_ratio)
    if not (e > 0 and -1.0 < nu < 0.5):
        raise ValueError(f"invalid material: E={e}, nu={nu} (need E>0, -1<nu<0.5)")
    mu = e / (2.0 * (1.0 + nu))
    lam = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def tet_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes [K] (m³) of tets [K,4] on vertices [N,3]."""
    x = vertices[tets]
    ds = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
    return np.linalg.det(ds) / 6.0


def lumped_mass(mesh, density: float) -> np.ndarray:
    """Lumped vertex masses [N] (kg): each tet gives ρ·V/4 to each of its corners."""
    vol = tet_volumes(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.tets))
    if np.any(vol <= 0):
        raise ValueError(f"{int(np.sum(vol <= 0))} tets have non-positive rest volume")
    mass = np.zeros(len(mesh.vertices))
    np.add.at(mass, np.asarray(mesh.tets).reshape(-1), np.repeat(density * vol / 4.0, 4))
    return mass


class StableNeoHookean:
    """Stable Neo-Hookean energy of a tet mesh.

    ``mesh`` needs ``vertices`` [N,3] (rest, m) and ``tets`` [K,4] (positive
    volume); ``material`` needs ``youngs_modulus`` (Pa) and ``poisson_ratio``.
    Positions ``x`` passed to the methods are [N,3] world positions (m).
    """

    def __init__(self, mesh, material, j_hat: float = 0.1) -> None:
        self.rest = np.asarray(mesh.vertices, dtype=np.float64)
        self.tets = np.asarray(mesh.tets, dtype=np.int64)
        self.n_vertices = len(self.rest)
        mu_l, lam_l = lame_parameters(material.youngs_modulus, material.poisson_ratio)
        self.mu = 4.0 / 3.0 * mu_l
        self.lam = lam_l + 5.0 / 6.0 * mu_l
        self.alpha = 1.0 + 0.75 * self.mu / self.lam
        self.psi_rest = 0.5 * self.lam * (1.0 - self.alpha) ** 2 - 0.5 * self.mu * np.log(4.0)
        self.j_hat = float(j_hat)
        self.inv_stiffness = self.lam + self.mu

        dm = self.edge_matrix(self.rest)
        self.volumes = np.linalg.det(dm) / 6.0
        if np.any(self.volumes <= 0):
            raise ValueError(f"{int(np.sum(self.volumes <= 0))} tets have non-positive rest volume")
        b = np.linalg.inv(dm)  # [K,3,3], F = Ds · B
        # G[a, j] = ∂F_ij/∂x_{a,i}: rows of B for corners 1..3, minus their sum for corner 0.
        self.grad_op = np.concatenate([-b.sum(axis=1, keepdims=True), b], axis=1)  # [K,4,3]
        # D[(i,j),(a,k)] = δ_ik G[a,j]  (row-major vec(F), DOF order 3a+k): [K,9,12].
        k = len(self.tets)
        d = np.zeros((k, 3, 3, 4, 3))
        for i in range(3):
            d[:, i, :, :, i] = self.grad_op.transpose(0, 2, 1)
        self.dfdx = d.reshape(k, 9, 12)
        self._init_pattern()

    # ----------------------------------------------------------------- helpers
    def edge_matrix(self, x: np.ndarray) -> np.ndarray:
        """Ds [K,3,3]: the edge vectors x1 - x0, x2 - x0, x3 - x0 of every tet as columns, for positions x [N,3]."""
        xt = x[self.tets]
        return np.stack([xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0], xt[:, 3] - xt[:, 0]], axis=2)

    def _init_pattern(self) -> None:
        """Sparsity pattern of the 3N×3N Hessian and the scatter map element entry -> CSR slot."""
        dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(-1, 12)  # [K,12]
        rows = np.repeat(dofs, 12, axis=1).reshape(-1)
        cols = np.tile(dofs, (1, 12)).reshape(-1)
        n = 3 * self.n_vertices
        key = rows * n + cols
        uniq, inverse = np.unique(key, return_inverse=True)
        self._scatter = inverse.reshape(-1)
        self._indptr = np.searchsorted(uniq // n, np.arange(n + 1)).astype(np.int64)
        self._indices = (uniq % n).astype(np.int64)
        self._nnz = len(uniq)

    def deformation_gradients(self, x: np.ndarray) -> np.ndarray:
        """F [K,3,3] for positions x [N,3]."""
        xt = np.asarray(x, dtype=np.float64)[self.tets]  # [K,4,3]
        return np.einsum("kai,kaj->kij", xt, self.grad_op)

    def jacobians(self, x: np.ndarray) -> np.ndarray:
        """J = det F [K] (volume ratio) for positions x [N,3]."""
        return np.linalg.det(self.edge_matrix(np.asarray(x, dtype=np.float64))) / (6.0 * self.volumes)

    @staticmethod
    def cofactor(f: np.ndarray) -> np.ndarray:
        """∂J/∂F [K,3,3] (cofactor matrix): columns f1×f2, f2×f0, f0×f1."""
        c0, c1, c2 = f[:, :, 0], f[:, :, 1], f[:, :, 2]
        return np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=2)

    # ------------------------------------------------------------------ energy
    def _inversion_barrier(self, j: np.ndarray, order: int):
        """Ψ_inv(J) and its first two derivatives in J (arrays [K]); +inf for J <= 0."""
        zero = np.zeros_like(j)
        if self.j_hat <= 0:
            return zero, zero, zero
        r = j / self.j_hat
        act = r < 1.0
        if not act.any():
            return zero, zero, zero
        b, b1, b2 = zero.copy(), zero.copy(), zero.copy()
        ra = r[act]
        with np.errstate(divide="ignore", invalid="ignore"):
            ln = np.where(ra > 0, np.log(np.where(ra > 0, ra, 1.0)), -np.inf)
            d = ra - 1.0
            b[act] = np.where(ra > 0, -d * d * ln, np.inf)
            if order > 0:
                b1[act] = -2.0 * d * ln - d * d / ra
                b2[act] = -2.0 * ln - 4.0 * d / ra + d * d / (ra * ra)
        k = self.inv_stiffness
        return k * b, k * b1 / self.j_hat, k * b2 / self.j_hat**2

    def energy_density(self, f: np.ndarray) -> np.ndarray:
        """Ψ(F) [K] (J/m³); +inf for inverted or flat elements when the inversion barrier is on."""
        ic = np.einsum("kij,kij->k", f, f)
        j = np.linalg.det(f)
        return (
            0.5 * self.mu * (ic - 3.0)
            - 0.5 * self.mu * np.log1p(ic)
            + 0.5 * self.lam * (j - self.alpha) ** 2
            - self.psi_rest
            + self._inversion_barrier(j, 0)[0]
        )

    def energy(self, x: np.ndarray) -> float:
        """Total elastic energy Σ V_e Ψ(F_e) (J)."""
        return float(self.volumes @ self.energy_density(self.deformation_gradients(x)))

    def _stress(self, f: np.ndarray):
        ic = np.einsum("kij,kij->k", f, f)
        j = np.linalg.det(f)
        cof = self.cofactor(f)
        a = self.mu * (1.0 - 1.0 / (1.0 + ic))
        _, b1, b2 = self._inversion_barrier(j, 2)
        dpsi_dj = self.lam * (j - self.alpha) + b1  # ∂Ψ/∂J
        p = a[:, None, None] * f + dpsi_dj[:, None, None] * cof
        return p, ic, j, cof, dpsi_dj, self.lam + b2

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """∂E/∂x [N,3] (N)."""
        f = self.deformation_gradients(x)
        p, *_ = self._stress(f)
        # grad of corner a, coordinate i: V Σ_j P_ij G_aj
        ge = np.einsum("kij,kaj->kai", p, self.grad_op) * self.volumes[:, None, None]
        g = np.zeros((self.n_vertices, 3))
        np.add.at(g, self.tets.reshape(-1), ge.reshape(-1, 3))
        return g

    def element_hessians(self, x: np.ndarray, project_psd: bool = True) -> np.ndarray:
        """Per-tet 12×12 Hessian blocks [K,12,12], PSD-projected if asked."""
        f = self.deformation_gradients(x)
        _, ic, j, cof, dpsi_dj, d2psi_dj2 = self._stress(f)
        k = len(f)
        fv = f.reshape(k, 9)
        gv = cof.reshape(k, 9)
        s = 1.0 / (1.0 + ic)
        hf = np.einsum("kn,ijn->kij", f.reshape(k, 9), HJ_BASIS) * dpsi_dj[:, None, None]
        hf += (2.0 * self.mu * s * s)[:, None, None] * fv[:, :, None] * fv[:, None, :]
        hf += d2psi_dj2[:, None, None] * gv[:, :, None] * gv[:, None, :]
        hf[:, np.arange(9), np.arange(9)] += (self.mu * (1.0 - s))[:, None]
        if project_psd:
            hf = self._project_analytic(f, self.mu * (1.0 - s), 2.0 * self.mu * s * s, dpsi_dj, d2psi_dj2)
        h12 = np.matmul(self.dfdx.transpose(0, 2, 1), np.matmul(hf, self.dfdx))
        return h12 * self.volumes[:, None, None]

    @staticmethod
    def _project_analytic(f, a, b, c, lam2) -> np.ndarray:
        """PSD projection of ∂²Ψ/∂F² = a·I + b·f fᵀ + lam2·g gᵀ + c·∂²J/∂F² via its analytic eigensystem.

        With the rotation-variant SVD F = U Σ Vᵀ (Smith et al. 2019), six eigenvectors are the
        twists/flips U T Vᵀ with eigenvalues a ± c·σ_k, and three are U diag(e) Vᵀ with e the
        eigenvectors of the 3×3 scaling block A = a I + b σσᵀ + lam2 γγᵀ + c Z (γ_i = Π_{j≠i} σ_j,
        Z_ij = σ_k for i≠j). Negative eigenvalues are clamped to 0. About 3× cheaper than a batched
        9×9 eigh and exact to round-off (tested against it).
        """
        k = len(f)
        u, sig, vt = np.linalg.svd(f)
        flip_u = np.linalg.det(u) < 0
        u[flip_u, :, 2] *= -1.0
        sig[flip_u, 2] *= -1.0
        flip_v = np.linalg.det(vt) < 0
        vt[flip_v, 2, :] *= -1.0
        sig[flip_v, 2] *= -1.0
        s0, s1, s2 = sig[:, 0], sig[:, 1], sig[:, 2]
        gam = np.stack([s1 * s2, s0 * s2, s0 * s1], axis=1)
        amat = b[:, None, None] * sig[:, :, None] * sig[:, None, :] + lam2[:, None, None] * gam[:, :, None] * gam[:,
                                                                                                                  None,
                                                                                                                  :]
        amat[:, 0, 1] += c * s2
        amat[:, 1, 0] += c * s2
        amat[:, 0, 2] += c * s1
        amat[:, 2, 0] += c * s1
        amat[:, 1, 2] += c * s0
        amat[:, 2, 1] += c * s0
        amat[:, np.arange(3), np.arange(3)] += a[:, None]
        w_scale, e_scale = np.linalg.eigh(amat)
        # Outer products u_a v_bᵀ of singular-vector columns, row-major vec: [K, 3(a), 3(b), 9].
        outer = (u[:, :, :, None, None] * vt.transpose(0, 2, 1)[:, None, None, :, :]
                 ).transpose(0, 2, 4, 1, 3).reshape(k, 3, 3, 9)
        q = np.empty((k, 9, 9))
        lam = np.empty((k, 9))
        diag = outer[:, np.arange(3), np.arange(3)]  # [K,3,9]: u_a v_aᵀ
        q[:, 0:3] = np.matmul(e_scale.transpose(0, 2, 1), diag)  # U diag(e_m) Vᵀ
        lam[:, 0:3] = w_scale
        r = 1.0 / np.sqrt(2.0)
        for m, (i, j, sk) in enumerate(((1, 2, s0), (0, 2, s1), (0, 1, s2))):
            q[:, 3 + m] = r * (outer[:, j, i] - outer[:, i, j])  # twist, eigenvalue a + c σ_k
            q[:, 6 + m] = r * (outer[:, j, i] + outer[:, i, j])  # flip, eigenvalue a − c σ_k
            lam[:, 3 + m] = a + c * sk
            lam[:, 6 + m] = a - c * sk
        return np.matmul(q.transpose(0, 2, 1) * np.maximum(lam, 0.0)[:, None, :], q)

    def hessian(self, x: np.ndarray, project_psd: bool = True) -> sp.csr_matrix:
        """∂²E/∂x² as CSR [3N,3N] (DOF order x0 y0 z0 x1 ...)."""
        h12 = self.element_hessians(x, project_psd)
        data = np.bincount(self._scatter, weights=h12.reshape(-1), minlength=self._nnz)
        n = 3 * self.n_vertices
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(n, n))
