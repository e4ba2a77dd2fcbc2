"""``colgnn evaluate --frontier``: speed against error, every method on the same test poses in one run.

Points (each one the mean over the chosen held-out test sequences, cut to ``steps`` + 1 frames):

* every given GNN checkpoint, raw and with the collision-aware correction (labelled by variant and
  latent / message-passing steps / MLP layers);
* the IPC solver at the settings the data was generated with (its error is 0 by definition: it *is* the
  reference) and at looser settings (``IPC_SETTINGS``: a 10x looser Newton tolerance, a 2x larger d-hat),
  re-simulated here so that its time is measured in the same run.

* the trivial baseline ``rest + correction`` (the network replaced by "stay at rest", the correction on).

x = median wall ms per step (Predictor / network step, or solver step); y = the relative displacement error
(:func:`colgnn_core.evaluation.measure.relative_displacement_error`, all vertices; 1.0 = "nothing moves"), mean over
the sequences, with the contact region's and the RMSE at the last step (a fraction of the bbox diagonal) in the
table; every point carries its exact crossing count (N_vf + N_ee
summed over the steps, ipctk oracle) and intersecting frames. Outputs in ``out_dir``: ``frontier.json``
(atomic), ``frontier.md`` and ``frontier.png`` (log x).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import torch

from colgnn_core.collision.metrics import sequence_metrics
from colgnn_core.errors import InputError
from colgnn_core.evaluation.accuracy import write_report
from colgnn_core.evaluation.measure import collision_aggregate, relative_errors, rmse_fraction, stats, test_files
from colgnn_core.evaluation.render import save_png
from colgnn_core.io import ensure_writable_dir, load_sequence
from colgnn_core.learn.data import load_checked_sequence
from colgnn_core.runtime.interior import interior_lift
from colgnn_core.runtime.models import load_model, rest_baseline, settled_rest
from colgnn_core.runtime.predictor import REALTIME_INTERIOR
from colgnn_core.runtime.rollout import rollout
from colgnn_core.scenes import load_scene, scene_names
from colgnn_core.sim.dataset import simulate_sequence

IPC_SETTINGS: tuple[tuple[str, dict], ...] = (
    ("IPC (data settings)", {}),
    ("IPC newton_tol x10", {"newton_tol": 1e-1}),
    ("IPC dhat x2", {"dhat_scale": 2.0}),
)


def model_size(loaded) -> str:
    """'latent/message-passing steps/MLP layers' of a GNN checkpoint ('' for models without one)."""
    m = getattr(loaded.simulator, "config", None)
    if not all(hasattr(m, k) for k in ("latent", "message_passing_steps", "mlp_layers")):
        return ""  # the subspace model has no graph network
    return f"{m.latent}/{m.message_passing_steps}/{m.mlp_layers}"


def _label(loaded, path) -> str:
    size = model_size(loaded)
    return f"{loaded.meta.variant}{' ' + size if size else ''} ({Path(str(path)).stem})"


def _point(label: str, kind: str, seqs: list, truths: list, ms: list[float], diagonal: float, exact: bool) -> dict:
    """One frontier point from rollouts ``seqs`` against ``truths`` (Sequences) and per-step times ``ms``."""
    last = [float(rmse_fraction(s.object_positions, t.object_positions, diagonal)[-1]) for s, t in zip(seqs, truths)]
    agg = collision_aggregate([sequence_metrics(s, exact=exact) for s in seqs])
    rel = [relative_errors(s.object_positions, t.object_positions) for s, t in zip(seqs, truths)]
    return {"label": label, "kind": kind, "ms_median": stats(ms)["median"],
            "relative": float(np.mean([r["all"] for r in rel])),
            "relative_contact": float(np.mean([r["contact"] for r in rel])),
            "rmse_last": float(np.mean(last)),
            "rmse_last_std": float(np.std(last)), "crossings": agg["N_vf_total"] + agg["N_ee_total"],
            "intersecting_frames": agg["intersecting_frames"]}


def frontier(scene_name: str, checkpoints: list, data_dir, out_dir="out/frontier", *, steps: int = 40,
             max_sequences: int = 2, threads: int = 2, compile: bool = False, ipc: bool = True,
             ipc_sequences: int | None = None, exact: bool = True, progress: bool = True) -> dict:
    """Measure the speed/error frontier of ``checkpoints`` (and the IPC solver) on a scene's test data.

    Args:
        scene_name: the scene; every checkpoint must be of it, at the data's resolution.
        checkpoints: GNN checkpoint paths (at least one).
        data_dir: dataset folder with ``test_XXXX.npz`` (``colgnn generate``).
        steps: rollout length (the sequences must have at least ``steps`` + 1 frames).
        max_sequences: how many test sequences (the first ones).
        threads: torch threads for every network (set process-wide).
        compile: torch.compile the networks (see :class:`~colgnn_core.runtime.predictor.Predictor`).
        ipc: include the solver points (re-simulated: the slow part at full resolution).
        ipc_sequences: re-simulate only the first this many sequences for the solver points (default: all the
            network points use); at full resolution a solver step takes seconds.
        exact: crossings with ipctk's exact CCD (False: the project's narrow phase).
    """
    if scene_name not in scene_names():
        raise InputError(f"unknown scene {scene_name!r}; valid scenes: {', '.join(scene_names())}")
    if not checkpoints:
        raise InputError("the frontier needs at least one checkpoint")
    ipc_sequences = max_sequences if ipc_sequences is None else ipc_sequences
    if steps < 1 or max_sequences < 1 or threads < 1 or ipc_sequences < 1:
        raise InputError(f"steps, max_sequences, ipc_sequences and threads must be >= 1, got {steps}, "
                         f"{max_sequences}, {ipc_sequences}, {threads}")
    models = [load_model(c) for c in checkpoints]
    resolutions = {m.meta.resolution for m in models}
    for c, m in zip(checkpoints, models):
        if m.meta.scene != scene_name:
            raise InputError(f"{c}: checkpoint is for scene {m.meta.scene!r}, not {scene_name!r}")
    if len(resolutions) != 1:
        raise InputError(f"the checkpoints mix resolutions {sorted(resolutions)}")
    scene = load_scene(scene_name, resolutions.pop())
    files = test_files(data_dir, scene)[:max_sequences]
    truths = []
    for f in files:
        load_checked_sequence(f, scene)
        seq = load_sequence(f)
        if seq.frames < steps + 1:
            raise InputError(f"{f.name} has {seq.frames} frames; the frontier needs {steps + 1}")
        truths.append(_head(seq, steps + 1))
    out = ensure_writable_dir(out_dir)
    diagonal = scene.bbox_diagonal()
    torch.set_num_threads(threads)
    t_start = time.perf_counter()
    points = []
    for c, loaded in zip(checkpoints, models):
        if compile and hasattr(loaded.simulator, "compile_network"):
            loaded.simulator.compile_network()  # raw and corrected rollouts alike (the median skips compiling)
        for correction in (False, True):
            seqs, ms = [], []
            for t in truths:
                s = rollout(loaded, t.tool_poses, correction=correction, scene=scene,
                            initial_positions=t.object_positions[0],
                            predictor_options={"compile": compile, "interior": REALTIME_INTERIOR} if correction
                            else None)
                if correction:  # timed as the node runs it (no interior solve), scored with the elastic interior
                    s = dataclasses.replace(s, object_positions=elastic_interior(s.object_positions, loaded, scene))
                seqs.append(s)
                ms.extend(s.extra["step_ms"][1:].tolist())
            label = _label(loaded, c) + (" + correction" if correction else " raw")
            points.append(_point(label, "corrected" if correction else "raw", seqs, truths, ms, diagonal, exact))
            if progress:
                print(f"{label}: {points[-1]['ms_median']:.2f} ms/step, RMSE@{steps} {points[-1]['rmse_last']:.2e}",
                      flush=True)
    seqs, ms = [], []
    for t in truths:  # the trivial baseline every model must beat (the first checkpoint's graph and rest state)
        base = rest_baseline(models[0], scene)
        s = rollout(base, t.tool_poses, correction=True, scene=scene, initial_positions=t.object_positions[0],
                    predictor_options={"interior": REALTIME_INTERIOR})
        seqs.append(dataclasses.replace(s, object_positions=elastic_interior(s.object_positions, base, scene)))
        ms.extend(s.extra["step_ms"][1:].tolist())
    points.append(_point("rest + correction (no network)", "baseline", seqs, truths, ms, diagonal, exact))
    if ipc:
        for label, options in IPC_SETTINGS:
            seqs, ms = [], []
            for t in truths[:ipc_sequences]:
                s = simulate_sequence(scene, t.tool_poses, **options)
                seqs.append(s)
                ms.extend(s.extra["step_ms"][1:].tolist())
            points.append(_point(label, "ipc", seqs, truths[:ipc_sequences], ms, diagonal, exact))
            if progress:
                print(f"{label}: {points[-1]['ms_median']:.1f} ms/step, RMSE@{steps} {points[-1]['rmse_last']:.2e}",
                      flush=True)
    result = {
        "scene": scene.name, "resolution": scene.resolution, "steps": steps, "threads": threads,
        "compiled": bool(compile), "exact": bool(exact), "sequences": [f.name for f in files],
        "ipc_sequences": [f.name for f in files[:ipc_sequences]] if ipc else [],
        "cpu_count": os.cpu_count(), "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "points": points, "wall_s": time.perf_counter() - t_start,
    }
    return write_report(result, out, "frontier", "frontier.png", format_frontier, plot_frontier)


def _head(seq, frames: int):
    """The first ``frames`` frames of a Sequence (per-frame arrays cut, the rest kept)."""
    cut = {}
    for f in dataclasses.fields(seq):
        v = getattr(seq, f.name)
        if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == seq.frames and f.name not in (
                "object_faces", "tool_faces"):
            cut[f.name] = v[:frames]
    extra = {k: (v[:frames] if isinstance(v, np.ndarray) and v.shape[:1] == (seq.frames,) else v)
             for k, v in seq.extra.items()}
    return dataclasses.replace(seq, **cut, extra=extra)


def format_frontier(result: dict) -> str:
    """Markdown table of the frontier points, fastest first."""
    lines = [f"# Speed against error: {result['scene']} ({result['resolution']})", "",
             f"{len(result['sequences'])} test sequence(s), {result['steps']} steps, {result['threads']} torch "
             f"thread(s){', compiled' if result['compiled'] else ''}; crossings = N_vf + N_ee summed over the steps "
             f"({'ipctk exact CCD' if result['exact'] else 'narrow phase'})."
             + (f" Solver points on {len(result['ipc_sequences'])} of them ({', '.join(result['ipc_sequences'])})."
                if 0 < len(result.get("ipc_sequences", [])) < len(result["sequences"]) else ""), "",
             "Relative displacement error: ||X - X_gt|| / ||X_gt - X_rest|| over the steps (1.0 = no better than "
             "\"nothing moves\"; contact region: the 10% of vertices the ground truth moves most), mean over the "
             "sequences.", "",
             f"| method | ms/step (median) | relative error, all | relative error, contact | RMSE at step "
             f"{result['steps']} (% of bbox diagonal) | crossings | intersecting frames |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for p in sorted(result["points"], key=lambda p: p["ms_median"]):
        rel = (f"{p['relative']:.3f} | {p['relative_contact']:.3f}" if "relative" in p else "– | –")
        lines.append(f"| {p['label']} | {p['ms_median']:.2f} | {rel} | {100 * p['rmse_last']:.3f} ± "
                     f"{100 * p['rmse_last_std']:.3f} | {p['crossings']} | {p['intersecting_frames']} |")
    return "\n".join(lines) + "\n"


def _model_key(label: str) -> str:
    """A network point's model (its label without " raw" / " + correction"); other labels unchanged."""
    for suffix in (" raw", " + correction"):
        if label.endswith(suffix):
            return label[: -len(suffix)]
    return label


