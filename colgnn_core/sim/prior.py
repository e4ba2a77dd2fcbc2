"""The physics priors a quasi-static model can add its output to, by name (``ModelConfig.prior``).

Each prior is built once for a scene, its settled rest and the graph nodes, and answers
``step(state, pose_prev, pose) -> (state, displacement [N,3] m)`` along a pose sequence, and ``rollout(poses)``:

* ``tip`` (``sim.tip_prior``): a sharp cone whose tip carries the surface point it entered (state: that point);
* ``tip_side`` (``sim.tip_prior.TipSidePrior``): the same, with the cone's side holding every face it reaches
  outside it (a pocket as wide as the cone);
* ``contact`` (``sim.contact_prior``): a frictionless smooth tool that holds every face it reaches on its surface
  (no state).

Any of them can be solved on the scene's mesh at a coarser resolution and carried onto the graph's nodes
(``mesh``, ``sim.coarse_prior``): the full banana's contact prior costs 280 ms a step on a long contact, its ``ci``
one about 1 ms.
"""

from __future__ import annotations

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.scenes import RESOLUTIONS, load_scene
from colgnn_core.sim.coarse_prior import CoarsePrior
from colgnn_core.sim.contact_prior import ContactPrior
from colgnn_core.sim.tip_prior import TipPrior, TipSidePrior

__all__ = ["PRIORS", "physics_prior"]

PRIORS = {"tip": TipPrior, "tip_side": TipSidePrior, "contact": ContactPrior}


def physics_prior(kind: str, scene, rest_mesh: np.ndarray, nodes: np.ndarray, mesh: str = ""
                  ) -> TipPrior | TipSidePrior | ContactPrior | CoarsePrior:
    """The ``kind`` prior (a key of PRIORS) for ``scene`` at the settled rest ``rest_mesh`` [N_mesh,3] (m), giving the
    displacement of mesh vertices ``nodes`` [N]. Factorises the stiffness (seconds at full resolution).

    mesh: "" (or the scene's own resolution) solves it on the scene's mesh; another resolution of the same scene
    ("ci") solves it there and carries it onto ``nodes`` (sim.coarse_prior)."""
    if kind not in PRIORS:
        raise InputError(f"unknown physics prior {kind!r}: choose one of {sorted(PRIORS)}")
    if not mesh or mesh == scene.resolution:
        return PRIORS[kind](scene, rest_mesh, nodes)
    if mesh not in RESOLUTIONS:
        raise InputError(f"unknown prior mesh {mesh!r}: choose a resolution, one of {sorted(RESOLUTIONS)}")
    return CoarsePrior(PRIORS[kind], load_scene(scene.name, mesh), scene, rest_mesh, nodes)
