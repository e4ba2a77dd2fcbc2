"""Cases of the correction tests: real (untrained) networks with controlled output, and the ipctk oracle.

The guarantee must hold for any network output, so the cases use real Simulators whose output is either nothing
(decoder weights zero: the object only keeps its velocity, the tool drives into it) or random accelerations of
realistic size. The oracle is ipctk on the object *surface* against the tool.
"""

from __future__ import annotations

import torch

from colgnn_core.collision.exact import tool_intersects, tool_step_free
from colgnn_core.learn.checkpoint import CheckpointMeta, LoadedCheckpoint
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import ModelConfig, Simulator


# -- the oracle (ipctk) ------------------------------------------------------------------------------------------------
def oracle_intersects(object_V, object_F, tool_V, tool_F) -> bool:
    """ipctk: does the object surface intersect the tool?"""
    return tool_intersects(object_V, object_F, tool_V, tool_F)


def oracle_step_free(object_V0, object_V1, object_F, tool_V0, tool_V1, tool_F, *, contact_only: bool = False) -> bool:
    """ipctk Tight-Inclusion CCD: is the linear step of object surface and tool contact-free? (see
    :func:`colgnn_core.collision.exact.tool_step_free`: stricter than "no contact" unless ``contact_only``)."""
    return tool_step_free(object_V0, object_V1, object_F, tool_V0, tool_V1, tool_F, contact_only=contact_only)


# -- real networks with controlled output -----------------------------------------------------------------------------
def make_model(scene, kind: str, *, scale: float = 2e-4, seed: int = 0) -> LoadedCheckpoint:
    """A real Simulator (latent 16, 2 steps): 'static' (zero decoder: no acceleration) or 'noisy' (random
    weights, output std ``scale`` m: random accelerations of about the size of real ones)."""
    cfg = ModelConfig.from_scene(scene, latent=16, message_passing_steps=2, mlp_layers=1)
    tpl = template_from_scene(scene, surface_only=cfg.surface_only, world_radius=cfg.world_radius)
    torch.manual_seed(seed)
    sim = Simulator(tpl, cfg)
    with torch.no_grad():
        if kind == "static":
            for p in sim.core.decoder.parameters():
                p.zero_()
        elif kind == "noisy":
            sim.output_normalizer.accumulate(torch.randn(4096, 3, dtype=torch.float64) * scale)
        else:
            raise ValueError(kind)
    sim.eval()
    return LoadedCheckpoint(sim, CheckpointMeta.for_scene(scene, "full"), cfg, None, None, None, {})
