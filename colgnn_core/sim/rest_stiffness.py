"""Linear elasticity at the settled rest: the factorised free stiffness and its cached unit-force responses.

The physics priors (``sim.tip_prior``, ``sim.contact_prior``) answer a tool's contact with the displacement that
minimises 1/2 u^T K u under a few linear constraints on surface points: u = K^-1 A^T (A K^-1 A^T)^-1 d. The
columns K^-1 A^T are combinations of K^-1 E_v, the free displacement for a unit force on each coordinate of one
vertex v. Those are three back-substitutions per vertex, solved together for the vertices a step needs and kept in
a least-recently-used cache, so contact that stays in one place pays for them once.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
from scipy import sparse

from colgnn_core.errors import InputError
from colgnn_core.sim.elasticity import StableNeoHookean
from colgnn_core.sim.linear_solve import cholesky_solver

__all__ = ["RestStiffness"]


class RestStiffness:
    """K, the stable Neo-Hookean Hessian at the settled rest with the glued vertices fixed, factorised.

    scene: its object (tet mesh), material and glued vertices; rest_mesh: [N_mesh,3] the settled rest (m);
    cache_vertices: how many vertices' K^-1 E_v [3, 3N_free] are kept (float64: 72 N_free bytes each).
    Set-up factorises K (seconds at full resolution).
    """

    def __init__(self, scene, rest_mesh: np.ndarray, cache_vertices: int = 64):
        self.rest = np.asarray(rest_mesh, dtype=np.float64)
        n = scene.object.vertices.shape[0]
        if self.rest.shape != (n, 3) or not np.all(np.isfinite(self.rest)):
            raise InputError(f"the physics prior's rest must be a finite [{n},3] array, got {self.rest.shape}")
        pinned = np.zeros(n, dtype=bool)
        pinned[np.asarray(scene.pinned, dtype=np.int64)] = True
        self.free_index = np.full(n, -1, dtype=np.int64)   # [N_mesh] row of each free vertex, -1 when glued
        free = np.flatnonzero(~pinned)
        self.free_index[free] = np.arange(free.size)
        self.n_free = int(free.size)
        dof = (3 * free[:, None] + np.arange(3)).reshape(-1)
        h = StableNeoHookean(scene.object, scene.material).hessian(self.rest).tocsr()
        self.hessian: sparse.csr_matrix = h[dof][:, dof].tocsr()   # [3N_free,3N_free] K (N/m)
        self.hessian.sum_duplicates()
        self.solve = cholesky_solver(self.hessian)                 # [3N_free(,k)] force (N) -> displacement (m)
        digest = hashlib.sha256()
        for part in (self.hessian.indptr, self.hessian.indices, self.hessian.data):
            digest.update(np.ascontiguousarray(part).tobytes())
        self.fingerprint = digest.hexdigest()[:16]                 # names K in on-disk caches (sim.compliance)
        self.cache_vertices = int(cache_vertices)
        self._columns: OrderedDict[int, np.ndarray] = OrderedDict()

    def columns(self, vertices: list[int]) -> list[np.ndarray]:
        """K^-1 E_v [3, 3N_free] for each free vertex v of ``vertices`` (mesh ids). Missing ones are solved
        together, in one multi-right-hand-side pass."""
        missing = [v for v in dict.fromkeys(vertices) if v not in self._columns]
        if missing:
            rhs = np.zeros((3 * self.n_free, 3 * len(missing)))
            for j, v in enumerate(missing):
                rhs[3 * self.free_index[v] + np.arange(3), 3 * j + np.arange(3)] = 1.0
            sol = self.solve(rhs)
            for j, v in enumerate(missing):
                self._columns[v] = np.ascontiguousarray(sol[:, 3 * j:3 * j + 3].T)
        for v in vertices:
            self._columns.move_to_end(v)
        out = [self._columns[v] for v in vertices]
        limit = max(self.cache_vertices, len(set(vertices)))  # never evict what this call returns
        while len(self._columns) > limit:
            self._columns.popitem(last=False)
        return out

    def to_nodes(self, free_u: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """[len(nodes),3] (m): the free displacement ``free_u`` [3N_free] at mesh vertices ``nodes``; 0 where glued."""
        u = np.zeros((nodes.size, 3))
        rows = self.free_index[nodes]
        moving = rows >= 0
        u[moving] = free_u.reshape(-1, 3)[rows[moving]]
        return u
