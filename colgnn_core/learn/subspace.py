"""The ``subspace`` baseline, in the spirit of Holden et al. 2019 ("Subspace Neural Physics").

* Subspace: PCA of the object graph nodes' displacements from rest over the
  training frames, ``x = rest + mean + B^T z`` with ``K`` components.
* Dynamics: an MLP predicts the subspace acceleration from the subspace state
  and the tool, ``z_{t+1} = 2 z_t - z_{t-1} + MLP(z_t, z_t - z_{t-1}, tool)``;
  the tool enters as its vertex centroid at t+1 relative to the object's rest
  centroid, its displacement t -> t+1 and its orientation (two rotation-matrix
  columns) at t+1. Inputs and outputs are normalised with statistics of the
  training set; Gaussian noise on z_t during training, as in the paper.

There is no collision handling of any kind: this is the comparison point the
paper calls "subphysics". It implements ``predict(frame)`` like
:class:`~colgnn_core.learn.model.Simulator`, so rollout and evaluation treat
both alike, and is saved in the same checkpoint format (``kind = 'subspace'``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import nn

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.io import ensure_writable_dir
from colgnn_core.learn.checkpoint import CheckpointMeta, save_checkpoint
from colgnn_core.learn.core_model import make_mlp
from colgnn_core.learn.data import FrameDataset
from colgnn_core.learn.graph import GraphTemplate, template_from_scene
from colgnn_core.learn.normalizer import Normalizer
from colgnn_core.learn.training_common import (GeometricDecay, TrainResult, data_stats, domain_extra,
                                              read_resumable)

TOOL_FEATURES = 12  # centroid (3), displacement (3), rotation columns x and z (6)
RESUME_KEYS = ("steps", "batch", "lr_init", "lr_final", "variance_kept")  # the run's settings in a checkpoint


@dataclass
class SubspaceConfig:
    components: int = 32       # K, PCA components
    hidden: int = 128          # MLP width
    layers: int = 2            # MLP hidden layers
    noise_std: float = 0.05    # training noise on z_t, in units of each component's std
    surface_only: bool = True  # graph nodes as in the GNN (interior vertices interpolated)
    world_radius: float = 0.01  # unused by the model; keeps the template identical to the GNN's

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SubspaceConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"unknown subspace config keys: {', '.join(sorted(unknown))}")
        return cls(**d)


def tool_features(tool_t: torch.Tensor, tool_next: torch.Tensor, pose_next: np.ndarray,
                  origin: torch.Tensor) -> torch.Tensor:
    """[..., 12] tool features from tool vertices [..., M, 3] at t and t+1 and the pose [..., 7] at t+1."""
    c_next = tool_next.mean(dim=-2)
    c_t = tool_t.mean(dim=-2)
    r = torch.from_numpy(quat_to_matrix(np.asarray(pose_next)[..., 3:7])).to(tool_t.dtype)
    return torch.cat([c_next - origin, c_next - c_t, r[..., :, 0], r[..., :, 2]], dim=-1)


class SubspaceModel(nn.Module):
    """PCA subspace + MLP dynamics for one scene's object (graph nodes of ``template``)."""

    checkpoint_kind = "subspace"

    def __init__(self, template: GraphTemplate, config: SubspaceConfig):
        super().__init__()
        self.template = template
        self.config = config
        n, k = template.num_object_nodes, config.components
        self.register_buffer("mean", torch.zeros(n * 3, dtype=torch.float64))   # mean displacement
        self.register_buffer("basis", torch.zeros(k, n * 3, dtype=torch.float64))  # orthonormal rows
        self.register_buffer("origin", template.rest.mean(dim=0).clone())
        self.in_norm = Normalizer(2 * k + TOOL_FEATURES)
        self.out_norm = Normalizer(k)
        self.mlp = make_mlp(2 * k + TOOL_FEATURES, config.hidden, k, config.layers, layer_norm=False)

    def project(self, x: torch.Tensor) -> torch.Tensor:
        """Positions [..., N, 3] -> subspace coordinates [..., K]."""
        d = (x - self.template.rest).reshape(*x.shape[:-2], -1) - self.mean
        return d @ self.basis.T

    def positions(self, z: torch.Tensor) -> torch.Tensor:
        """Subspace coordinates [..., K] -> positions [..., N, 3]."""
        d = z @ self.basis + self.mean
        return self.template.rest + d.reshape(*z.shape[:-1], -1, 3)

    def accel_norm(self, z_t: torch.Tensor, z_prev: torch.Tensor, tool: torch.Tensor) -> torch.Tensor:
        """Normalised subspace acceleration [..., K] from float64 inputs."""
        inp = self.in_norm(torch.cat([z_t, z_t - z_prev, tool], dim=-1))
        return self.mlp(inp.float())

    @torch.no_grad()
    def predict(self, frame) -> torch.Tensor:
        """Object graph-node positions at t+1 [N,3] (same interface as Simulator.predict)."""
        z_t, z_prev = self.project(frame.x_t), self.project(frame.x_prev)
        tool = tool_features(frame.tool_t, frame.tool_next, frame.pose_next, self.origin)
        a = self.out_norm.inverse(self.accel_norm(z_t, z_prev, tool).double())
        x_next = self.positions(2 * z_t - z_prev + a)
        return torch.where(self.template.pinned[:, None], frame.x_t, x_next)

    def forward(self, frame):
        return self.predict(frame)


