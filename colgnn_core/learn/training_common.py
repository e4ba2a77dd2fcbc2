"""What both trainers share (the GNN in :mod:`.train`, the subspace baseline in :mod:`.subspace`).

* :class:`GeometricDecay`: the exponential learning-rate schedule (a LambdaLR factor whose state is saved);
* :class:`TrainResult`: what a training run returns;
* :func:`data_stats`: displacement statistics of the training data, saved in every checkpoint (``limits='data'``);
* :func:`read_resumable` / :class:`ResumeState`: the checks of ``--resume`` and the restored optimizer state,
  written once for both trainers.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.checkpoint import CheckpointMeta, check_compatible, read_checkpoint
from colgnn_core.learn.data import FrameDataset
from colgnn_core.learn.symmetry import NodeSymmetry


class GeometricDecay:
    """LR factor ``ratio ** (min(step, steps) / steps)``: exponential decay to ``ratio`` at ``steps``, then flat.

    A callable object (not a function) so LambdaLR saves its state in the checkpoint.
    """

    def __init__(self, ratio: float, steps: int):
        self.ratio = float(ratio)
        self.steps = int(max(steps, 1))

    def __call__(self, step: int) -> float:
        return self.ratio ** (min(step, self.steps) / self.steps)


@dataclass
class TrainResult:
    checkpoint: str
    step: int                 # steps done in total (warm-up included)
    steps: int                # the run's planned total
    wall_s: float             # this invocation
    stopped: str              # 'done' | 'time budget' | 'stop_after'
    last: dict[str, float]    # last logged loss terms (rank average)
    history: list[dict]       # logged rows (step, loss terms, lr)
    simulator: torch.nn.Module | None = None  # the trained model (this rank's copy)


DOMAIN_POSES = 4096  # training tool positions a checkpoint keeps for the Predictor's domain check (subsampled)


def domain_extra(dataset: FrameDataset, seed: int = 0, symmetry: NodeSymmetry | None = None) -> dict:
    """What the runtime needs to know of the training data, for a checkpoint's ``extra``.

    ``settled_rest`` [N_mesh,3] float64: frame 0 of the first training sequence, the rest shape the ground truth
    settles to under gravity before any tool moves (the Predictor starts from it and relaxes toward it);
    ``domain_tool_positions`` [K,3] float32: the tool positions of the training frames (at most DOMAIN_POSES, a
    seeded subsample); ``domain_max_deviation`` (m): the largest distance of a mesh vertex from the settled rest
    in the training data. With ``symmetry`` (training turned the samples) the tool positions include every turn.
    """
    rest = np.asarray(dataset.sequences[0].object_positions[0], dtype=np.float64)
    poses = np.concatenate([s.tool_poses[:, :3] for s in dataset.sequences])
    if symmetry is not None:
        poses = np.concatenate([poses] + [symmetry.turn_points(poses, a) for a in symmetry.angles])
    if len(poses) > DOMAIN_POSES:
        poses = poses[np.random.default_rng(seed).choice(len(poses), DOMAIN_POSES, replace=False)]
    deviation = max(float(np.linalg.norm(s.object_positions - rest, axis=2).max()) for s in dataset.sequences)
    return {"settled_rest": torch.from_numpy(rest.copy()),
            "domain_tool_positions": torch.from_numpy(poses.astype(np.float32)),
            "domain_max_deviation": deviation}


def data_stats(dataset: FrameDataset, template) -> dict[str, float]:
    """Displacement statistics (m) of the free graph nodes (see ``FrameDataset.displacement_stats``)."""
    return dataset.displacement_stats(template.object_nodes, ~template.pinned.numpy())


@dataclass
class ResumeState:
    """A checked, resumable checkpoint: its raw payload, header and ``extra`` (the trainer's saved settings)."""

    payload: dict
    meta: CheckpointMeta
    extra: dict

    @property
    def step(self) -> int:
        """Steps already done (the run continues from here)."""
        return int(self.meta.step)

    def restore_optimizer(self, optimizer: torch.optim.Optimizer, scheduler) -> None:
        """Load the saved optimizer and learning-rate scheduler states into freshly built ones."""
        optimizer.load_state_dict(self.payload["optimizer"])
        scheduler.load_state_dict(self.payload["scheduler"])


def read_resumable(path: str | os.PathLike, scene, variant: str, required: tuple[str, ...] = ()) -> ResumeState:
    """The checkpoint ``path`` of a run to resume, checked: same scene (name, mesh, dt) and ``variant``, with its
    optimizer state and the ``required`` keys of ``extra`` (InputError naming the file otherwise)."""
    path = Path(path)
    payload = read_checkpoint(path)
    meta = CheckpointMeta(**payload["meta"])
    check_compatible(meta, scene.name, scene.object.fingerprint(), float(scene.dt), source=str(path))
    if meta.variant != variant:
        raise InputError(f"{path} was trained as variant {meta.variant!r}, not {variant!r}")
    extra = payload.get("extra") or {}
    if payload.get("optimizer") is None or any(k not in extra for k in required):
        raise InputError(f"{path} has no training state to resume (a shipped/stripped model?)")
    return ResumeState(payload, meta, extra)
