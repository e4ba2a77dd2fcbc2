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

from colgnn_core.collision import CollisionDetector
from colgnn_core.collision.kernels import use_kernel_threads
from colgnn_core.errors import InputError
from colgnn_core.io import ensure_writable_dir
from colgnn_core.learn.checkpoint import (CheckpointMeta, check_compatible, read_checkpoint, save_checkpoint,
                                         simulator_from_payload)
from colgnn_core.learn.data import FrameDataset, read_manifest, sample_at
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.losses import REDUCTIONS, SurfaceRest, kl_latent, loss_ccd, loss_q, xi_random
from colgnn_core.learn.model import ModelConfig, Simulator
from colgnn_core.learn.subspace import train_subspace
from colgnn_core.learn.symmetry import NodeSymmetry, node_symmetry
from colgnn_core.learn.training_common import (GeometricDecay, TrainResult, data_stats, domain_extra,
                                              read_resumable)
from colgnn_core.scenes import load_scene
from colgnn_core.sim.prior import physics_prior

VARIANTS = ("full", "baseline", "no-compact", "subspace")
GNN_VARIANTS = ("full", "baseline", "no-compact")

# Model sizes come from the scene's [model] table (32/5/1 in the built-in scenes, sized for a small CPU: on the
# full-resolution scenes, 3-6k graph nodes, 1 thread, 128/15/2 took ~6.4 s per training step, 64/5/1 0.45-1.1 s,
# 32/3/1 0.13-0.29 s), unless TrainConfig.model or `colgnn train --model` overrides them.
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
    w_valid: float = 0.0              # L_valid (losses.flip_hinge): surface triangles turned from their rest normal
    valid_cos: float = 0.1            # ... cost below this cosine (the IPC truth stays above 0.19)
    ccd_form: str = "max"             # 'max' (paper) | 'mean' | 'sum_squares' (see losses.reduce_depths)
    compact_form: str = "max"
    compact_threshold: float | None = None  # Δ (m) of ξ_Random; None = the scene's dhat
    depth_scale: float | None = None  # length unit of the collision terms (m); None = target acceleration std
    ramp_begin: float = 0.1           # collision weights: 0 before this fraction of the optimisation steps ...
    ramp_end: float = 0.3             # ... full weight after this one
    clip_grad_norm: float | None = None
    symmetry: bool = False            # turn each sample by a random symmetry of the scene (learn.symmetry)
    checkpoint_every: int = 500
    log_every: int = 25
    # Overrides of the scene's [model] table; empty: the table decides (a user's `scene new` TOML, edited by hand,
    # is what `colgnn fit` trains).
    model: dict = field(default_factory=dict)

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
        if not self.w_valid >= 0 or not -1.0 < self.valid_cos < 1.0:
            raise InputError(f"need w_valid >= 0 and -1 < valid_cos < 1 (got {self.w_valid}, {self.valid_cos})")
        return self


def variant_weights(variant: str, cfg: TrainConfig) -> dict[str, float]:
    """The loss weights of a variant (before ramping)."""
    if variant not in GNN_VARIANTS:
        raise InputError(f"unknown variant {variant!r}; valid: {', '.join(VARIANTS)}")
    w = {"q": cfg.w_q, "ccd": cfg.w_ccd, "random": cfg.w_random, "kl": cfg.w_kl, "valid": cfg.w_valid}
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
    import torch.distributed as dist  # lazy: only under torchrun (WORLD_SIZE > 1)

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
    import torch.distributed as dist  # lazy: only under torchrun (WORLD_SIZE > 1)

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
LOSS_NAMES = ("loss", "L_q", "L_ccd", "xi_vf", "xi_ee", "xi_random", "L_kl", "L_valid", "n_vf", "n_ee")


def _resolve_scene(scene, data_dir: Path, resolution: str | None):
    if not isinstance(scene, str):
        return scene
    if resolution is None:
        manifest = read_manifest(data_dir) or {}
        resolution = manifest.get("resolution", "full")
    return load_scene(scene, resolution)


