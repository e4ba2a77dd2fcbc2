"""A physics prior for a smooth tool: linear elasticity at the settled rest, pushed out of the tool face by face.

Why: a tool presses on face interiors, between the mesh nodes. On the cow held by its legs (a sphere of radius
18 mm against faces of 6 mm at ``ci``), the vertices next to the contact stay 0.5-1.2 mm outside the sphere while
the body under them moves 3 mm, so a prior that pushes only the vertices inside the tool out of it moved the body
too little (0.61 relative displacement error on six sequences, offline). Constraining each face's deepest point
instead scored 0.43 on 20 training sequences, and holding it at the solver's gap 0.38 (0.46 on the next 40). A
network trained on the cow's data alone had scored 0.60 held-out (docs/FIDELITY.md, session 13).

The model (units: m):

* **Contact.** Frictionless: a surface face whose deepest point (the lowest tool SDF among
  ``(SAMPLE_LEVEL+1)(SAMPLE_LEVEL+2)/2`` barycentric samples) comes nearer the tool than the solver's gap
  (``gap``: dmin + dhat/2, where the ground truth's offset barrier holds it) is held at that distance along the
  tool's normal there, and is free to slide along it. Each such face is one constraint
  n . sum_k b_k u_k = d on its three vertices k (barycentric weights b).
* **Response.** u minimises 1/2 u^T K u (K the stable Neo-Hookean Hessian at the settled rest, glued vertices fixed)
  under the contact constraints A u >= d: u = K^-1 A^T lambda with lambda >= 0 the solution of the dual, a small
  non-negative least squares problem in A K^-1 A^T (a face that would pull is released). The set of faces grows
  over up to ``MAX_ROUNDS`` rounds, until no new face reaches the tool: each round adds the faces that the last
  answer pushed into the tool, and moves each face's point onto the surface from where the last answer left it
  (a fixed-point iteration on the tool's curvature).
* **No state.** A frictionless tool leaves nothing behind, so the prior is a function of the tool's pose. (A sharp
  cone drags its pocket along; ``sim.tip_prior`` carries that state.)

What it misses: a press on a ridge (the cow's back) where the ground truth's body leans to one side and the prior's
to the other; the truth's tool is the sphere's mesh (its facets tilt the contact force by up to about 9 degrees),
and a prior against that mesh scored worse on the training sequences (0.435 against 0.383).

Cost: one K^-1 E_v per vertex that contact reaches (``sim.rest_stiffness``, cached) and a dense solve of one
equation per face in contact. About 1-3 ms a step at ``ci`` on the cow (569 vertices); at full resolution (9,845)
set-up took 17 s and a first contact 1.5 s, so the prior is meant for ``ci`` meshes.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from colgnn_core.sim.ipc import DMIN_SCALE
from colgnn_core.sim.rest_stiffness import RestStiffness

__all__ = ["CACHE_BYTES", "MAX_ROUNDS", "SAMPLE_LEVEL", "ContactPrior"]

SAMPLE_LEVEL = 4  # barycentric samples per face: a triangular grid of (L+1)(L+2)/2 = 15 points
MAX_ROUNDS = 8    # active-set rounds per pose (the cow: 2-4)
CACHE_BYTES = 1 << 27  # 128 MiB of cached K^-1 E_v columns (72 N_free bytes a vertex)
_RIDGE = 1e-9     # relative ridge on A K^-1 A^T: constraints of faces that share their vertices are nearly dependent


def _barycentric_grid(level: int) -> np.ndarray:
    """[S,3] barycentric weights of a triangular grid with ``level`` intervals per edge."""
    return np.array([(i, j, level - i - j) for i in range(level + 1) for j in range(level + 1 - i)],
                    dtype=np.float64) / level


class ContactPrior:
    """The prior's displacement of graph nodes for tool poses, for one scene and settled rest (module docstring).

    scene: its object (tet mesh, surface faces), material, glued vertices and tool (any analytic shape);
    rest_mesh: [N_mesh,3] the settled rest (m); nodes: [N] mesh ids of the graph nodes the prior is given for.
    """

    def __init__(self, scene, rest_mesh: np.ndarray, nodes: np.ndarray):
        self.tool = scene.tool
        # The ground truth keeps the surface dmin to dmin + dhat away from the tool (the solver's offset barrier):
        # the prior holds it at the middle of that band. On the cow's training sequences, 0.43 -> 0.38.
        self.gap = (DMIN_SCALE + 0.5) * float(scene.dhat)
        self.stiffness = RestStiffness(scene, rest_mesh)
        # Keep every vertex that contact reaches while the cache stays under CACHE_BYTES (at ci: all of them).
        self.stiffness.cache_vertices = max(256, CACHE_BYTES // (72 * max(self.stiffness.n_free, 1)))
        self.rest = self.stiffness.rest
        self.nodes = np.asarray(nodes, dtype=np.int64)
        faces = np.asarray(scene.object.faces, dtype=np.int64)
        movable = (self.stiffness.free_index[faces] >= 0).any(axis=1)
        self.faces = faces[movable]                     # [F,3] surface faces with a free vertex (others cannot move)
        self.surface = np.unique(self.faces)            # their vertices
        self.samples = _barycentric_grid(SAMPLE_LEVEL)  # [S,3]

    def step(self, previous: None, pose_prev: np.ndarray, pose: np.ndarray) -> tuple[None, np.ndarray]:
        """(no state, the displacement [N,3] at ``pose`` [7]): the interface of ``sim.tip_prior.TipPrior``."""
        return None, self.displacement(pose)

    def displacement(self, pose: np.ndarray) -> np.ndarray:
        """[N,3] (m): the graph nodes' displacement with the tool at ``pose`` [7]."""
        return self.stiffness.to_nodes(self.free_displacement(pose), self.nodes)

    def free_displacement(self, pose: np.ndarray) -> np.ndarray:
        """[3N_free] (m): the free vertices' displacement with the tool at ``pose`` [7] (module docstring)."""
        pose = np.asarray(pose, dtype=np.float64)
        free_u = np.zeros(3 * self.stiffness.n_free)
        active: dict[int, np.ndarray] = {}       # face row -> barycentric weights [3] of its constrained point
        every = np.arange(self.rest.shape[0])
        for _ in range(MAX_ROUNDS):
            x = self.rest + self.stiffness.to_nodes(free_u, every)
            new = self._entering(x, pose, active)
            if not new and active:
                break
            active.update(new)
            if not active:
                return free_u
            free_u = self._solve(x, pose, active)
        return free_u

    def _entering(self, x: np.ndarray, pose: np.ndarray, active: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """{face row: barycentric weights of its deepest sample} for faces at positions ``x`` [N_mesh,3] that reach
        into the tool and are not ``active``. Only faces with a vertex nearer the tool than their longest edge can
        (the SDF is 1-Lipschitz), so only those are sampled."""
        near = np.full(x.shape[0], np.inf)
        near[self.surface] = self.tool.sdf(x[self.surface], pose) - self.gap
        tri = x[self.faces]                                                          # [F,3,3]
        longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
        cand = np.flatnonzero(near[self.faces].min(axis=1) < longest)
        if cand.size == 0:
            return {}
        points = np.einsum("sk,fkd->fsd", self.samples, tri[cand])
        sdf = self.tool.sdf(points.reshape(-1, 3), pose).reshape(cand.size, -1) - self.gap
        deepest = np.argmin(sdf, axis=1)
        inside = sdf[np.arange(cand.size), deepest] < 0
        return {int(f): self.samples[j] for f, j in zip(cand[inside], deepest[inside]) if int(f) not in active}

    def _solve(self, x: np.ndarray, pose: np.ndarray, active: dict[int, np.ndarray]) -> np.ndarray:
        """[3N_free]: the minimiser under the ``active`` faces' inequality constraints: each face's point, from its
        place at ``x``, on or outside the tool's surface along the normal there."""
        rows = np.fromiter(active, dtype=np.int64)
        bary = np.stack([active[int(f)] for f in rows])                              # [k,3]
        verts = self.faces[rows]                                                     # [k,3]
        fi = self.stiffness.free_index[verts]
        weight = np.where(fi >= 0, bary, 0.0)
        here = np.einsum("kj,kjd->kd", bary, x[verts])
        depth, normal = self.tool.sdf_grad(here, pose)
        depth = depth - self.gap
        moved = np.einsum("kd,kd->k", normal, here - np.einsum("kj,kjd->kd", bary, self.rest[verts]))
        target = moved - depth                                                       # n . (b u) after the step
        unique = np.unique(verts[fi >= 0])
        cols = dict(zip(unique.tolist(), self.stiffness.columns(unique.tolist())))
        # K^-1 A^T [3N_free, k]: column c = sum_j w_cj K^-1 E_{v_cj} n_c
        kat = np.zeros((3 * self.stiffness.n_free, rows.size))
        for c in range(rows.size):
            for j in range(3):
                if weight[c, j] > 0:
                    kat[:, c] += weight[c, j] * (normal[c] @ cols[int(verts[c, j])])
        by_vertex = kat.reshape(self.stiffness.n_free, 3, rows.size)
        s = sum(weight[:, j, None] * np.einsum("kd,kdm->km", normal, by_vertex[np.maximum(fi[:, j], 0)])
                for j in range(3))                                                   # A K^-1 A^T [k,k]
        return kat @ self._dual(s, target)

    @staticmethod
    def _dual(s: np.ndarray, target: np.ndarray) -> np.ndarray:
        """lambda [k] >= 0 maximising lambda . target - 1/2 lambda^T s lambda: the multipliers of the inequality
        constraints A u >= target (a face outside the tool gets 0, a face inside pushes). With s = L L^T this is
        the non-negative least squares problem min ||L^T lambda - L^-1 target||."""
        ridge = _RIDGE * max(float(np.trace(s)) / target.size, 1e-300)
        chol = np.linalg.cholesky(s + ridge * np.eye(target.size))
        lam, _ = nnls(chol.T, np.linalg.solve(chol, target), maxiter=50 * target.size)
        return lam

    def rollout(self, poses: np.ndarray) -> np.ndarray:
        """[T,N,3] (m): the prior along a pose sequence [T,7]."""
        return np.stack([self.displacement(p) for p in np.asarray(poses, dtype=np.float64)])
