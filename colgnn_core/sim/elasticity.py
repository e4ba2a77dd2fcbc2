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

import math

import numpy as np
import scipy.sparse as sp
from numba import njit

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


@njit(cache=True, inline="always")
def _barrier_derivatives(jdet: float, j_hat: float, stiffness: float) -> tuple[float, float]:
    """dPsi_inv/dJ and d2Psi_inv/dJ2 of the inversion barrier (module docstring; 0 above j_hat)."""
    if not (j_hat > 0.0 and jdet < j_hat):
        return 0.0, 0.0
    r = jdet / j_hat
    ln = math.log(r) if r > 0.0 else -math.inf
    d = r - 1.0
    return (stiffness * (-2.0 * d * ln - d * d / r) / j_hat,
            stiffness * (-2.0 * ln - 4.0 * d / r + d * d / (r * r)) / (j_hat * j_hat))


@njit(cache=True, inline="always")
def _deformation(xt: np.ndarray, g: np.ndarray, f: np.ndarray, cof: np.ndarray) -> tuple[float, float]:
    """F [3,3] = sum_a x_a G_a^T of one tet (corners ``xt`` [4,3], ``g`` its gradient operator [4,3]) and its
    cofactor ``cof`` (columns f1 x f2, f2 x f0, f0 x f1), both written in place; returns (I_C, J)."""
    for i in range(3):
        for j in range(3):
            f[i, j] = xt[0, i] * g[0, j] + xt[1, i] * g[1, j] + xt[2, i] * g[2, j] + xt[3, i] * g[3, j]
    ic = 0.0
    for i in range(3):
        for j in range(3):
            ic += f[i, j] * f[i, j]
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        cof[0, i] = f[1, i1] * f[2, i2] - f[2, i1] * f[1, i2]
        cof[1, i] = f[2, i1] * f[0, i2] - f[0, i1] * f[2, i2]
        cof[2, i] = f[0, i1] * f[1, i2] - f[1, i1] * f[0, i2]
    return ic, f[0, 0] * cof[0, 0] + f[1, 0] * cof[1, 0] + f[2, 0] * cof[2, 0]


@njit(cache=True)
def _elastic_gradient(xt: np.ndarray, tets: np.ndarray, grad_op: np.ndarray, volumes: np.ndarray, mu: float,
                      lam: float, alpha: float, j_hat: float, inv_stiffness: float, n_vertices: int) -> np.ndarray:
    """dE/dx [N,3] (N) from corner positions ``xt`` [K,4,3] (m): per tet V P G^T (P the first Piola stress),
    summed into its corners."""
    out = np.zeros((n_vertices, 3))
    f = np.empty((3, 3))
    cof = np.empty((3, 3))
    for e in range(xt.shape[0]):
        g = grad_op[e]
        ic, jdet = _deformation(xt[e], g, f, cof)
        b1, _ = _barrier_derivatives(jdet, j_hat, inv_stiffness)
        ca = mu * (1.0 - 1.0 / (1.0 + ic))
        cc = lam * (jdet - alpha) + b1
        vol = volumes[e]
        for a in range(4):
            v = tets[e, a]
            for i in range(3):
                acc = 0.0
                for j in range(3):
                    acc += (ca * f[i, j] + cc * cof[i, j]) * g[a, j]
                out[v, i] += vol * acc
    return out


_JACOBI_SWEEPS = 30  # cyclic Jacobi sweeps for a 3x3 (converges quadratically: 4-6 in practice)


@njit(cache=True, inline="always")
def _rotate_columns(m: np.ndarray, p: int, q: int, c: float, s: float) -> None:
    """Columns p, q of ``m`` [3,3] <- (c m_p - s m_q, s m_p + c m_q), in place."""
    for i in range(3):
        mp, mq = m[i, p], m[i, q]
        m[i, p] = c * mp - s * mq
        m[i, q] = s * mp + c * mq


@njit(cache=True)
def _eigh3(a: np.ndarray, w: np.ndarray, v: np.ndarray) -> None:
    """Eigenvalues ``w`` [3] and eigenvector columns ``v`` [3,3] of the symmetric ``a`` [3,3] (destroyed) by cyclic
    Jacobi rotations: a few hundred flops, where a LAPACK call from compiled code costs microseconds of overhead."""
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(_JACOBI_SWEEPS):
        off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
        scale = abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2]) + off
        if off <= 1e-18 * scale:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = a[p, q]
            if apq == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            _rotate_columns(a, p, q, c, s)  # a <- a J, J = [[c, s], [-s, c]] on (p, q)
            for j in range(3):               # a <- J^T a
                ap, aq = a[p, j], a[q, j]
                a[p, j] = c * ap - s * aq
                a[q, j] = s * ap + c * aq
            _rotate_columns(v, p, q, c, s)
    for i in range(3):
        w[i] = a[i, i]


