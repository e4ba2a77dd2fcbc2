"""Interior vertices of a surface-only model: the elastic extension of the surface's displacement.

A surface-only network predicts the surface nodes; the tet mesh's interior vertices follow from them. Two ways:

- ``interpolated``: each interior vertex takes the inverse-distance-weighted displacement of its 4 nearest surface
  nodes (:func:`colgnn_core.learn.graph.lift_to_mesh`). Free, but not physics: given the *exact* surface of the
  ground truth, the interior is off by 0.18 in relative displacement error on the full-resolution knife_torus
  held-out set, which caps the whole mesh's accuracy before the network makes any error.
- ``elastic`` (the default): the interior displacement that the object's linear elasticity at the settled rest
  gives for the surface's displacement, ``u_I = -H_II^-1 H_IS u_S`` (H the elastic Hessian at the rest shape,
  pinned vertices held fixed). That is the quasi-static interior of a linear-elastic body, which the ground truth
  (Neo-Hookean) approaches for small strains: 0.02-0.03 on the same set (0.11 on the fast plunge to the workspace
  floor). One sparse Cholesky factorisation per scene and rest shape (a few seconds at full resolution, cached),
  then a back-substitution per call (3.6 ms for knife_torus's 4,712 free interior vertices, 1 thread).

The ROS node publishes the surface only and uses ``interpolated`` (nothing it sends depends on the interior);
rollouts, evaluation and the Python API default to ``elastic``.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import GraphTemplate, lift_to_mesh
from colgnn_core.sim.elasticity import StableNeoHookean
from colgnn_core.sim.linear_solve import cholesky_solver

__all__ = ["INTERIOR_KINDS", "ElasticInterior", "check_interior_kind", "interior_lift"]

INTERIOR_KINDS = ("elastic", "interpolated")
_CACHE: OrderedDict[str, ElasticInterior] = OrderedDict()
_CACHE_SIZE = 4


class ElasticInterior:
    """Mesh vertices [N_mesh,3] from graph nodes [N,3] by the linear-elastic extension (module docstring).

    scene: the Scene (its tet mesh, material and pinned vertices); template: a surface-only graph template;
    rest_mesh: [N_mesh,3] the settled rest (m) that displacements refer to.
    """

    def __init__(self, scene, template: GraphTemplate, rest_mesh: np.ndarray):
        if template.interior_ids is None:
            raise InputError("the elastic interior needs a surface-only model (this graph has every mesh vertex)")
        self.template = template
        self.rest = np.asarray(rest_mesh, dtype=np.float64).copy()
        n = self.rest.shape[0]
        known = np.zeros(n, dtype=bool)
        known[template.object_nodes] = True
        known[np.asarray(scene.pinned, dtype=np.int64)] = True
        self.free = np.flatnonzero(~known)        # interior vertices that are solved for
        self.known = np.flatnonzero(known)        # graph nodes and pinned vertices (displacement given)
        h = StableNeoHookean(scene.object, scene.material).hessian(self.rest).tocsr()
        fi, ki = _dofs(self.free), _dofs(self.known)
        rows = h[fi]
        self._h_fk = rows[:, ki].tocsr()
        self._solve = cholesky_solver(rows[:, fi].tocsr())

    def __call__(self, x_graph: np.ndarray) -> np.ndarray:
        """Every mesh vertex [N_mesh,3] (m) for graph-node positions ``x_graph`` [N,3]."""
        x_graph = np.asarray(x_graph, dtype=np.float64)
        out = self.rest.copy()
        out[self.template.object_nodes] = x_graph
        u_known = (out[self.known] - self.rest[self.known]).reshape(-1)
        out[self.free] += self._solve(-(self._h_fk @ u_known)).reshape(-1, 3)
        return out


def _dofs(ids: np.ndarray) -> np.ndarray:
    return (3 * ids[:, None] + np.arange(3)).reshape(-1)


def check_interior_kind(kind: str) -> str:
    """``kind`` if it is one of INTERIOR_KINDS, else InputError."""
    if kind not in INTERIOR_KINDS:
        raise InputError(f"interior must be one of {', '.join(INTERIOR_KINDS)}, got {kind!r}")
    return kind


def interior_lift(kind: str, scene, template: GraphTemplate, rest_mesh: np.ndarray
                  ) -> Callable[[np.ndarray], np.ndarray]:
    """The lift graph nodes [N,3] -> mesh vertices [N_mesh,3] of ``kind`` (INTERIOR_KINDS); a model with every mesh
    vertex in its graph needs none (a reorder, whatever ``kind``). Elastic lifts are cached per scene and rest."""
    check_interior_kind(kind)
    rest = np.asarray(rest_mesh, dtype=np.float64)
    if kind == "interpolated" or template.interior_ids is None:
        return lambda x_graph: lift_to_mesh(template, x_graph, rest)
    key = hashlib.sha256(b"".join([scene.name.encode(), scene.resolution.encode(), rest.tobytes(),
                                   np.asarray(template.object_nodes).tobytes()])).hexdigest()
    if key in _CACHE:
        _CACHE.move_to_end(key)
    else:
        _CACHE[key] = ElasticInterior(scene, template, rest)
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return _CACHE[key]
