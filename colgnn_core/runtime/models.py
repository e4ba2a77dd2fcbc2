"""The shipped models and checkpoint loading for the runtime.

A model is named by a checkpoint path, a :class:`~colgnn_core.learn.checkpoint.LoadedCheckpoint`, or a scene name
(its shipped model, ``assets/models/<scene>.pt``). ``limits='data'`` caps the network's output by the extremes of
the training data the checkpoint records (:func:`output_limits`).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.checkpoint import LoadedCheckpoint, read_checkpoint
from colgnn_core.learn.registry import load_checkpoint
from colgnn_core.scenes import is_custom, scene_file, scene_names

MODEL_DIR = Path(__file__).resolve().parents[1] / "assets" / "models"
DATA_STEP_FACTOR = 2.0       # limits='data': per-step cap = 2 x the largest per-frame displacement in training
DATA_DEVIATION_FACTOR = 1.5  # ... and distance-from-rest cap = 1.5 x the largest one in training


def shipped_checkpoint(scene_name: str) -> Path:
    """Path of a scene's default model (InputError if there is none): ``assets/models/<scene>.pt`` for a built-in
    scene, ``<scene>.pt`` beside a user's scene TOML (written by ``colgnn fit``)."""
    if scene_name not in scene_names():
        raise InputError(f"unknown scene {scene_name!r}; valid scenes: {', '.join(scene_names())}")
    if is_custom(scene_name):
        path = scene_file(scene_name).with_suffix(".pt")
        if not path.is_file():
            raise InputError(f"scene {scene_name!r} has no model yet ({path}); run `colgnn fit {scene_name}` or pass "
                             "a checkpoint")
        return path
    path = MODEL_DIR / f"{scene_name}.pt"
    if not path.is_file():
        raise InputError(f"no shipped model for scene {scene_name!r} ({path}); pass a checkpoint")
    return path


def checkpoint_resolution(path: str | os.PathLike) -> str:
    """The scene resolution ('ci' or 'full') the checkpoint at ``path`` was trained at (InputError, naming the file,
    when it is missing or unreadable)."""
    return str(read_checkpoint(path)["meta"].get("resolution", "full"))


def load_model(checkpoint_or_scene, scene=None) -> LoadedCheckpoint:
    """A loaded checkpoint from a LoadedCheckpoint, a checkpoint path, or a scene name (its shipped model)."""
    if isinstance(checkpoint_or_scene, LoadedCheckpoint):
        return checkpoint_or_scene
    if isinstance(checkpoint_or_scene, (str, os.PathLike)):
        text = str(checkpoint_or_scene)
        if text in scene_names() and not Path(text).exists():
            return load_checkpoint(shipped_checkpoint(text), scene)
        return load_checkpoint(text, scene)
    raise InputError(f"expected a checkpoint path or a scene name, got {type(checkpoint_or_scene).__name__}")


def model_and_scene(checkpoint_or_scene, scene=None) -> tuple[LoadedCheckpoint, object]:
    """(loaded model, its Scene): ``scene`` if given, else the one the checkpoint names, at its resolution."""
    loaded = load_model(checkpoint_or_scene, scene)
    return loaded, (scene if scene is not None else loaded.meta.load_scene())


def output_limits(loaded: LoadedCheckpoint, limits: str, max_displacement: float | None = None,
                  max_deviation: float | None = None) -> tuple[float | None, float | None]:
    """(max displacement per step, max distance from rest) caps in m for the network's output.

    ``limits``: 'none' (only the explicit values) or 'data': ``DATA_STEP_FACTOR`` x the largest per-frame node
    displacement and ``DATA_DEVIATION_FACTOR`` x the largest node distance from rest in the checkpoint's training
    data, where no explicit value is given.
    """
    if limits not in ("none", "data"):
        raise InputError(f"limits must be 'none' or 'data', got {limits!r}")
    if limits == "data":
        stats = (loaded.extra or {}).get("data_stats")
        if not stats:
            raise InputError("this checkpoint records no training-data statistics; pass explicit limits")
        if max_displacement is None:
            max_displacement = DATA_STEP_FACTOR * float(stats["max"])
        if max_deviation is None:
            max_deviation = DATA_DEVIATION_FACTOR * float(stats["max_deviation"])
    return max_displacement, max_deviation


def settled_rest(loaded: LoadedCheckpoint, scene) -> np.ndarray:
    """[N_mesh,3] the rest shape the model's ground truth starts from: the object settled under gravity (frame 0 of
    its training data, recorded in the checkpoint). Checkpoints that predate the record give the scene's mesh."""
    rest = (loaded.extra or {}).get("settled_rest")
    mesh = np.asarray(scene.object.vertices, dtype=np.float64)
    if rest is None or tuple(rest.shape) != mesh.shape:
        return mesh.copy()
    return np.asarray(rest, dtype=np.float64).copy()


class RestModel:
    """The trivial model "nothing moves": every step predicts the rest graph-node positions [N,3].

    Behind the Predictor it gives the ``rest + correction`` baseline: the rest shape, with only the collision-aware
    correction acting (the tool pushes a dent, the network adds nothing)."""

    def __init__(self, template, rest_graph: np.ndarray):
        self.template = template
        self.rest = torch.from_numpy(np.asarray(rest_graph, dtype=np.float64))

    def predict(self, frame) -> torch.Tensor:
        return self.rest.clone()


class PriorModel(RestModel):
    """A model's physics prior alone (``tip_prior`` or ``contact_prior``): every step predicts the rest graph-node
    positions plus the frame's prior displacement [N,3] (the stepper computes it, as for the model).

    Behind the Predictor it gives the ``prior + correction`` baseline: what the network adds over its prior."""

    def __init__(self, template, rest_graph: np.ndarray, config):
        super().__init__(template, rest_graph)
        self.config = config  # its prior_kind: the stepper gives every frame the prior

    def predict(self, frame) -> torch.Tensor:
        return self.rest + frame.prior


def prior_baseline(loaded: LoadedCheckpoint, scene) -> LoadedCheckpoint:
    """``loaded`` (a model with a physics prior) with its network replaced by :class:`PriorModel`, like
    :func:`rest_baseline`."""
    template = loaded.simulator.template
    rest = settled_rest(loaded, scene)[template.object_nodes]
    return replace(loaded, simulator=PriorModel(template, rest, loaded.simulator.config))


def rest_baseline(loaded: LoadedCheckpoint, scene) -> LoadedCheckpoint:
    """``loaded`` with its network replaced by :class:`RestModel` at the model's settled rest (same graph nodes,
    step limits and training-data records, so the baseline runs exactly as the model would)."""
    template = loaded.simulator.template
    return replace(loaded, simulator=RestModel(template, settled_rest(loaded, scene)[template.object_nodes]))
