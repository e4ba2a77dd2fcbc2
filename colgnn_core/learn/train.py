"""Training loop behind ``colgnn train``: one code path for the variants full, baseline and no-compact.

Loss (paper eq. 2): ``L = w_q L_q + w_ccd L_ccd + w_random ξ_Random + w_kl L_KL``

* ``baseline``   (MeshGraphNets): L_q only;
* ``no-compact`` (the paper's ablation): L_q + L_ccd;
* ``full``       (the paper's method): L_q + L_ccd + L_compact;
* ``subspace``   (Holden et al. 2019): a different model, trained by :mod:`colgnn_core.learn.subspace`.

The collision weights ramp linearly from 0 (``ramp_begin``) to their value
(``ramp_end``, fractions of the optimisation steps): the collision terms only
make sense once the network predicts roughly the right motion.

Optimisation follows the paper / MGN: batch size 1 (one transition per step and
rank), Adam, exponential learning-rate decay ``lr_init -> lr_final`` over the
run, Gaussian noise on the input positions, online normalizers that first
accumulate statistics for ``warmup_steps`` steps without optimising.

Determinism: the sample order is a pure function of (seed, step, rank) and the
noise / random-latent generator is re-seeded from (seed, step, rank) every step,
so a run is fixed by its seed and ``resume`` continues bit for bit from the
checkpoint (model, normalizers, Adam, scheduler and step are saved).

Data-parallel: started under ``torchrun``, each rank takes a disjoint shard of
every epoch; gradients are averaged and the normalizer statistics summed with
one all-reduce per step (gloo on CPU), so all ranks hold identical parameters.
Only rank 0 writes checkpoints and logs.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.io import ensure_writable_dir
from colgnn_core.learn.checkpoint import (CheckpointMeta, check_compatible, read_checkpoint, save_checkpoint,
                                          simulator_from_payload)
from colgnn_core.learn.data import FrameDataset, read_manifest, sample_at
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.losses import REDUCTIONS, kl_latent, loss_ccd, loss_q, xi_random
from colgnn_core.learn.model import ModelConfig, Simulator

VARIANTS = ("full", "baseline", "no-compact", "subspace")
GNN_VARIANTS = ("full", "baseline", "no-compact")

# Model size for training on a small CPU. Measured on the full-resolution scenes (3-6k graph nodes, 1 thread, shared
# 2-core machine): 128/15/2 (the scene TOMLs) ~6.4 s per training step and ~1.9 s per prediction; 64/5/1 0.45-1.1 s
# per step; 32/3/1 0.13-0.29 s per step. 32/5/1 allows ~10-25k steps in 90 minutes.
DEFAULT_MODEL = {"latent": 32, "message_passing_steps": 5, "mlp_layers": 1}


@dataclass
class TrainConfig:
    """Training settings (saved in the checkpoint; a resumed run uses the saved ones).

    Lengths in metres, steps counted in training steps (one transition per rank each).
    """

    steps: int = 20000                # total steps, warm-up included
    warmup_steps: int = 200           # normalizer accumulation only (MGN: 1000)
    lr_init: float = 1e-3             # paper: 1e-4 -> 1e-6 over 1e5 steps; we train ~10x fewer steps
    lr_final: float = 1e-5
    decay_steps: int | None = None    # optimisation steps of the lr decay; None = the whole run
    noise_std: float | None = None    # input noise (m); None = noise_fraction * RMS per-frame displacement
    noise_fraction: float = 0.1
    w_q: float = 1.0
    w_ccd: float = 1.0
    w_random: float = 1.0
    w_kl: float = 0.01
    ccd_form: str = "max"             # 'max' (paper) | 'mean' | 'sum_squares' (see losses.reduce_depths)
    compact_form: str = "max"
    compact_threshold: float | None = None  # Δ (m) of ξ_Random; None = the scene's dhat
    depth_scale: float | None = None  # length unit of the collision terms (m); None = target acceleration std
    ramp_begin: float = 0.1           # collision weights: 0 before this fraction of the optimisation steps ...
    ramp_end: float = 0.3             # ... full weight after this one
    clip_grad_norm: float | None = None
    checkpoint_every: int = 500
    log_every: int = 25
    model: dict = field(default_factory=lambda: dict(DEFAULT_MODEL))  # overrides of the scene's [model] table

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"unknown training config keys: {', '.join(sorted(unknown))}")
        return cls(**d)

    def validate(self) -> "TrainConfig":
        if self.steps < 1 or self.warmup_steps < 0:
            raise InputError(f"steps must be >= 1 and warmup_steps >= 0 (got {self.steps}, {self.warmup_steps})")
        if not (self.lr_init > 0 and self.lr_final > 0):
            raise InputError("learning rates must be > 0")
        for name in ("ccd_form", "compact_form"):
            if getattr(self, name) not in REDUCTIONS:
                raise InputError(f"{name} must be one of {', '.join(REDUCTIONS)}, got {getattr(self, name)!r}")
        if not 0 <= self.ramp_begin <= self.ramp_end:
            raise InputError("need 0 <= ramp_begin <= ramp_end")
        return self


def variant_weights(variant: str, cfg: TrainConfig) -> dict[str, float]:
    """The loss weights of a variant (before ramping)."""
    if variant not in GNN_VARIANTS:
        raise InputError(f"unknown variant {variant!r}; valid: {', '.join(VARIANTS)}")
    w = {"q": cfg.w_q, "ccd": cfg.w_ccd, "random": cfg.w_random, "kl": cfg.w_kl}
    if variant in ("baseline", "no-compact"):
        w["random"] = w["kl"] = 0.0
    if variant == "baseline":
        w["ccd"] = 0.0
    return w


def ramp(opt_step: int, opt_total: int, begin: float, end: float) -> float:
    """Linear ramp 0 -> 1 between fractions ``begin`` and ``end`` of ``opt_total`` optimisation steps."""
    a, b = begin * opt_total, end * opt_total
    if opt_step >= b:
        return 1.0
    if opt_step < a:
        return 0.0
    return (opt_step - a) / max(b - a, 1e-12)


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
    simulator: Simulator | None = None  # the trained model (this rank's copy)


# ---------------------------------------------------------------------------------------------------- distributed
@dataclass
class _Dist:
    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def _init_distributed() -> _Dist:
    """gloo process group when started by torchrun (WORLD_SIZE > 1); single process otherwise."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return _Dist()
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo")
    return _Dist(dist.get_rank(), dist.get_world_size())


