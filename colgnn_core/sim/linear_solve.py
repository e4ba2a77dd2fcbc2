"""Sparse symmetric positive definite solves for the IPC solver's Newton systems and the interior fill.

A Newton step solves H p = r on the free degrees of freedom. ``NewtonSystemSolver`` tries, in order:

1. conjugate gradients preconditioned by the Cholesky factor of an earlier H with the same free set (the "lagged"
   factor: H changes little between Newton iterations and frames), at most LAGGED_CG_MAX_ITERATIONS;
2. conjugate gradients with a Jacobi preconditioner, at most PCG_MAX_ITERATIONS, until it has once failed or once
   needed more than JACOBI_SLOW_ITERATIONS;
3. a fresh Cholesky factorisation, which solves exactly and becomes the lagged factor.

Why: on the soft scenes the mass term M/h² dominates H, and Jacobi CG converges in ~200 iterations (0.2 s on
full-resolution knife_torus, where a factorisation took 1.4 s). On a stiffer object
(cone_bunny at 1 MPa, full resolution) Jacobi CG did not converge in 1,000 iterations on most solves, so each solve
paid both; there a factorisation takes 0.7 s and the lagged-factor CG 2-28 iterations of 6 ms: 38 Newton solves of
a 6-frame stab took 12 s against 55 s. Every route stops at the same relative residual PCG_RTOL (or is exact), so
the converged Newton state is the same to the Newton tolerance.

Slow is as bad as failed. The glued banana at full resolution (17,832 free coordinates, soft) converged by Jacobi CG
in 200-400 iterations a solve, 30-40 Newton solves a frame on a deep press: minutes a frame. A factorisation costs
a few hundred CG iterations' worth once, and the lagged factor then solves each system in a few iterations for many
frames, so a system that needs more than JACOBI_SLOW_ITERATIONS switches the simulation to route 1 for good.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp

PCG_RTOL = 1e-9                 # CG stops at ||H p - r|| <= PCG_RTOL ||r||
PCG_MAX_ITERATIONS = 1000       # Jacobi CG; beyond, the system is factorised
LAGGED_CG_MAX_ITERATIONS = 40   # CG preconditioned by a lagged factor; beyond, the system is factorised afresh
JACOBI_SLOW_ITERATIONS = 100    # a Jacobi CG solve that needed more: the simulation factorises from then on


def cholesky_solver(h: sp.csr_matrix) -> Callable[[np.ndarray], np.ndarray]:
    """A solver ``b [n] -> x [n]`` (or ``[n,k] -> [n,k]``: k right-hand sides in one pass over the factor, about 3x
    cheaper than k calls) of ``h x = b`` for a symmetric positive definite CSR ``h`` [n,n]: cholespy's sparse
    Cholesky, else (no cholespy, or it refused the matrix) scipy's LU."""
    h = h.tocsr()
    h.sum_duplicates()
    try:
        import cholespy

        chol = cholespy.CholeskySolverD(h.shape[0], h.indptr.astype(np.int32), h.indices.astype(np.int32),
                                        h.data.astype(np.float64), cholespy.MatrixType.CSR)

        def solve(b: np.ndarray) -> np.ndarray:
            b = np.asarray(b, dtype=np.float64)
            b = np.ascontiguousarray(b if b.ndim == 2 else b.reshape(-1))
            x = np.zeros_like(b)
            chol.solve(b, x)
            return x

        return solve
    except (ImportError, ValueError, RuntimeError):
        from scipy.sparse.linalg import splu

        return splu(h.tocsc()).solve


def pcg_solve(h: sp.spmatrix, r: np.ndarray, preconditioner: Callable[[np.ndarray], np.ndarray] | None = None,
              max_iterations: int = PCG_MAX_ITERATIONS, stats: dict | None = None) -> np.ndarray | None:
    """Solve the SPD system ``h x = r`` by preconditioned conjugate gradients (Jacobi unless ``preconditioner``, an
    approximate inverse ``v -> H^-1 v``, is given); None when CG does not reach PCG_RTOL within ``max_iterations``
    (or the diagonal is not positive). ``stats['iterations']`` gets the iterations used."""
    import scipy.sparse.linalg as spla  # lazy: scipy's solvers are only needed by the simulator

    d = h.diagonal()
    if not np.all(d > 0):
        return None
    if not np.any(r):
        return np.zeros_like(r)
    # dtype given: without it LinearOperator probes the preconditioner once (a wasted triangular solve, 8 ms on the
    # full bunny, one per Newton solve).
    m = (sp.diags(1.0 / d) if preconditioner is None
         else spla.LinearOperator(h.shape, matvec=preconditioner, dtype=np.float64))
    count = [0]

    def counted(_):
        count[0] += 1

    x, info = spla.cg(h, r, rtol=PCG_RTOL, maxiter=max_iterations, M=m, callback=counted)
    if stats is not None:
        stats["iterations"] = count[0]
    return x if info == 0 and np.all(np.isfinite(x)) else None


class NewtonSystemSolver:
    """Solves one simulation's sequence of Newton systems (module docstring); keeps a lagged factor per free set."""

    def __init__(self) -> None:
        self._factors: dict[int, Callable[[np.ndarray], np.ndarray]] = {}
        self.jacobi_failed = False  # Jacobi CG failed or was slow once: not tried again
        self.factorisations = 0  # how many times a system was factorised (for tests and diagnostics)

    def solve(self, h: sp.csr_matrix, r: np.ndarray, key: int) -> np.ndarray:
        """x [n] with ``h x = r`` for an SPD ``h`` [n,n]; ``key`` names the free set (systems with the same key have
        the same sparsity and nearly the same values)."""
        lagged = self._factors.get(key)
        if lagged is not None:
            x = pcg_solve(h, r, lagged, LAGGED_CG_MAX_ITERATIONS)
            if x is not None:
                return x
        if not self.jacobi_failed:
            stats: dict = {}
            x = pcg_solve(h, r, stats=stats)
            self.jacobi_failed = x is None or stats.get("iterations", 0) > JACOBI_SLOW_ITERATIONS
            if x is not None:
                return x
        solve = cholesky_solver(h)
        self.factorisations += 1
        x = solve(r)
        if np.all(np.isfinite(x)):
            self._factors[key] = solve
            return x
        import scipy.sparse.linalg as spla  # the last resort: a factorisation that returned non-finite values

        self._factors.pop(key, None)
        return spla.spsolve(h.tocsc(), r)
