"""A physics prior solved on a coarser mesh of the same object, carried onto the model's nodes by that mesh's tets.

Why: the contact prior (``sim.contact_prior``) solves one dense problem in the faces that the tool reaches. A roller
dragged along the full banana (3,578 surface vertices) reaches hundreds of faces at once: 280 ms a step (median, one
thread) on a flank drag, up to 1.8 s when contact moves onto vertices whose responses are not yet cached. On the
banana's ``ci`` mesh (312 vertices) the same prior costs 0.4-1.4 ms a step (p95 under 8 ms), and the linear
elasticity it solves is smooth over the object, so a coarse mesh carries its long-range part (the body's bend and
shift) nearly as well. The local dent under the tool is coarser; the network on top learns that remainder.
Measured on four test sequences of the banana's full family (prior alone, no network, relative displacement error):
full mesh 0.18 / 0.39 / 0.69 / 0.10, ``ci`` mesh 0.25 / 0.47 / 0.67 / 0.27 (docs/FIDELITY.md, session 37).

* **Embedding.** Each point of the fine mesh lies in (or, on a convex surface that the coarse mesh inscribes, just
  outside) a coarse tet; its barycentric coordinates there carry any coarse vertex field to it, exactly for a field
  that is affine over the tet.
* **One rest.** The coarse mesh starts from the fine mesh's settled rest: the fine mesh's settle displacement is
  carried to the coarse vertices by the same embedding the other way round.

Units: m throughout.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from colgnn_core.errors import InputError

__all__ = ["CANDIDATE_TETS", "CoarsePrior", "TetEmbedding"]

CANDIDATE_TETS = 24  # nearest tets (by centroid) searched for each point's best-holding one


@dataclass(frozen=True)
class TetEmbedding:
    """Points held by tets of a mesh: ``weights`` [P,4] the barycentric coordinates of each point in its holding tet
    (all >= 0 inside; slightly negative for a point just outside the mesh), ``corners`` [P,4] that tet's vertex ids,
    and ``matrix`` [P,N] (sparse) the same weights as one interpolation operator."""

    weights: np.ndarray
    corners: np.ndarray
    matrix: sparse.csr_matrix

    @classmethod
    def of(cls, vertices: np.ndarray, tets: np.ndarray, points: np.ndarray) -> "TetEmbedding":
        """Embed ``points`` [P,3] in the tet mesh (``vertices`` [N,3], ``tets`` [K,4]): each point goes to the tet,
        among its CANDIDATE_TETS nearest by centroid, whose smallest barycentric coordinate is largest (the one
        that holds it, or the least outside)."""
        vertices, tets = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise InputError(f"points to embed must be a finite [P,3] array, got {points.shape}")
        corner = vertices[tets]                                                       # [K,4,3]
        edges = np.stack([corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0],
                          corner[:, 3] - corner[:, 0]], axis=2)                        # [K,3,3] columns
        inverse = np.linalg.inv(edges)
        k = min(CANDIDATE_TETS, len(tets))
        _, cand = cKDTree(corner.mean(axis=1)).query(points, k=k)
        cand = cand.reshape(len(points), k)
        lam = np.einsum("pkij,pkj->pki", inverse[cand], points[:, None] - corner[cand, 0])  # [P,k,3]
        bary = np.concatenate([1.0 - lam.sum(axis=2, keepdims=True), lam], axis=2)         # [P,k,4]
        best = bary.min(axis=2).argmax(axis=1)
        rows = np.arange(len(points))
        held = cand[rows, best]
        weights, corners = bary[rows, best], tets[held]
        # one sparse product per step: 0.09 ms for the full banana's nodes, where gathering the corners took 0.5 ms
        matrix = sparse.csr_matrix((weights.reshape(-1), (np.repeat(rows, 4), corners.reshape(-1))),
                                   shape=(len(points), len(vertices)))
        return cls(weights=weights, corners=corners, matrix=matrix)

    def apply(self, field: np.ndarray) -> np.ndarray:
        """[P,...]: the vertex field ``field`` [N,...] at the embedded points (barycentric interpolation)."""
        field = np.asarray(field)
        flat = field.reshape(field.shape[0], -1)
        return np.asarray(self.matrix @ flat).reshape((self.matrix.shape[0],) + field.shape[1:])


class CoarsePrior:
    """A physics prior solved on ``coarse`` (the same object at a coarser resolution) and given at the fine mesh's
    graph nodes: the interface of ``sim.tip_prior.TipPrior`` (``step``, ``rollout``; displacements [N,3] m).

    make: builds the prior on the coarse mesh, ``make(coarse_scene, coarse_rest [N_c,3], coarse_nodes [N_c])``;
    scene, rest_mesh [N_mesh,3], nodes [N]: the fine scene, its settled rest and the graph's mesh ids."""

    def __init__(self, make: Callable, coarse, scene, rest_mesh: np.ndarray, nodes: np.ndarray):
        if coarse.name != scene.name:
            raise InputError(f"a coarse prior needs the same object: {coarse.name!r} is not {scene.name!r}")
        fine_v, coarse_v = scene.object.vertices, coarse.object.vertices
        rest_mesh = np.asarray(rest_mesh, dtype=np.float64)
        if rest_mesh.shape != fine_v.shape:
            raise InputError(f"the prior's rest must be [{len(fine_v)},3], got {rest_mesh.shape}")
        settle = TetEmbedding.of(fine_v, scene.object.tets, coarse_v).apply(rest_mesh - fine_v)
        self.coarse_rest = coarse_v + settle                                          # [N_c,3]
        self.inner = make(coarse, self.coarse_rest, np.arange(len(coarse_v)))
        self.to_nodes = TetEmbedding.of(coarse_v, coarse.object.tets, fine_v[np.asarray(nodes, dtype=np.int64)])

    def step(self, previous, pose_prev: np.ndarray, pose: np.ndarray) -> tuple[object, np.ndarray]:
        """(the coarse prior's state, the nodes' displacement [N,3]) at ``pose`` [7]."""
        state, u = self.inner.step(previous, pose_prev, pose)
        return state, self.to_nodes.apply(u)

    def rollout(self, poses: np.ndarray) -> np.ndarray:
        """[T,N,3] (m): the prior along a pose sequence [T,7]."""
        coarse = self.inner.rollout(poses)                                            # [T,N_c,3]
        return self.to_nodes.apply(coarse.transpose(1, 0, 2)).transpose(1, 0, 2)