def subspace_from_payload(payload: dict, scene, source: str = "checkpoint") -> SubspaceModel:
    cfg = SubspaceConfig.from_dict(payload["config"])
    tpl = template_from_scene(scene, surface_only=cfg.surface_only, world_radius=cfg.world_radius)
    model = SubspaceModel(tpl, cfg)
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as exc:
        raise InputError(f"{source}: subspace weights do not match its config/scene: "
                         f"{str(exc).splitlines()[0]}") from exc
    return model.eval()


def _dataset_arrays(model: SubspaceModel, ds: FrameDataset):
    """Per sequence: node positions [T,N,3], tool features [T-1,12] for each transition t -> t+1."""
    nodes = model.template.object_nodes
    xs, feats = [], []
    for seq in ds.sequences:
        x = torch.from_numpy(np.ascontiguousarray(seq.object_positions[:, nodes]))
        tool = torch.from_numpy(seq.tool_positions)
        feats.append(tool_features(tool[:-1], tool[1:], seq.tool_poses[1:], model.origin))
        xs.append(x)
    return xs, feats


def fit_pca(model: SubspaceModel, xs: list[torch.Tensor]) -> float:
    """Set mean and basis from the training frames; returns the fraction of displacement variance kept."""
    d = torch.cat([(x - model.template.rest).reshape(x.shape[0], -1) for x in xs])  # [F, 3N]
    mean = d.mean(dim=0)
    u, s, vt = torch.linalg.svd(d - mean, full_matrices=False)
    k = model.config.components
    if k > vt.shape[0]:
        raise InputError(f"subspace: {k} components requested but the data have only {vt.shape[0]} frames")
    model.mean.copy_(mean)
    model.basis.copy_(vt[:k])
    total = float((s ** 2).sum())
    return float((s[:k] ** 2).sum()) / total if total > 0 else 1.0