def _step_generator(seed: int, step: int, rank: int) -> torch.Generator:
    """Noise / random-latent generator of one step, derived from (seed, step, rank): no state to save."""
    s = np.random.SeedSequence([int(seed), int(step), int(rank)]).generate_state(2, np.uint32)
    return torch.Generator().manual_seed(int(s[0]) << 32 | int(s[1]))


def default_noise_std(stats: dict[str, float], fraction: float) -> float:
    """``fraction`` x the RMS per-frame displacement of the free graph nodes over the frames where things move."""
    return float(fraction * stats["rms_moving"])


def _optimizer(sim: Simulator, cfg: TrainConfig):
    opt = torch.optim.Adam(sim.parameters(), lr=cfg.lr_init)
    decay = cfg.decay_steps if cfg.decay_steps is not None else max(cfg.steps - cfg.warmup_steps, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, GeometricDecay(cfg.lr_final / cfg.lr_init, decay))
    return opt, sched


@dataclass
class _Model:
    """The trained model with its settings and optimizer, fresh or restored from a checkpoint."""

    cfg: TrainConfig
    template: object
    sim: Simulator
    opt: torch.optim.Optimizer
    sched: object
    start: int = 0            # steps done before this invocation
    wall_before: float = 0.0  # training wall time of the earlier invocations (s)
    init_from: str | None = None  # the checkpoint a fine-tune started from (``train(init=...)``)


def _fresh_model(scene, dataset: FrameDataset, config: TrainConfig | None, steps: int | None, seed: int) -> _Model:
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
    if sim.has_settled_rest:  # the quasi-static output and the rest feature refer to the ground truth's frame 0
        sim.set_settled_rest(dataset.sequences[0].object_positions[0][template.object_nodes])
    if mcfg.global_modes:
        if cfg.symmetry:
            raise InputError("global_modes and symmetry augmentation cannot be combined: the modes are fitted to "
                             "the unturned training displacements")
        sim.set_global_modes(dataset.displacements(template.object_nodes, sim.settled_rest.numpy()))
    return _Model(cfg, template, sim, *_optimizer(sim, cfg))


def _resumed_model(scene, out_ckpt: Path, variant: str, steps: int | None) -> _Model:
    state = read_resumable(out_ckpt, scene, variant, required=("train_config",))
    cfg = TrainConfig.from_dict(state.extra["train_config"])
    mcfg = ModelConfig.from_dict(state.payload["config"])
    template = template_from_scene(scene, surface_only=mcfg.surface_only, world_radius=mcfg.world_radius)
    sim = simulator_from_payload(state.payload, template, source=str(out_ckpt))
    if steps is not None:
        cfg.steps = int(steps)
    cfg.validate()
    opt, sched = _optimizer(sim, cfg)
    state.restore_optimizer(opt, sched)
    return _Model(cfg, template, sim, opt, sched, state.step, float(state.extra.get("wall_s", 0.0)),
                  state.extra.get("init_from"))


def _initialised_model(scene, init: Path, config: TrainConfig | None, steps: int | None) -> _Model:
    """A fine-tune: the weights and normalizer statistics of the checkpoint ``init`` (same scene, mesh and dt; a
    network, any variant), with a fresh optimizer and learning-rate schedule. The network's settings are the
    checkpoint's (the config's ``model`` overrides must be empty); the statistics go on accumulating on the new data
    (:mod:`.normalizer`)."""
    payload = read_checkpoint(init)
    meta = CheckpointMeta(**payload["meta"])
    check_compatible(meta, scene.name, scene.object.fingerprint(), float(scene.dt), source=str(init))
    if payload.get("kind", "gnn") != "gnn":
        raise InputError(f"{init}: only a network checkpoint can start a fine-tune, not a {payload['kind']!r} model")
    cfg = TrainConfig.from_dict((config or TrainConfig()).to_dict())
    if cfg.model:
        raise InputError("--init takes the network's settings from its checkpoint; drop --model, --model-options "
                         "and --graph")
    if steps is not None:
        cfg.steps = int(steps)
    cfg.validate()
    mcfg = ModelConfig.from_dict(payload["config"])
    template = template_from_scene(scene, surface_only=mcfg.surface_only, world_radius=mcfg.world_radius)
    sim = simulator_from_payload(payload, template, source=str(init))
    return _Model(cfg, template, sim, *_optimizer(sim, cfg), init_from=str(init))


