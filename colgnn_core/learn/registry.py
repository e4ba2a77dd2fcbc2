"""Which model a checkpoint holds, and loading it: the GNN :class:`~.model.Simulator` (``kind = 'gnn'``) or the
subspace baseline (``kind = 'subspace'``, :mod:`.subspace`). Both share the file format and the scene checks of
:mod:`.checkpoint`; only this module knows both model classes.
"""

from __future__ import annotations

import os

from colgnn_core.learn.checkpoint import (CheckpointMeta, LoadedCheckpoint, check_compatible, read_checkpoint,
                                          simulator_from_payload)
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import ModelConfig
from colgnn_core.learn.subspace import subspace_from_payload


def model_from_payload(payload: dict, scene, source: str = "checkpoint"):
    """The model of a checkpoint payload on ``scene``'s mesh: a Simulator or a SubspaceModel, in eval mode."""
    if payload.get("kind", "gnn") == "subspace":  # the Holden et al. baseline: same file format and checks
        return subspace_from_payload(payload, scene, source=source)
    config = ModelConfig.from_dict(payload["config"])
    template = template_from_scene(scene, surface_only=config.surface_only, world_radius=config.world_radius)
    return simulator_from_payload(payload, template, source=source)


def load_checkpoint(path: str | os.PathLike, scene=None) -> LoadedCheckpoint:
    """Load a checkpoint for ``scene`` (default: the scene and resolution it names), checking it belongs there."""
    payload = read_checkpoint(path)
    meta = CheckpointMeta(**payload["meta"])
    if scene is None:
        scene = meta.load_scene()
    check_compatible(meta, scene.name, scene.object.fingerprint(), float(scene.dt), source=str(path))
    model = model_from_payload(payload, scene, source=str(path))
    return LoadedCheckpoint(model, meta, model.config, payload.get("optimizer"), payload.get("scheduler"),
                            payload.get("rng"), payload.get("extra") or {})