def train_subspace(scene, data_dir, out_ckpt, resume: bool = False, steps: int | None = None, seed: int = 0,
                   progress: bool = True, config: SubspaceConfig | None = None, batch: int = 64,
                   lr_init: float = 1e-3, lr_final: float = 1e-5, stop_after: int | None = None):
    """Fit the PCA, train the MLP (Adam, exponential lr decay, mini-batches) and write ``out_ckpt``.

    Deterministic for a seed (batch indices and noise are drawn from generators seeded by (seed, step));
    ``resume`` continues from the checkpoint's step; ``stop_after`` stops (with a checkpoint) after that many
    steps of this invocation.
    """
    out_ckpt = Path(out_ckpt)
    ensure_writable_dir(out_ckpt.parent if str(out_ckpt.parent) else Path("."))
    ds = FrameDataset(scene, data_dir, "train")
    state = None
    if resume:
        state = read_resumable(out_ckpt, scene, "subspace", required=RESUME_KEYS)
        model = subspace_from_payload(state.payload, scene, str(out_ckpt))
        extra = state.extra
        total = int(steps if steps is not None else extra["steps"])
        start = state.step
        batch, lr_init, lr_final = extra["batch"], extra["lr_init"], extra["lr_final"]
        xs, feats = _dataset_arrays(model, ds)
        kept = extra["variance_kept"]
    else:
        cfg = config or SubspaceConfig(surface_only=bool(scene.model.get("surface_only", True)),
                                       world_radius=float(scene.model["world_radius"]))
        tpl = template_from_scene(scene, surface_only=cfg.surface_only, world_radius=cfg.world_radius)
        torch.manual_seed(seed)
        model = SubspaceModel(tpl, cfg)
        xs, feats = _dataset_arrays(model, ds)
        kept = fit_pca(model, xs)
        total, start = int(steps if steps is not None else 5000), 0
    # Subspace trajectories and the training set's transitions (z_prev, z_t, tool, target acceleration).
    with torch.no_grad():
        zs = [model.project(x) for x in xs]
        z_prev = torch.cat([torch.cat([z[:1], z[:-2]]) for z in zs])  # x_{-1} = x_0 at t = 0
        z_t = torch.cat([z[:-1] for z in zs])
        z_next = torch.cat([z[1:] for z in zs])
        tool = torch.cat(feats)
        target = z_next - 2 * z_t + z_prev
        if not resume:
            model.in_norm.accumulate(torch.cat([z_t, z_t - z_prev, tool], dim=-1))
            model.out_norm.accumulate(target)
        z_std = model.in_norm.std()[: model.config.components]
    model.train()
    opt = torch.optim.Adam(model.mlp.parameters(), lr=lr_init)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, GeometricDecay(lr_final / lr_init, total))
    if state is not None:
        state.restore_optimizer(opt, sched)
    n = z_t.shape[0]
    history, t0 = [], time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

        bar = tqdm(total=total, initial=start, desc=f"train {scene.name} subspace", unit="step")
    window = []
    end = total if stop_after is None else min(total, start + int(stop_after))
    for step in range(start, end):
        g = torch.Generator().manual_seed(int(np.random.SeedSequence([seed, step]).generate_state(1)[0]))
        idx = torch.randint(0, n, (min(batch, n),), generator=g)
        eps = torch.randn(idx.shape[0], z_std.shape[0], generator=g,
                          dtype=torch.float64) * z_std * model.config.noise_std
        zt = z_t[idx] + eps
        # the target asks to undo the noise (as the GNN's training noise does)
        tgt = model.out_norm(z_next[idx] - 2 * zt + z_prev[idx]).float()
        pred = model.accel_norm(zt, z_prev[idx], tool[idx])
        loss = ((pred - tgt) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        window.append(float(loss.detach()))
        if (step + 1) % 100 == 0 or step + 1 == total:
            history.append({"step": step + 1, "loss": float(np.mean(window)), "lr": opt.param_groups[0]["lr"]})
            window = []
            if bar is not None:
                bar.set_postfix(loss=f"{history[-1]['loss']:.3g}", refresh=False)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    model.eval()
    meta = CheckpointMeta.for_scene(scene, "subspace", end)
    save_checkpoint(out_ckpt, model, meta, optimizer=opt, scheduler=sched,
                    extra={"steps": total, "batch": batch, "lr_init": lr_init, "lr_final": lr_final, "seed": seed,
                           "variance_kept": kept, "data_dir": str(data_dir),
                           "data_stats": data_stats(ds, model.template), **domain_extra(ds, seed)})
    return TrainResult(str(out_ckpt), end, total, time.perf_counter() - t0, "done" if end == total else "stop_after",
                       history[-1] if history else {}, history, model)