def _surface_rest(dataset: FrameDataset, template) -> SurfaceRest:
    """L_valid's rest: the graph's surface at the settled rest, the first training sequence's frame 0."""
    return SurfaceRest.of(template.surface_faces, dataset.sequences[0].object_positions[0][template.object_nodes])


def _attach_prior(scene, dataset: FrameDataset, template, kind: str, progress: bool, mesh: str = "",
                  compliance: str = "", options: dict | None = None) -> None:
    """Give every training sample the ``kind`` physics prior (sim.prior), solved on the scene's ``mesh`` (its own
    when ""), along each sequence from its frame 0."""
    # With --symmetry each sample's prior is turned with it (learn.symmetry): the priors are functions of the pose
    # on the scene's mesh, so on a symmetric mesh the prior of a turned pose is the turned prior (knife_torus's edge
    # prior at full resolution, settled rest, modal compliance: to 5e-4 of its norm; exactly at ci).
    prior = physics_prior(kind, scene, dataset.sequences[0].object_positions[0], template.object_nodes, mesh=mesh,
                          compliance=compliance, options=options)
    dataset.attach_priors(lambda seq: prior.rollout(seq.tool_poses), progress=progress)


@dataclass
class _Run:
    """One training run: the model, the data and the loss set-up of the variant."""

    scene: object
    variant: str
    seed: int
    out_ckpt: Path
    dataset: FrameDataset
    dist: _Dist
    model: _Model
    detector: CollisionDetector
    weights: dict[str, float]
    delta: float              # Δ of ξ_Random (m)
    opt_total: int            # optimisation steps of the run (after the warm-up)
    free: torch.Tensor        # [N] bool: graph nodes that are not pinned
    n_free: int
    symmetry: NodeSymmetry | None = None  # cfg.symmetry: the scene's turns that each sample is augmented by
    extra: dict = field(default_factory=dict)  # saved with every checkpoint
    validity: SurfaceRest | None = None  # cfg.w_valid > 0: what L_valid compares the prediction with

    @property
    def cfg(self) -> TrainConfig:
        return self.model.cfg

    @property
    def sim(self) -> Simulator:
        return self.model.sim


def _setup(scene, data_dir: Path, out_ckpt: Path, variant: str, resume: bool, steps: int | None, seed: int,
           config: TrainConfig | None, init: Path | None = None) -> _Run:
    ensure_writable_dir(out_ckpt.parent if str(out_ckpt.parent) else Path("."))
    dist_ = _init_distributed()
    dataset = FrameDataset(scene, data_dir, "train")
    if resume:
        model = _resumed_model(scene, out_ckpt, variant, steps)
    elif init is not None:
        model = _initialised_model(scene, init, config, steps)
    else:
        model = _fresh_model(scene, dataset, config, steps, seed)
    model.sim.train()
    cfg, template = model.cfg, model.template
    # Crossings are also counted (without gradient) at logging steps of the baseline, for comparison.
    detector = CollisionDetector(template.surface_faces, scene.tool.faces, template.num_object_nodes,
                                 template.num_tool_nodes, tool=scene.tool)
    if model.sim.config.prior_kind:
        _attach_prior(scene, dataset, template, model.sim.config.prior_kind, dist_.main,
                      mesh=model.sim.config.prior_mesh, compliance=model.sim.config.prior_compliance,
                      options=model.sim.config.prior_options)
    symmetry = None
    if cfg.symmetry:
        symmetry = node_symmetry(scene, template.rest.numpy())
        if symmetry is None:
            raise InputError(f"{scene.name}: --symmetry needs a [symmetry] table in the scene (none declared)")
    extra = {"train_config": cfg.to_dict(), "seed": int(seed), "data_dir": str(data_dir),
             **({"init_from": model.init_from} if model.init_from else {}),
             "data_files": [s.name for s in dataset.sequences], "world_size": dist_.world,
             "noise_std": float(model.sim.config.noise_std), "data_stats": data_stats(dataset, template),
             **domain_extra(dataset, seed, symmetry)}
    if symmetry is not None:
        extra["symmetry_order"] = symmetry.order
    return _Run(scene, variant, seed, out_ckpt, dataset, dist_, model, detector, variant_weights(variant, cfg),
                delta=float(cfg.compact_threshold if cfg.compact_threshold is not None else scene.dhat),
                opt_total=max(cfg.steps - cfg.warmup_steps, 1), free=~template.pinned,
                n_free=int((~template.pinned).sum()), symmetry=symmetry, extra=extra,
                validity=_surface_rest(dataset, template) if cfg.w_valid > 0 else None)



