"""The physics priors a quasi-static model can add its output to, by name (``ModelConfig.prior``).

Each prior is built once for a scene, its settled rest and the graph nodes, and answers
``step(state, pose_prev, pose) -> (state, displacement [N,3] m)`` along a pose sequence, and ``rollout(poses)``:

* ``tip`` (``sim.tip_prior``): a sharp cone whose tip carries the surface point it entered (state: that point);
* ``tip_side`` (``sim.tip_prior.TipSidePrior``): the same, with the cone's side holding every face it reaches
  outside it (a pocket as wide as the cone);
* ``contact`` (``sim.contact_prior``): a frictionless smooth tool that holds every face it reaches on its surface
  (no state).
"""

from __future__ import annotations

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.sim.contact_prior import ContactPrior
from colgnn_core.sim.tip_prior import TipPrior, TipSidePrior

__all__ = ["PRIORS", "physics_prior"]

PRIORS = {"tip": TipPrior, "tip_side": TipSidePrior, "contact": ContactPrior}


def physics_prior(kind: str, scene, rest_mesh: np.ndarray, nodes: np.ndarray) -> TipPrior | TipSidePrior | ContactPrior:
    """The ``kind`` prior (a key of PRIORS) for ``scene`` at the settled rest ``rest_mesh`` [N_mesh,3] (m), giving the
    displacement of mesh vertices ``nodes`` [N]. Factorises the stiffness (seconds at full resolution)."""
    if kind not in PRIORS:
        raise InputError(f"unknown physics prior {kind!r}: choose one of {sorted(PRIORS)}")
    return PRIORS[kind](scene, rest_mesh, nodes)