def _normalizers(sim: Simulator) -> list:
    return [sim.node_normalizer, *sim.edge_normalizers.values(), sim.output_normalizer]


_NORM_BUFFERS = ("acc_count", "num_accumulations", "acc_sum", "acc_sum_squared")


def _snapshot(sim: Simulator) -> list[torch.Tensor]:
    return [getattr(n, b).clone() for n in _normalizers(sim) for b in _NORM_BUFFERS]


def _all_reduce_step(sim: Simulator, before: list[torch.Tensor], scalars: torch.Tensor, stop: bool,
                     dist_: _Dist) -> tuple[torch.Tensor, bool]:
    """One all-reduce: average gradients and loss scalars, sum normalizer increments, OR the stop flag."""
    import torch.distributed as dist

    params = list(sim.parameters())
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    bufs = [getattr(n, b) for n in _normalizers(sim) for b in _NORM_BUFFERS]
    deltas = [(a - b0).reshape(-1) for a, b0 in zip(bufs, before)]
    flat = torch.cat([*(g.reshape(-1).double() for g in grads), *deltas, scalars.double(),
                      torch.tensor([1.0 if stop else 0.0], dtype=torch.float64)])
    dist.all_reduce(flat)
    i = 0
    for p, g in zip(params, grads):
        n = g.numel()
        p.grad = (flat[i:i + n] / dist_.world).reshape(g.shape).to(p.dtype)
        i += n
    for buf, b0 in zip(bufs, before):
        n = buf.numel()
        buf.copy_(b0 + flat[i:i + n].reshape(buf.shape))
        i += n
    k = scalars.numel()
    out = flat[i:i + k] / dist_.world
    return out, bool(flat[i + k] > 0)


# ---------------------------------------------------------------------------------------------------- setup
def _resolve_scene(scene, data_dir: Path, resolution: str | None):
    if not isinstance(scene, str):
        return scene
    from colgnn_core.scenes import load_scene

    if resolution is None:
        manifest = read_manifest(data_dir) or {}
        resolution = manifest.get("resolution", "full")
    return load_scene(scene, resolution)