# ---------------------------------------------------------------------------------------------------- one step
@dataclass
class _StepLosses:
    total: torch.Tensor                 # the loss to back-propagate
    terms: dict[str, torch.Tensor]      # every LOSS_NAMES entry (0 where not computed this step)
    computed: set[str]                  # the terms computed this step
    warm: bool                          # normalizer warm-up: no optimisation
    ramp: float                         # this step's collision-weight ramp
    before: list[torch.Tensor] | None   # normalizer buffers before the step (data-parallel runs)


def _losses(run: _Run, step: int, log_now: bool) -> _StepLosses:
    """Sample the step's transition, run the network and sum the variant's loss terms (paper eq. 2)."""
    cfg, sim, rank = run.cfg, run.sim, run.dist.rank
    frame, x_next, pose_t = run.dataset.sample(run.model.template,
                                               sample_at(step, len(run.dataset), run.seed, rank, run.dist.world))
    if run.symmetry is not None:  # a pure function of (seed, step, rank), like the sample order; -1: not turned
        k = int(np.random.default_rng([run.seed, step, rank, 1]).integers(-1, run.symmetry.order - 1))
        frame, x_next, pose_t = run.symmetry.turn(frame, x_next, pose_t, k)
    gen = _step_generator(run.seed, step, rank)
    warm = step < cfg.warmup_steps
    r = 0.0 if warm else ramp(step - cfg.warmup_steps, run.opt_total, cfg.ramp_begin, cfg.ramp_end)
    w_ccd, w_rand, w_kl = run.weights["ccd"] * r, run.weights["random"] * r, run.weights["kl"] * r
    w_valid = run.weights["valid"] * r
    before = _snapshot(sim) if run.dist.world > 1 else None

    out = sim(frame, x_next, generator=gen, noise=True, accumulate=True, random_latent=w_rand > 0)
    terms = {k: torch.zeros((), dtype=torch.float64) for k in LOSS_NAMES}
    computed = {"loss", "L_q"}
    lq = loss_q(out.pred_norm, out.target_norm, out.loss_mask)
    total = run.weights["q"] * lq
    terms["L_q"] = lq.detach().double()
    scale = (float(cfg.depth_scale) if cfg.depth_scale is not None
             else float(sim.output_normalizer.std().mean()))
    if w_ccd > 0 or log_now:
        with torch.set_grad_enabled(w_ccd > 0):
            depths = run.detector.crossing_depths_torch(out.x_t, out.x_next_pred, frame.tool_t, frame.tool_next,
                                                        pose_t, frame.pose_next)
        lccd, vf, ee = loss_ccd(depths, cfg.ccd_form, scale, run.n_free)
        if w_ccd > 0:
            total = total + w_ccd * lccd
        terms.update(L_ccd=lccd.detach().double(), xi_vf=vf.detach().double(), xi_ee=ee.detach().double(),
                     n_vf=torch.tensor(float(depths["vertex_face"].numel()), dtype=torch.float64),
                     n_ee=torch.tensor(float(depths["edge_edge"].numel()), dtype=torch.float64))
        computed |= {"L_ccd", "xi_vf", "xi_ee", "n_vf", "n_ee"}
    if w_rand > 0 or w_kl > 0:
        xr = xi_random(run.scene.tool, out.x_next_random, frame.pose_next, run.delta, cfg.compact_form, scale,
                       run.free)
        kl = kl_latent(out.latents, out.loss_mask)
        total = total + w_rand * xr + w_kl * kl
        terms.update(xi_random=xr.detach().double(), L_kl=kl.detach().double())
        computed |= {"xi_random", "L_kl"}
    if run.validity is not None and (w_valid > 0 or log_now):
        with torch.set_grad_enabled(w_valid > 0):
            lv = run.validity.loss(out.x_next_pred, x_next, cfg.valid_cos)
        if w_valid > 0:
            total = total + w_valid * lv
        terms["L_valid"] = lv.detach().double()
        computed.add("L_valid")
    terms["loss"] = total.detach().double()
    return _StepLosses(total, terms, computed, warm, r, before)


