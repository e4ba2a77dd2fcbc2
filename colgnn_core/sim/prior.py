"""The physics priors a quasi-static model can add its output to, by name (``ModelConfig.prior``).

Each prior is built once for a scene, its settled rest and the graph nodes, and answers
``step(state, pose_prev, pose) -> (state, displacement [N,3] m)`` along a pose sequence, and ``rollout(poses)``:

* ``tip`` (``sim.tip_prior``): a sharp cone whose tip carries the surface point it entered (state: that point);
* ``tip_side`` (``sim.tip_prior.TipSidePrior``): the same, with the cone's side holding every face it reaches
  outside it (a pocket as wide as the cone);
* ``contact`` (``sim.contact_prior``): a frictionless smooth tool that holds every face it reaches on its surface
  (no state);
* ``edge`` (``sim.edge_prior``): a blade whose edge carries the surface above it, free to slide along the edge (no
  state).

Any of them can be solved on the scene's mesh at a coarser resolution and carried onto the graph's nodes
(``mesh``, ``sim.coarse_prior``): the full banana's contact prior costs 280 ms a step on a long contact, its ``ci``
one about 1 ms. The contact prior can instead stay on the fine mesh with ``compliance="modal"``
(``sim.compliance.ModalCompliance``, one constraint per surface vertex): 5-9 ms a step in contact on the full
banana, and as accurate as the exact one. ``compliance="modal_response"`` also reads the response from it, at the
graph's nodes only: the full torus's edge prior in about 2 ms instead of a 16 ms back-substitution.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.scenes import RESOLUTIONS, load_scene
from colgnn_core.sim.coarse_prior import CoarsePrior
from colgnn_core.sim.compliance import ModalCompliance, cache_dir
from colgnn_core.sim.contact_prior import ContactPrior
from colgnn_core.sim.edge_prior import EdgePrior
from colgnn_core.sim.rest_stiffness import RestStiffness
from colgnn_core.sim.tip_prior import TipPrior, TipSidePrior

__all__ = ["COMPLIANCES", "MODAL_PRIORS", "OPTIONS", "PRIORS", "physics_prior"]

PRIORS = {"tip": TipPrior, "tip_side": TipSidePrior, "contact": ContactPrior, "edge": EdgePrior}
OPTIONS = {"tip": ("kappa",), "tip_side": ("kappa",), "contact": (), "edge": ()}  # each prior's own settings
MODAL_PRIORS = ("contact", "edge")  # the priors whose rows sit on surface points, so the modal compliance serves
COMPLIANCES = ("", "modal", "modal_response")   # "": exact K^-1 (sim.compliance.ExactCompliance); "modal":
                                                # ModalCompliance (its dual; the response exact); "modal_response":
                                                # its response too, read at the graph nodes and the surface


def physics_prior(kind: str, scene, rest_mesh: np.ndarray, nodes: np.ndarray, mesh: str = "",
                  compliance: str = "", options: dict | None = None
                  ) -> TipPrior | TipSidePrior | ContactPrior | EdgePrior | CoarsePrior:
    """The ``kind`` prior (a key of PRIORS) for ``scene`` at the settled rest ``rest_mesh`` [N_mesh,3] (m), giving the
    displacement of mesh vertices ``nodes`` [N]. Factorises the stiffness (seconds at full resolution).

    mesh: "" (or the scene's own resolution) solves it on the scene's mesh; another resolution of the same scene
    ("ci") solves it there and carries it onto ``nodes`` (sim.coarse_prior).
    compliance: "" exact; "modal" (the contact or edge prior on the scene's own mesh only): K^-1 compressed for the
    dual, one constraint per surface vertex; its set-up (a minute on the full banana) is kept in
    sim.compliance.cache_dir. "modal_response": the same, and the response from the modes and the near field too,
    at ``nodes`` and the surface only (the full torus's edge prior: about 2 ms instead of a 16 ms
    back-substitution; the interior's response reads 0).
    options: the prior's own settings (OPTIONS), e.g. ``{"kappa": 1.0}`` for the tip priors' slide rule.
    """
    if kind not in PRIORS:
        raise InputError(f"unknown physics prior {kind!r}: choose one of {sorted(PRIORS)}")
    options = dict(options or {})
    if set(options) - set(OPTIONS[kind]):
        raise InputError(f"the {kind!r} prior has no setting {sorted(set(options) - set(OPTIONS[kind]))}: it takes "
                         f"{list(OPTIONS[kind]) or 'none'}")
    if compliance not in COMPLIANCES:
        raise InputError(f"unknown prior compliance {compliance!r}: choose one of {COMPLIANCES}")
    if compliance:
        if kind not in MODAL_PRIORS or (mesh and mesh != scene.resolution):
            raise InputError("the modal compliance is for the contact or edge prior on the scene's own mesh (a fine "
                             f"one), not the {kind!r} prior{' on ' + mesh if mesh else ''}")
        stiffness = RestStiffness(scene, rest_mesh)
        read = np.union1d(nodes, np.unique(scene.object.faces)) if compliance == "modal_response" else None
        modal = ModalCompliance.for_surface(stiffness, scene.object.faces, cache=cache_dir(), read=read)
        return PRIORS[kind](scene, rest_mesh, nodes, stiffness=stiffness, compliance=modal, points="vertices")
    make = partial(PRIORS[kind], **options)
    if not mesh or mesh == scene.resolution:
        return make(scene, rest_mesh, nodes)
    if mesh not in RESOLUTIONS:
        raise InputError(f"unknown prior mesh {mesh!r}: choose a resolution, one of {sorted(RESOLUTIONS)}")
    return CoarsePrior(make, load_scene(scene.name, mesh), scene, rest_mesh, nodes)