@njit(cache=True)
def _svd3(f: np.ndarray, u: np.ndarray, sig: np.ndarray, v: np.ndarray) -> None:
    """Rotation-variant SVD f = u diag(sig) v^T of ``f`` [3,3] (Smith et al. 2019): u and v rotations, |sig|
    descending, sig[2] < 0 when det f < 0. One-sided Jacobi on f's columns (accurate for every singular value)."""
    a = f.copy()
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(_JACOBI_SWEEPS):
        rotated = False
        for p, q in ((0, 1), (0, 2), (1, 2)):
            alpha = a[0, p] * a[0, p] + a[1, p] * a[1, p] + a[2, p] * a[2, p]
            beta = a[0, q] * a[0, q] + a[1, q] * a[1, q] + a[2, q] * a[2, q]
            gamma = a[0, p] * a[0, q] + a[1, p] * a[1, q] + a[2, p] * a[2, q]
            if gamma == 0.0 or abs(gamma) <= 1e-17 * math.sqrt(alpha * beta):
                continue
            rotated = True
            zeta = (beta - alpha) / (2.0 * gamma)
            t = (1.0 if zeta >= 0.0 else -1.0) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
            c = 1.0 / math.sqrt(1.0 + t * t)
            s = c * t
            _rotate_columns(a, p, q, c, s)
            _rotate_columns(v, p, q, c, s)
        if not rotated:
            break
    for i in range(3):
        sig[i] = math.sqrt(a[0, i] * a[0, i] + a[1, i] * a[1, i] + a[2, i] * a[2, i])
    for i in range(2):  # sort descending (selection sort of three); a swap negates one column to keep det v = +1
        k = i
        for j in range(i + 1, 3):
            if sig[j] > sig[k]:
                k = j
        if k != i:
            sig[i], sig[k] = sig[k], sig[i]
            for r in range(3):
                a[r, i], a[r, k] = a[r, k], -a[r, i]
                v[r, i], v[r, k] = v[r, k], -v[r, i]
    for j in range(3):
        if sig[j] > 0.0:
            for i in range(3):
                u[i, j] = a[i, j] / sig[j]
    if not sig[2] > 0.0:  # a flat tet: the third column completes the frame
        u[0, 2] = u[1, 0] * u[2, 1] - u[2, 0] * u[1, 1]
        u[1, 2] = u[2, 0] * u[0, 1] - u[0, 0] * u[2, 1]
        u[2, 2] = u[0, 0] * u[1, 1] - u[1, 0] * u[0, 1]
    det_u = (u[0, 0] * (u[1, 1] * u[2, 2] - u[2, 1] * u[1, 2]) - u[0, 1] * (u[1, 0] * u[2, 2] - u[2, 0] * u[1, 2])
             + u[0, 2] * (u[1, 0] * u[2, 1] - u[2, 0] * u[1, 1]))
    if det_u < 0.0:  # det f < 0: an inverted tet keeps u a rotation and carries the sign in sig[2]
        for i in range(3):
            u[i, 2] = -u[i, 2]
        sig[2] = -sig[2]