def _step_generator(seed: int, step: int, rank: int) -> torch.Generator:
    """Noise / random-latent generator of one step, derived from (seed, step, rank): no state to save."""
    s = np.random.SeedSequence([int(seed), int(step), int(rank)]).generate_state(2, np.uint32)
    return torch.Generator().manual_seed(int(s[0]) << 32 | int(s[1]))


def data_stats(dataset: FrameDataset, template) -> dict[str, float]:
    """Displacement statistics (m) of the free graph nodes (see ``FrameDataset.displacement_stats``)."""
    return dataset.displacement_stats(template.object_nodes, ~template.pinned.numpy())


def default_noise_std(stats: dict[str, float], fraction: float) -> float:
    """``fraction`` x the RMS per-frame displacement of the free graph nodes over the frames where things move."""
    return float(fraction * stats["rms_moving"])


def _optimizer(sim: Simulator, cfg: TrainConfig):
    opt = torch.optim.Adam(sim.parameters(), lr=cfg.lr_init)
    decay = cfg.decay_steps if cfg.decay_steps is not None else max(cfg.steps - cfg.warmup_steps, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, GeometricDecay(cfg.lr_final / cfg.lr_init, decay))
    return opt, sched


# ---------------------------------------------------------------------------------------------------- train
def train(scene, data_dir: str | os.PathLike, out_ckpt: str | os.PathLike, variant: str = "full",
          resume: bool = False, steps: int | None = None, seed: int = 0, threads: int | None = None, *,
          config: TrainConfig | None = None, resolution: str | None = None, time_budget_s: float | None = None,
          stop_after: int | None = None, progress: bool = True, log_dir: str | os.PathLike | None | bool = None
          ) -> TrainResult:
    """Train a model on a dataset folder and write the checkpoint ``out_ckpt``.

    Args:
        scene: a Scene, or a scene name (resolution from ``resolution``, else the dataset manifest, else 'full').
        data_dir: dataset folder with ``train_XXXX.npz`` (see :mod:`colgnn_core.learn.data`).
        out_ckpt: checkpoint path (written atomically every ``checkpoint_every`` steps and at the end).
        variant: 'full' | 'baseline' | 'no-compact' | 'subspace'.
        resume: continue from ``out_ckpt`` (same variant and scene; the saved training config is used).
        steps: total steps of the run (default: the config's); on resume it may extend the run (the lr
            schedule keeps its original length, then stays at lr_final).
        seed: fixes initial weights, sample order, noise and random latents.
        threads: ``torch.set_num_threads`` for this process (None: leave as is).
        config: training settings (default :class:`TrainConfig`()).
        time_budget_s: stop (with a checkpoint) once this much wall time has passed in this invocation.
        stop_after: stop (with a checkpoint) after this many steps in this invocation (training in chunks).
        progress: tqdm progress bar with the loss terms (rank 0).
        log_dir: TensorBoard folder (default ``<out_ckpt stem>.tb`` beside the checkpoint; False: none).

    Raises:
        InputError: unknown variant, bad data, a checkpoint of another scene/variant, unwritable output.
    """
    if variant not in VARIANTS:
        raise InputError(f"unknown variant {variant!r}; valid: {', '.join(VARIANTS)}")
    if threads is not None:
        if int(threads) < 1:
            raise InputError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(int(threads))
    data_dir = Path(data_dir)
    out_ckpt = Path(out_ckpt)
    scene = _resolve_scene(scene, data_dir, resolution)
    if variant == "subspace":
        from colgnn_core.learn.subspace import train_subspace

        return train_subspace(scene, data_dir, out_ckpt, resume=resume, steps=steps, seed=seed, progress=progress,
                              stop_after=stop_after)
    ensure_writable_dir(out_ckpt.parent if str(out_ckpt.parent) else Path("."))
    dist_ = _init_distributed()
    dataset = FrameDataset(scene, data_dir, "train")

    # -- model, optimizer: fresh or from the checkpoint ------------------------------------------------------
    if resume:
        payload = read_checkpoint(out_ckpt)
        meta = CheckpointMeta(**payload["meta"])
        check_compatible(meta, scene.name, scene.object.fingerprint(), float(scene.dt), source=str(out_ckpt))
        if meta.variant != variant:
            raise InputError(f"{out_ckpt} was trained as variant {meta.variant!r}, not {variant!r}")
        extra = payload.get("extra") or {}
        if "train_config" not in extra or payload.get("optimizer") is None:
            raise InputError(f"{out_ckpt} has no training state to resume (a shipped/stripped model?)")
        cfg = TrainConfig.from_dict(extra["train_config"])
        mcfg = ModelConfig.from_dict(payload["config"])
        template = template_from_scene(scene, surface_only=mcfg.surface_only, world_radius=mcfg.world_radius)
        sim = simulator_from_payload(payload, template, source=str(out_ckpt))
        if steps is not None:
            cfg.steps = int(steps)
        cfg.validate()
        opt, sched = _optimizer(sim, cfg)
        opt.load_state_dict(payload["optimizer"])
        sched.load_state_dict(payload["scheduler"])
        start = int(meta.step)
        wall_total = float(extra.get("wall_s", 0.0))
    else:
        cfg = TrainConfig.from_dict((config or TrainConfig()).to_dict())
        if steps is not None:
            cfg.steps = int(steps)
        cfg.validate()
        template = template_from_scene(scene, surface_only=cfg.model.get("surface_only"),
                                       world_radius=cfg.model.get("world_radius"))
        noise = (cfg.noise_std if cfg.noise_std is not None
                 else default_noise_std(data_stats(dataset, template), cfg.noise_fraction))
        mcfg = ModelConfig.from_scene(scene, **{**cfg.model, "noise_std": float(noise)})
        torch.manual_seed(seed)  # identical initial weights on every rank
        sim = Simulator(template, mcfg)
        opt, sched = _optimizer(sim, cfg)
        start = 0
        wall_total = 0.0
    sim.train()
    weights = variant_weights(variant, cfg)
    delta = float(cfg.compact_threshold if cfg.compact_threshold is not None else scene.dhat)
    opt_total = max(cfg.steps - cfg.warmup_steps, 1)
    # Crossings are also counted (without gradient) at logging steps of the baseline, for comparison.
    from colgnn_core.collision import CollisionDetector

    detector = CollisionDetector(template.surface_faces, scene.tool.faces, template.num_object_nodes,
                                 template.num_tool_nodes, tool=scene.tool)
    free = ~template.pinned
    n_free = int(free.sum())
    extra_base = {"train_config": cfg.to_dict(), "seed": int(seed), "data_dir": str(data_dir),
                  "data_files": [s.name for s in dataset.sequences], "world_size": dist_.world,
                  "noise_std": float(mcfg.noise_std), "data_stats": data_stats(dataset, template)}

    # -- logging (rank 0) ----------------------------------------------------------------------------------
    writer = None
    bar = None
    if dist_.main:
        if log_dir is None:
            log_dir = out_ckpt.parent / f"{out_ckpt.stem}.tb"
        if log_dir is not False:
            from torch.utils.tensorboard import SummaryWriter

            writer = SummaryWriter(str(log_dir))
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=cfg.steps, initial=start, desc=f"train {scene.name} {variant}", unit="step",
                       dynamic_ncols=True)

    def checkpoint(step: int) -> None:
        if not dist_.main:
            return
        meta = CheckpointMeta.for_scene(scene, variant, step)
        save_checkpoint(out_ckpt, sim, meta, optimizer=opt, scheduler=sched,
                        extra={**extra_base, "wall_s": wall_total + (time.perf_counter() - t0)})

    names = ("loss", "L_q", "L_ccd", "xi_vf", "xi_ee", "xi_random", "L_kl", "n_vf", "n_ee")
    history: list[dict] = []
    window = {k: [0.0, 0] for k in names}
    last: dict[str, float] = {}
    t0 = time.perf_counter()
    step = start
    stopped = "done"
    try:
        while step < cfg.steps:
            i = sample_at(step, len(dataset), seed, dist_.rank, dist_.world)
            frame, x_next, pose_t = dataset.sample(template, i)
            gen = _step_generator(seed, step, dist_.rank)
            warm = step < cfg.warmup_steps
            opt_step = step - cfg.warmup_steps
            r = 0.0 if warm else ramp(opt_step, opt_total, cfg.ramp_begin, cfg.ramp_end)
            w_ccd, w_rand, w_kl = weights["ccd"] * r, weights["random"] * r, weights["kl"] * r
            log_now = (step + 1) % cfg.log_every == 0 or step + 1 == cfg.steps
            before = _snapshot(sim) if dist_.world > 1 else None

            out = sim(frame, x_next, generator=gen, noise=True, accumulate=True, random_latent=w_rand > 0)
            terms = {k: torch.zeros((), dtype=torch.float64) for k in names}
            computed = {"loss", "L_q"}
            lq = loss_q(out.pred_norm, out.target_norm, out.loss_mask)
            total = weights["q"] * lq
            terms["L_q"] = lq.detach().double()
            scale = (float(cfg.depth_scale) if cfg.depth_scale is not None
                     else float(sim.output_normalizer.std().mean()))
            if w_ccd > 0 or log_now:
                with torch.set_grad_enabled(w_ccd > 0):
                    depths = detector.crossing_depths_torch(out.x_t, out.x_next_pred, frame.tool_t, frame.tool_next,
                                                            pose_t, frame.pose_next)
                lccd, vf, ee = loss_ccd(depths, cfg.ccd_form, scale, n_free)
                if w_ccd > 0:
                    total = total + w_ccd * lccd
                terms.update(L_ccd=lccd.detach().double(), xi_vf=vf.detach().double(), xi_ee=ee.detach().double(),
                             n_vf=torch.tensor(float(depths["vertex_face"].numel()), dtype=torch.float64),
                             n_ee=torch.tensor(float(depths["edge_edge"].numel()), dtype=torch.float64))
                computed |= {"L_ccd", "xi_vf", "xi_ee", "n_vf", "n_ee"}
            if w_rand > 0 or w_kl > 0:
                xr = xi_random(scene.tool, out.x_next_random, frame.pose_next, delta, cfg.compact_form, scale, free)
                kl = kl_latent(out.latents, out.loss_mask)
                total = total + w_rand * xr + w_kl * kl
                terms.update(xi_random=xr.detach().double(), L_kl=kl.detach().double())
                computed |= {"xi_random", "L_kl"}
            terms["loss"] = total.detach().double()

            opt.zero_grad(set_to_none=False)
            if not warm:
                total.backward()
            over_budget = time_budget_s is not None and time.perf_counter() - t0 >= time_budget_s
            scalars = torch.stack([terms[k].reshape(()) for k in names])
            stop = over_budget
            if dist_.world > 1:
                scalars, stop = _all_reduce_step(sim, before, scalars, stop, dist_)
            if not warm:
                if cfg.clip_grad_norm is not None:
                    torch.nn.utils.clip_grad_norm_(sim.parameters(), cfg.clip_grad_norm)
                opt.step()
                sched.step()
            step += 1
            if stop_after is not None and step - start >= stop_after:
                stop, stopped = True, "stop_after"
            elif stop:
                stopped = "time budget"

            for k, v in zip(names, scalars.tolist()):  # window means between log rows (one sample per step is noisy)
                if k in computed:
                    window[k][0] += v
                    window[k][1] += 1
            if log_now and dist_.main:
                row = {"step": step, "lr": float(opt.param_groups[0]["lr"]), "ramp": r,
                       **{k: window[k][0] / max(window[k][1], 1) for k in names}}
                history.append(row)
                last = row
                if writer is not None:
                    for k in names:
                        writer.add_scalar(f"loss/{k}" if not k.startswith("n_") else f"collisions/{k}", row[k], step)
                    writer.add_scalar("train/lr", row["lr"], step)
                    writer.add_scalar("train/ramp", r, step)
                    writer.add_scalar("train/steps_per_s", (step - start) / max(time.perf_counter() - t0, 1e-9), step)
                window = {k: [0.0, 0] for k in names}
                if bar is not None:
                    bar.set_postfix(q=f"{row['L_q']:.3g}", ccd=f"{row['L_ccd']:.3g}", rand=f"{row['xi_random']:.3g}",
                                    kl=f"{row['L_kl']:.3g}", lr=f"{row['lr']:.1e}", refresh=False)
            if bar is not None:
                bar.update(1)
            if step % cfg.checkpoint_every == 0 and step < cfg.steps and not stop:
                checkpoint(step)
            if stop:
                break
    except KeyboardInterrupt:
        checkpoint(step)
        raise
    finally:
        if bar is not None:
            bar.close()
    checkpoint(step)
    if writer is not None:
        writer.flush()
        writer.close()
    return TrainResult(str(out_ckpt), step, cfg.steps, time.perf_counter() - t0, stopped, last, history, sim)
