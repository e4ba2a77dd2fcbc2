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
* **Shared with the sharp tip.** ``sim.tip_prior.TipSidePrior`` uses the same constraints on a cone's side, with
  the tip's three equality constraints added (:func:`multipliers` eliminates their free multipliers), a second
  point on a stretched face that slides over the cone (``resample``), and the cone's axis as one more sample.
* **No state.** A frictionless tool leaves nothing behind, so the prior is a function of the tool's pose. (A sharp
  cone drags its pocket along; ``sim.tip_prior`` carries that state.)

What it misses: a press on a ridge (the cow's back) where the ground truth's body leans to one side and the prior's
to the other; the truth's tool is the sphere's mesh (its facets tilt the contact force by up to about 9 degrees),
and a prior against that mesh scored worse on the training sequences (0.435 against 0.383).

Cost: one K^-1 E_v per vertex that contact reaches (``sim.rest_stiffness``, cached) and a dense solve of one
equation per face in contact; K^-1 A^T over all free coordinates is never formed (a round costs O(U N_free) for U
constrained vertices). About 1-3 ms a step at ``ci`` on the cow (569 vertices); at full resolution (9,845)
set-up took 17 s and a first contact 1.5 s, so with this exact compliance the prior is meant for ``ci`` meshes.
On a fine mesh ``sim.compliance.ModalCompliance`` with ``points="vertices"`` costs about 6 ms a step in contact (the
full banana; ``sim.prior.physics_prior(..., compliance="modal")``).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import nnls

from colgnn_core.errors import InputError
from colgnn_core.geometry.rays import ray_faces
from colgnn_core.sim.compliance import ExactCompliance, ModalCompliance
from colgnn_core.sim.ipc import DMIN_SCALE
from colgnn_core.sim.rest_stiffness import RestStiffness

__all__ = ["CACHE_BYTES", "MAX_ROUNDS", "RESAMPLE_DEPTH", "SAMPLE_LEVEL", "Constraint", "ContactPrior", "EqualityRows",
           "POINTS", "multipliers", "nonnegative_qp", "point_rows"]

SAMPLE_LEVEL = 4  # barycentric samples per face: a triangular grid of (L+1)(L+2)/2 = 15 points
MAX_ROUNDS = 8    # active-set rounds per pose (the cow: 2-4)
CACHE_BYTES = 1 << 27  # 128 MiB of cached K^-1 E_v columns (72 N_free bytes a vertex)
RESAMPLE_DEPTH = 0.05  # a second point on an active face only when it lies this many gaps deeper inside
POINTS = ("faces", "vertices")  # where the contact constraints sit (ContactPrior's ``points``)
BPP_MAX_ITERATIONS = 50   # block principal pivoting swaps before nnls takes over (the banana: 1-4)
BPP_BACKUP = 3            # full swaps allowed without fewer wrong entries before single swaps
BPP_TOLERANCE = 1e-12     # y = s x - t counts as negative below this times max |t|
_RIDGE = 1e-9     # relative ridge on A K^-1 A^T: constraints of faces that share their vertices are nearly dependent


Constraint = tuple[int, tuple[float, ...]]  # (face row, its point's barycentric weights rounded): one constraint
# Equality rows n_e . sum_j b_ej u_{v_ej} = target_e: (vertices [e,3] mesh ids, barycentric weights [e,3],
# normals [e,3], targets [e] m).
EqualityRows = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def point_rows(verts: np.ndarray, bary: np.ndarray, displacement: np.ndarray) -> EqualityRows:
    """The three equality rows (along x, y, z) that move the material point ``bary`` [3] of the face ``verts`` [3]
    by exactly ``displacement`` [3] (m)."""
    verts, bary = np.asarray(verts, dtype=np.int64), np.asarray(bary, dtype=np.float64)
    return (np.repeat(verts[None], 3, axis=0), np.repeat(bary[None], 3, axis=0), np.eye(3),
            np.asarray(displacement, dtype=np.float64).reshape(3))


def _barycentric_grid(level: int) -> np.ndarray:
    """[S,3] barycentric weights of a triangular grid with ``level`` intervals per edge."""
    return np.array([(i, j, level - i - j) for i in range(level + 1) for j in range(level + 1 - i)],
                    dtype=np.float64) / level


def nonnegative_qp(s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """x [k] >= 0 minimising 1/2 x^T s x - t . x for a symmetric positive definite ``s`` [k,k].

    Block principal pivoting (Kim and Park's rule with Murty's single-exchange backup): guess the set F of positive
    entries, solve s_FF x_F = t_F, and swap every entry that breaks the optimality conditions (x_F < 0, or
    y = s x - t < 0 outside F) until none does. Why not scipy's nnls: its Lawson-Hanson adds one entry an
    iteration; on the full banana's 300-400 contact rows it took 8 ms a solve, where the first guess "every row
    pushes" is right but for a few rows and this needs 2-4 Cholesky solves. Falls back to nnls when it has not
    converged in BPP_MAX_ITERATIONS."""
    k = t.size
    free = np.ones(k, dtype=bool)           # the guess: every contact row pushes
    x, backup, fewest = np.zeros(k), BPP_BACKUP, k + 1
    for _ in range(BPP_MAX_ITERATIONS):
        x[:] = 0.0
        if free.any():
            x[free] = cho_solve(cho_factor(s[np.ix_(free, free)], check_finite=False), t[free], check_finite=False)
        y = s @ x - t
        x_tol = BPP_TOLERANCE * max(float(np.abs(x).max()), 1e-300)
        y_tol = BPP_TOLERANCE * max(float(np.abs(t).max()), 1e-300)
        wrong = (free & (x < -x_tol)) | (~free & (y < -y_tol))
        count = int(wrong.sum())
        if count == 0:
            return np.maximum(x, 0.0)
        if count < fewest:
            fewest, backup = count, BPP_BACKUP
            free ^= wrong
        elif backup > 0:
            backup -= 1
            free ^= wrong
        else:                                # Murty's rule: swap only the last wrong entry (finite)
            free[np.flatnonzero(wrong)[-1]] ^= True
    chol = np.linalg.cholesky(s)
    lam, _ = nnls(chol.T, np.linalg.solve(chol, t), maxiter=50 * k)
    return lam


def multipliers(s: np.ndarray, target: np.ndarray, n_eq: int = 0) -> np.ndarray:
    """lambda [k] maximising lambda . target - 1/2 lambda^T s lambda, with lambda >= 0 beyond its first ``n_eq``
    entries: the multipliers of the constraints A u = target (first n_eq rows) and A u >= target (a face
    outside the tool gets 0, a face inside pushes). The free multipliers are eliminated in closed form (a
    Schur complement); with the rest's s = L L^T this is the non-negative least squares problem
    min ||L^T lambda - L^-1 target||."""
    ridge = _RIDGE * max(float(np.trace(s)) / target.size, 1e-300)
    s = s + ridge * np.eye(target.size)
    if n_eq:
        see, sei, sii = s[:n_eq, :n_eq], s[:n_eq, n_eq:], s[n_eq:, n_eq:]
        te, ti = target[:n_eq], target[n_eq:]
        s = sii - sei.T @ np.linalg.solve(see, sei)
        target = ti - sei.T @ np.linalg.solve(see, te)
    if target.size == 0:  # equality rows alone
        return np.linalg.solve(see, te)
    lam = nonnegative_qp(s, target)
    if not n_eq:
        return lam
    return np.concatenate([np.linalg.solve(see, te - sei @ lam), lam])


class ContactPrior:
    """The prior's displacement of graph nodes for tool poses, for one scene and settled rest (module docstring).

    scene: its object (tet mesh, surface faces), material, glued vertices and tool (any analytic shape);
    rest_mesh: [N_mesh,3] the settled rest (m); nodes: [N] mesh ids of the graph nodes the prior is given for.
    stiffness, compliance: K and how K^-1 is read (default: exact, ``sim.compliance``); points: "faces" (each
    face's deepest sample, module docstring) or "vertices" (each surface vertex in the tool: for a fine mesh, whose
    faces dip into a smooth tool by far less than the gap; the full banana's roller, 3 mm faces under a 20 mm
    radius: 0.06 mm. There it scores the same, 0.226 / 0.430 / 0.715 / 0.167 against 0.223 / 0.433 / 0.730 /
    0.165 on four validation sequences, with 163 rows instead of 375 and one active-set round instead of 1-3:
    5 ms a step in contact against 16-38; docs/FIDELITY.md, session 44).
    """

    def __init__(self, scene, rest_mesh: np.ndarray, nodes: np.ndarray, stiffness: RestStiffness | None = None,
                 compliance: ExactCompliance | ModalCompliance | None = None, points: str = "faces"):
        if points not in POINTS:
            raise InputError(f"unknown contact points {points!r}: choose one of {POINTS}")
        self.points = points
        self.tool = scene.tool
        # The ground truth keeps the surface dmin to dmin + dhat away from the tool (the solver's offset barrier):
        # the prior holds it at the middle of that band. On the cow's training sequences, 0.43 -> 0.38.
        self.gap = (DMIN_SCALE + 0.5) * float(scene.dhat)
        self.stiffness = stiffness if stiffness is not None else RestStiffness(scene, rest_mesh)
        # Keep every vertex that contact reaches while the cache stays under CACHE_BYTES (at ci: all of them).
        self.stiffness.cache_vertices = max(256, CACHE_BYTES // (72 * max(self.stiffness.n_free, 1)))
        self.compliance = compliance if compliance is not None else ExactCompliance(self.stiffness)
        self.rest = self.stiffness.rest
        self.nodes = np.asarray(nodes, dtype=np.int64)
        faces = np.asarray(scene.object.faces, dtype=np.int64)
        movable = (self.stiffness.free_index[faces] >= 0).any(axis=1)
        self.faces = faces[movable]                     # [F,3] surface faces with a free vertex (others cannot move)
        self.surface = np.unique(self.faces)            # their vertices
        # points == "vertices": each surface vertex's constraint is written on one face holding it (a corner weight 1)
        corner_of = {int(v): (f, j) for f, tri in reversed(list(enumerate(self.faces))) for j, v in enumerate(tri)}
        self.vertex_face = np.array([corner_of[int(v)] for v in self.surface], dtype=np.int64).reshape(-1, 2)
        self.surface_free = self.stiffness.free_index[self.surface] >= 0   # [S] not glued
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
        active: dict[Constraint, np.ndarray] = {}   # (face row, point) -> barycentric weights [3] of that point
        every = np.arange(self.rest.shape[0])
        for _ in range(MAX_ROUNDS):
            x = self.rest + self.stiffness.to_nodes(free_u, every)
            new = self.entering(x, pose, active)
            if not new and active:
                break
            active.update(new)
            if not active:
                return free_u
            free_u = self.solve(x, pose, active)
        return free_u

    def entering(self, x: np.ndarray, pose: np.ndarray, active: dict[Constraint, np.ndarray], *,
                 resample: bool = False, ray: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> dict[Constraint, np.ndarray]:
        """{(face row, point): barycentric weights [3]} of the deepest sample of each face at positions ``x``
        [N_mesh,3] that reaches into the tool, beyond ``active``. Only faces with a vertex nearer the tool than their
        longest edge can (the SDF is 1-Lipschitz), so only those are sampled.

        By default a face that is already ``active`` is skipped. ``resample``: an active face gets a second point
        when another one lies deeper than ``RESAMPLE_DEPTH`` x gap (a stretched face sliding over the tool); its
        first point alone would let the tool through it. ``ray`` (origin [3], direction [3]): where the ray
        crosses a face is one more sample (a sharp tool's axis, which pierces a wide face between its samples).
        With ``points == "vertices"`` the constraints are the surface vertices in the tool (no resample, no ray)."""
        if self.points == "vertices":
            return self._entering_vertices(x, pose, active)
        near = np.full(x.shape[0], np.inf)
        near[self.surface] = self.tool.sdf(x[self.surface], pose) - self.gap
        tri = x[self.faces]                                                          # [F,3,3]
        longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
        cand = np.flatnonzero(near[self.faces].min(axis=1) < longest)
        if not resample:
            taken = {f for f, _ in active}
            cand = np.array([f for f in cand if int(f) not in taken], dtype=np.int64)
        if cand.size == 0:
            return {}
        points = np.einsum("sk,fkd->fsd", self.samples, tri[cand])
        sdf = self.tool.sdf(points.reshape(-1, 3), pose).reshape(cand.size, -1) - self.gap
        deepest = np.argmin(sdf, axis=1)
        depth = sdf[np.arange(cand.size), deepest]
        bary = self.samples[deepest]
        if ray is not None:
            depth, bary = self._ray_sample(tri[cand], pose, ray, depth, bary)
        inside = depth < (-RESAMPLE_DEPTH * self.gap if resample else 0.0)
        out = {}
        for f, b in zip(cand[inside], bary[inside]):
            key = (int(f), tuple(np.round(b, 3).tolist()))
            if key not in active:
                out[key] = b
        return out

    def _entering_vertices(self, x: np.ndarray, pose: np.ndarray, active: dict[Constraint, np.ndarray]
                           ) -> dict[Constraint, np.ndarray]:
        """{(face row, corner weights): weights [3]} of the surface vertices at ``x`` [N_mesh,3] nearer the tool than
        the gap, beyond ``active`` (each written on the face that ``vertex_face`` gives it). Glued vertices cannot
        move: they get no constraint (it would be a zero row)."""
        inside = np.flatnonzero((self.tool.sdf(x[self.surface], pose) < self.gap) & self.surface_free)
        out = {}
        for face, corner in self.vertex_face[inside].tolist():
            weights = np.zeros(3)
            weights[corner] = 1.0
            key = (face, tuple(weights.tolist()))
            if key not in active:
                out[key] = weights
        return out

    def _ray_sample(self, tri: np.ndarray, pose: np.ndarray, ray: tuple[np.ndarray, np.ndarray],
                    depth: np.ndarray, bary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth [F], barycentric weights [F,3]) of the faces ``tri`` [F,3,3]: the deeper of the given sample and
        the point where ``ray`` crosses the face."""
        hit, _, b = ray_faces(tri, np.asarray(ray[0], dtype=np.float64), np.asarray(ray[1], dtype=np.float64))
        if not hit.any():
            return depth, bary
        idx = np.flatnonzero(hit)
        on_ray = self.tool.sdf(np.einsum("fk,fkd->fd", b[idx], tri[idx]), pose) - self.gap
        deeper = on_ray < depth[idx]
        depth, bary = depth.copy(), bary.copy()
        depth[idx[deeper]], bary[idx[deeper]] = on_ray[deeper], b[idx[deeper]]
        return depth, bary

    def solve(self, x: np.ndarray, pose: np.ndarray, active: dict[Constraint, np.ndarray],
              equality: EqualityRows | None = None) -> np.ndarray:
        """[3N_free]: the minimiser under the ``active`` points' inequality constraints (each point, from its place
        at ``x``, on or outside the tool's surface along the normal there) and, when given, the ``equality`` rows
        (:data:`EqualityRows`, e.g. :func:`point_rows`: a material point moves by exactly a displacement)."""
        faces = np.fromiter((f for f, _ in active), dtype=np.int64, count=len(active))
        bary = np.stack(list(active.values())) if active else np.zeros((0, 3))      # [k,3]
        verts = self.faces[faces]                                                    # [k,3]
        here = np.einsum("kj,kjd->kd", bary, x[verts])
        if active:
            depth, normal = self.tool.sdf_grad(here, pose)
        else:
            depth, normal = np.zeros(0), np.zeros((0, 3))
        moved = np.einsum("kd,kd->k", normal, here - np.einsum("kj,kjd->kd", bary, self.rest[verts]))
        target = moved - (depth - self.gap)                                          # n . (b u) after the step
        n_eq = 0
        if equality is not None:  # the equality rows first
            e_verts, e_bary, e_normal, e_target = (np.asarray(a) for a in equality)
            verts = np.vstack([e_verts.astype(np.int64).reshape(-1, 3), verts])
            bary = np.vstack([e_bary.reshape(-1, 3), bary])
            normal = np.vstack([e_normal.reshape(-1, 3), normal])
            target = np.concatenate([e_target.reshape(-1), target])
            n_eq = int(e_target.size)
        if target.size == 0:
            return np.zeros(3 * self.stiffness.n_free)
        return self._constrained_response(verts, bary, normal, target, n_eq)

    def _constrained_response(self, verts: np.ndarray, bary: np.ndarray, normal: np.ndarray, target: np.ndarray,
                              n_eq: int) -> np.ndarray:
        """[3N_free]: u = K^-1 A^T lambda for the rows n_c . sum_j b_cj u_{v_cj} (glued vertices dropped), with
        lambda from :func:`multipliers`. K^-1 A^T is never formed: with M [3U, k] the rows' weighted normals on the
        U constrained vertices' coordinates (at most 9 entries a column), A K^-1 A^T = M^T C_UU M and
        u = C_{:,U} (M lambda), both from ``self.compliance`` (``sim.compliance``)."""
        fi = self.stiffness.free_index[verts]
        weight = np.where(fi >= 0, bary, 0.0)
        unique, slot = np.unique(np.where(fi >= 0, verts, -1), return_inverse=True)
        slot = slot.reshape(verts.shape)
        first = int(unique[0] < 0)                 # slot 0 holds the glued vertices' -1 when there are any
        unique = unique[first:]
        if unique.size == 0:
            return np.zeros(3 * self.stiffness.n_free)
        keep = slot >= first                                                          # [k,3]
        row, col = np.nonzero(keep)
        entries = (weight[row, col, None] * normal[row]).reshape(-1)                  # [E*3]
        rows = (3 * (slot[row, col] - first)[:, None] + np.arange(3)).reshape(-1)
        m = sparse.csc_matrix((entries, (rows, np.repeat(row, 3))), shape=(3 * unique.size, len(verts)))
        lam = multipliers(self.compliance.dual(unique, m), target, n_eq)
        return self.compliance.response(unique, np.asarray(m @ lam).reshape(-1))

    def rollout(self, poses: np.ndarray) -> np.ndarray:
        """[T,N,3] (m): the prior along a pose sequence [T,7]."""
        return np.stack([self.displacement(p) for p in np.asarray(poses, dtype=np.float64)])