@njit(cache=True)
def _projected_element_hessians(xt: np.ndarray, grad_op: np.ndarray, volumes: np.ndarray, mu: float, lam: float,
                                alpha: float, j_hat: float, inv_stiffness: float) -> np.ndarray:
    """Per-tet PSD-projected 12x12 Hessians [K,12,12] (J/m^2) from corner positions ``xt`` [K,4,3] (m): the same
    numbers as clamping the eigenvalues of each tet's exact dPsi/dF2, through its analytic eigensystem (Smith et al.
    2019: three scaling modes from a 3x3 block, three twists, three flips), one tet at a time so that nothing
    [K,9,9] is ever materialised.
    Why: the vectorised numpy form spent about 370 ms a Newton iteration on the full-resolution bunny's 19,836
    tets, most of the solver's time per iteration."""
    k_count = xt.shape[0]
    out = np.empty((k_count, 12, 12))
    f = np.empty((3, 3))
    cof = np.empty((3, 3))
    amat = np.empty((3, 3))
    u = np.empty((3, 3))
    sig = np.empty(3)
    vm = np.empty((3, 3))
    w_scale = np.empty(3)
    e_scale = np.empty((3, 3))
    q = np.empty((9, 9))
    lam_q = np.empty(9)
    wv = np.empty(12)
    outer = np.empty((3, 3, 9))
    r2 = 1.0 / math.sqrt(2.0)
    for e in range(k_count):
        g = grad_op[e]
        ic, jdet = _deformation(xt[e], g, f, cof)
        b1, b2 = _barrier_derivatives(jdet, j_hat, inv_stiffness)
        s = 1.0 / (1.0 + ic)
        ca = mu * (1.0 - s)
        cb = 2.0 * mu * s * s
        cc = lam * (jdet - alpha) + b1
        cl = lam + b2
        _svd3(f, u, sig, vm)
        s0, s1, s2 = sig[0], sig[1], sig[2]
        gam0, gam1, gam2 = s1 * s2, s0 * s2, s0 * s1
        gam = (gam0, gam1, gam2)
        sg = (s0, s1, s2)
        for i in range(3):
            for j in range(3):
                amat[i, j] = cb * sg[i] * sg[j] + cl * gam[i] * gam[j]
        amat[0, 1] += cc * s2
        amat[1, 0] += cc * s2
        amat[0, 2] += cc * s1
        amat[2, 0] += cc * s1
        amat[1, 2] += cc * s0
        amat[2, 1] += cc * s0
        for i in range(3):
            amat[i, i] += ca
        _eigh3(amat, w_scale, e_scale)
        for a in range(3):  # outer[a, b] = vec(u_a v_b^T), row-major
            for b in range(3):
                for i in range(3):
                    for j in range(3):
                        outer[a, b, 3 * i + j] = u[i, a] * vm[j, b]
        for m in range(3):
            for n in range(9):
                q[m, n] = (e_scale[0, m] * outer[0, 0, n] + e_scale[1, m] * outer[1, 1, n]
                           + e_scale[2, m] * outer[2, 2, n])
            lam_q[m] = w_scale[m]
        pairs = ((1, 2), (0, 2), (0, 1))
        for m in range(3):
            i, j = pairs[m]
            for n in range(9):
                q[3 + m, n] = r2 * (outer[j, i, n] - outer[i, j, n])
                q[6 + m, n] = r2 * (outer[j, i, n] + outer[i, j, n])
            lam_q[3 + m] = ca + cc * sg[m]
            lam_q[6 + m] = ca - cc * sg[m]
        # H12 = V D^T hf D with hf = sum_n max(lam_n, 0) q_n q_n^T, so H12 = V sum_n lam_n w_n w_n^T with
        # w_n = D^T q_n [12]: (D^T q)[3a+k] = sum_j G[a,j] q[3k+j] (D = d vec F / dx is G in blocks).
        for r in range(12):
            for c in range(12):
                out[e, r, c] = 0.0
        vol = volumes[e]
        for n in range(9):
            if not lam_q[n] > 0.0:
                continue
            for a in range(4):
                for kk in range(3):
                    wv[3 * a + kk] = g[a, 0] * q[n, 3 * kk] + g[a, 1] * q[n, 3 * kk + 1] + g[a, 2] * q[n, 3 * kk + 2]
            scale = vol * lam_q[n]
            for r in range(12):
                sr = scale * wv[r]
                for c in range(12):
                    out[e, r, c] += sr * wv[c]
    return out


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
        xt = np.ascontiguousarray(np.asarray(x, dtype=np.float64)[self.tets])
        return _elastic_gradient(xt, self.tets, self.grad_op, self.volumes, self.mu, self.lam, self.alpha,
                                 self.j_hat, self.inv_stiffness, self.n_vertices)

    def element_hessians(self, x: np.ndarray, project_psd: bool = True) -> np.ndarray:
        """Per-tet 12×12 Hessian blocks [K,12,12], PSD-projected if asked (then by the compiled kernel)."""
        if project_psd:
            xt = np.ascontiguousarray(np.asarray(x, dtype=np.float64)[self.tets])
            return _projected_element_hessians(xt, self.grad_op, self.volumes, self.mu, self.lam, self.alpha,
                                               self.j_hat, self.inv_stiffness)
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
        h12 = np.matmul(self.dfdx.transpose(0, 2, 1), np.matmul(hf, self.dfdx))
        return h12 * self.volumes[:, None, None]

    def hessian(self, x: np.ndarray, project_psd: bool = True) -> sp.csr_matrix:
        """∂²E/∂x² as CSR [3N,3N] (DOF order x0 y0 z0 x1 ...)."""
        h12 = self.element_hessians(x, project_psd)
        data = np.bincount(self._scatter, weights=h12.reshape(-1), minlength=self._nnz)
        n = 3 * self.n_vertices
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(n, n))