def _optimise(run: _Run, losses: _StepLosses, over_budget) -> tuple[torch.Tensor, bool]:
    """Back-propagate, average over the ranks and step the optimizer (not in the warm-up).

    ``over_budget()`` says whether the time budget is spent (asked after the backward pass). Returns the loss
    scalars (rank average, LOSS_NAMES order) and whether to stop (any rank over budget)."""
    run.model.opt.zero_grad(set_to_none=False)
    if not losses.warm:
        losses.total.backward()
    stop = over_budget()
    scalars = torch.stack([losses.terms[k].reshape(()) for k in LOSS_NAMES])
    if run.dist.world > 1:
        scalars, stop = _all_reduce_step(run.sim, losses.before, scalars, stop, run.dist)
    if not losses.warm:
        if run.cfg.clip_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(run.sim.parameters(), run.cfg.clip_grad_norm)
        run.model.opt.step()
        run.model.sched.step()
    return scalars, stop


# ---------------------------------------------------------------------------------------------------- logging
class _TrainLog:
    """Logged rows (window means of the loss terms every ``log_every`` steps), TensorBoard and the progress bar;
    rank 0 only."""

    def __init__(self, run: _Run, log_dir, progress: bool):
        self.main = run.dist.main
        self.start = run.model.start
        self.writer = None
        self.bar = None
        self.history: list[dict] = []
        self.last: dict[str, float] = {}
        self.window = {k: [0.0, 0] for k in LOSS_NAMES}
        if not self.main:
            return
        if log_dir is None:
            log_dir = run.out_ckpt.parent / f"{run.out_ckpt.stem}.tb"
        if log_dir is not False:
            from torch.utils.tensorboard import SummaryWriter  # lazy: tensorboard is heavy and optional

            self.writer = SummaryWriter(str(log_dir))
        if progress:
            from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

            self.bar = tqdm(total=run.cfg.steps, initial=self.start, desc=f"train {run.scene.name} {run.variant}",
                            unit="step", dynamic_ncols=True)

    def record(self, step: int, scalars: torch.Tensor, losses: _StepLosses, lr: float, log_now: bool,
               t0: float) -> None:
        """Add a step's loss scalars to the window; at a logging step write the row (``step``: steps done)."""
        for k, v in zip(LOSS_NAMES, scalars.tolist()):  # window means between log rows (one sample is noisy)
            if k in losses.computed:
                self.window[k][0] += v
                self.window[k][1] += 1
        if log_now and self.main:
            row = {"step": step, "lr": lr, "ramp": losses.ramp,
                   **{k: self.window[k][0] / max(self.window[k][1], 1) for k in LOSS_NAMES}}
            self.history.append(row)
            self.last = row
            if self.writer is not None:
                for k in LOSS_NAMES:
                    self.writer.add_scalar(f"loss/{k}" if not k.startswith("n_") else f"collisions/{k}", row[k], step)
                self.writer.add_scalar("train/lr", row["lr"], step)
                self.writer.add_scalar("train/ramp", losses.ramp, step)
                self.writer.add_scalar("train/steps_per_s",
                                       (step - self.start) / max(time.perf_counter() - t0, 1e-9), step)
            self.window = {k: [0.0, 0] for k in LOSS_NAMES}
            if self.bar is not None:
                self.bar.set_postfix(q=f"{row['L_q']:.3g}", ccd=f"{row['L_ccd']:.3g}", rand=f"{row['xi_random']:.3g}",
                                     kl=f"{row['L_kl']:.3g}", lr=f"{row['lr']:.1e}", refresh=False)
        if self.bar is not None:
            self.bar.update(1)

    def close_bar(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()


def _save(run: _Run, step: int, t0: float) -> None:
    """Write the checkpoint after ``step`` steps (rank 0), atomically."""
    if not run.dist.main:
        return
    meta = CheckpointMeta.for_scene(run.scene, run.variant, step)
    save_checkpoint(run.out_ckpt, run.sim, meta, optimizer=run.model.opt, scheduler=run.model.sched,
                    extra={**run.extra, "wall_s": run.model.wall_before + (time.perf_counter() - t0)})


# ---------------------------------------------------------------------------------------------------- train
def train(scene, data_dir: str | os.PathLike, out_ckpt: str | os.PathLike, variant: str = "full",
          resume: bool = False, steps: int | None = None, seed: int = 0, threads: int | None = None, *,
          config: TrainConfig | None = None, resolution: str | None = None, time_budget_s: float | None = None,
          stop_after: int | None = None, progress: bool = True, log_dir: str | os.PathLike | None | bool = None,
          on_step=None, init: str | os.PathLike | None = None) -> TrainResult:
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
        on_step: called as ``on_step(step, total_steps)`` after every logged step (rank 0), e.g. by a pipeline's
            own progress display.
        init: start from this checkpoint's weights and normalizers (a fine-tune; see :func:`_initialised_model`),
            not from random weights; ignored on resume (the run stored in ``out_ckpt`` records it).

    Raises:
        InputError: unknown variant, bad data, a checkpoint of another scene/variant, unwritable output.
    """
    if variant not in VARIANTS:
        raise InputError(f"unknown variant {variant!r}; valid: {', '.join(VARIANTS)}")
    if threads is not None:
        if int(threads) < 1:
            raise InputError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(int(threads))
        use_kernel_threads(int(threads))
    data_dir = Path(data_dir)
    out_ckpt = Path(out_ckpt)
    scene = _resolve_scene(scene, data_dir, resolution)
    if variant == "subspace":
        return train_subspace(scene, data_dir, out_ckpt, resume=resume, steps=steps, seed=seed, progress=progress,
                              stop_after=stop_after)
    if init is not None and variant == "subspace":
        raise InputError("--init fine-tunes a network; the subspace variant has none")
    run = _setup(scene, data_dir, out_ckpt, variant, resume, steps, seed, config,
                 Path(init) if init is not None and not resume else None)
    log = _TrainLog(run, log_dir, progress)
    t0 = time.perf_counter()
    step, stopped = run.model.start, "done"

    def over_budget() -> bool:
        return time_budget_s is not None and time.perf_counter() - t0 >= time_budget_s

    try:
        while step < run.cfg.steps:
            log_now = (step + 1) % run.cfg.log_every == 0 or step + 1 == run.cfg.steps
            losses = _losses(run, step, log_now)
            scalars, stop = _optimise(run, losses, over_budget)
            step += 1
            if stop_after is not None and step - run.model.start >= stop_after:
                stop, stopped = True, "stop_after"
            elif stop:
                stopped = "time budget"
            log.record(step, scalars, losses, float(run.model.opt.param_groups[0]["lr"]), log_now, t0)
            if on_step is not None and log_now and run.dist.main:
                on_step(step, run.cfg.steps)
            if step % run.cfg.checkpoint_every == 0 and step < run.cfg.steps and not stop:
                _save(run, step, t0)
            if stop:
                break
    except KeyboardInterrupt:
        _save(run, step, t0)
        raise
    finally:
        log.close_bar()
    _save(run, step, t0)
    log.close()
    return TrainResult(str(out_ckpt), step, run.cfg.steps, time.perf_counter() - t0, stopped, log.last, log.history,
                       run.sim)