def plot_frontier(result: dict, path: Path) -> Path:
    """Log-x scatter of ms/step against the relative error (all vertices); written atomically as PNG. Each network
    is a number beside its two points (raw, corrected), keyed below the plot with its crossings: on a crowded
    frontier, names beside the points overlap."""
    import matplotlib  # lazy: matplotlib is heavy and only the plots need it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    style = {"raw": ("o", "tab:orange"), "corrected": ("s", "tab:blue"), "baseline": ("x", "tab:gray"),
             "ipc": ("^", "tab:green")}
    nets = [p for p in result["points"] if p["kind"] in ("raw", "corrected")]
    best = {}
    for p in nets:  # models ordered by their best error, the best first
        key = _model_key(p["label"])
        best[key] = min(best.get(key, np.inf), p["relative"])
    number = {key: k + 1 for k, key in enumerate(sorted(best, key=best.get))}
    key_height = 0.3 + 0.13 * len(number)  # inches: the key's rows below the plot
    fig, (ax, key_ax) = plt.subplots(2, 1, figsize=(7.5, 4.8 + key_height), dpi=110,
                                     gridspec_kw={"height_ratios": [4.8, key_height]})
    for kind, (marker, color) in style.items():
        pts = [p for p in result["points"] if p["kind"] == kind]
        if pts:
            ax.scatter([p["ms_median"] for p in pts], [p["relative"] for p in pts], marker=marker, color=color,
                       label={"raw": "GNN raw", "corrected": "GNN + correction", "baseline": "rest + correction",
                              "ipc": "IPC solver"}[kind])
        for p in pts:
            text = (str(number[_model_key(p["label"])]) if kind in ("raw", "corrected")
                    else f"{p['label']}\n{p['crossings']} crossings")
            ax.annotate(text, (p["ms_median"], p["relative"]), fontsize=6, xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("ms per step (median, log scale)")
    ax.axhline(1.0, color="tab:gray", lw=0.8, ls="--")  # "nothing moves"
    ax.set_ylabel("relative displacement error (1 = nothing moves)")
    ax.set_title(f"{result['scene']} ({result['resolution']}): speed against error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    crossings = {(_model_key(p["label"]), p["kind"]): p["crossings"] for p in nets}
    key_lines = [f"{k}  {key}: crossings raw {crossings.get((key, 'raw'), '-')}, corrected "
                 f"{crossings.get((key, 'corrected'), '-')}" for key, k in number.items()]
    key_ax.axis("off")
    key_ax.text(0.0, 1.0, "\n".join(key_lines), fontsize=6.5, family="monospace", va="top",
                transform=key_ax.transAxes)
    return save_png(fig, path)


def elastic_interior(positions: np.ndarray, loaded, scene) -> np.ndarray:
    """Mesh positions [T,N_mesh,3] with the interior vertices re-lifted elastically from the model's graph nodes (a
    rollout run with the node's free interpolation, so that its step times are the node's)."""
    template = loaded.simulator.template
    lift = interior_lift("elastic", scene, template, settled_rest(loaded, scene))
    return np.stack([lift(x[template.object_nodes]) for x in positions])
