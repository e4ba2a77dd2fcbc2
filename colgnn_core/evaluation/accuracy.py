"""``colgnn evaluate``: accuracy and collision metrics of a model on a dataset's held-out test sequences.

For every ``test_XXXX.npz`` of a dataset folder (``colgnn generate``), the model is rolled out on the
sequence's tool poses from its frame 0 (:func:`colgnn_core.runtime.rollout.rollout`), once per mode: ``raw`` (the
network alone) and ``corrected`` (through the Predictor's collision-aware correction). Reported
(docs/ARCHITECTURE.md, "Metrics"):

* rollout RMSE of the positions (all mesh vertices) as a fraction of the object's rest bounding-box diagonal
  (:func:`colgnn_core.evaluation.measure.rmse_fraction`) at steps 1, 10, 50 (where the sequences are long
  enough) and over all steps (per sequence the mean of steps 1..T-1), mean ± std over the test sequences, and
  the per-step curve;
* crossings over [t, t+1] (N_vf, d_vf mean/max, N_ee, d_ee mean/max) and penetrations per frame of the
  ground truth and of each rollout (:func:`colgnn_core.collision.metrics.sequence_metrics`, exact oracle
  unless ``exact=False``), pooled across sequences by :func:`colgnn_core.evaluation.measure.collision_aggregate`.

* the relative displacement error (all vertices and the contact region) next to the two trivial baselines, over
  all sequences and per sequence (with the ratio to ``rest + correction``);
* the surface's validity, object alone, every SURFACE_CHECK_EVERY-th frame (and the last) of the ground truth and
  of each rollout: frames that self-intersect (ipctk, exact) and frames with a flipped, collapsed or torn face
  (:class:`colgnn_core.collision.surface_validity.SurfaceValidity` against the settled rest).

Outputs in ``out_dir``: ``metrics.json`` (atomic), ``metrics.md`` (Markdown table), ``rmse_over_time.png``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from colgnn_core.collision.exact import self_intersects
from colgnn_core.collision.metrics import sequence_metrics
from colgnn_core.collision.surface_validity import SurfaceValidity
from colgnn_core.errors import InputError
from colgnn_core.evaluation.provenance import provenance_line
from colgnn_core.evaluation.measure import (collision_aggregate, contact_region, mean_std,
                                            relative_errors, rmse_fraction, stats, test_files)
from colgnn_core.evaluation.render import save_png
from colgnn_core.io import atomic_write, ensure_writable_dir, load_sequence
from colgnn_core.learn.data import load_checked_sequence
from colgnn_core.runtime.models import load_model, prior_baseline, rest_baseline
from colgnn_core.runtime.predictor import RECOMMENDED_REST_RELAXATION, self_contact_default
from colgnn_core.runtime.rollout import rollout
from colgnn_core.scenes import scene_names

MODES = ("raw", "corrected")
# Rows of the relative-displacement table: the model's modes, the model as the ROS node runs it (output caps from the
# training data and rest relaxation on), and the two trivial baselines a model must beat (a model with a physics
# prior also gets "prior_correction": its physics prior alone behind the correction).
RELATIVE_ROWS = ("raw", "corrected", "node", "rest", "rest_correction")
RELATIVE_LABELS = {"raw": "raw network", "corrected": "corrected (no caps, no rest relaxation)",
                   "node": "corrected, node defaults (caps + rest relaxation)", "rest": "rest (nothing moves)",
                   "rest_correction": "rest + correction (no network)",
                   "prior_correction": "physics prior + correction (no network)"}
RMSE_STEPS = (1, 10, 50)
SURFACE_CHECK_EVERY = 10  # frames between the object-alone validity checks (ipctk's check costs ~10-50 ms a frame)
ROW_LABELS = {"ground_truth": "ground truth", "raw": "raw network", "corrected": "corrected"}


def _rmse_summary(curves: list[np.ndarray]) -> dict:
    """RMSE at RMSE_STEPS and over all steps (mean ± std over sequences) plus the mean/std curve."""
    out: dict = {}
    for k in RMSE_STEPS:
        out[f"step_{k}"] = mean_std([c[k] for c in curves if len(c) > k])
    out["all"] = mean_std([float(c[1:].mean()) for c in curves if len(c) > 1])
    T = max(len(c) for c in curves)
    mean, std, n = [], [], []
    for t in range(T):
        v = [c[t] for c in curves if len(c) > t]
        mean.append(float(np.mean(v)))
        std.append(float(np.std(v)))
        n.append(len(v))
    out["curve"] = {"mean": mean, "std": std, "n": n}
    return out


def evaluate(scene_name: str, checkpoint=None, data_dir=None, out_dir="out/evaluate",
             correction_modes=MODES, exact: bool = True, max_sequences: int | None = None,
             progress: bool = True, command: str | None = None, self_contact: bool | None = None) -> dict:
    """Evaluate a model on the test sequences of ``data_dir`` and write the reports into ``out_dir``.

    Args:
        scene_name: the scene; ``checkpoint`` defaults to its shipped model (resolution: the checkpoint's).
        checkpoint: checkpoint path (or a LoadedCheckpoint).
        data_dir: dataset folder with ``test_XXXX.npz`` (and optionally ``manifest.json``) of this scene and
            resolution. Required (InputError naming ``--data`` when absent).
        out_dir: output folder (created).
        correction_modes: any of 'raw', 'corrected'.
        exact: exact CCD oracle for the crossings (False: the project's narrow phase).
        max_sequences: evaluate only the first N test sequences.
        self_contact: the Predictor's self-contact stage in every corrected rollout (the model's, the node's
            defaults and ``rest + correction``); None: the scene's default, as the node runs it.

    Returns:
        The content of ``metrics.json`` (with 'files': the paths written).
    """
    if scene_name not in scene_names():
        raise InputError(f"unknown scene {scene_name!r}; valid scenes: {', '.join(scene_names())}")
    modes = tuple(correction_modes)
    bad = [m for m in modes if m not in MODES]
    if bad or not modes or len(set(modes)) != len(modes):
        raise InputError(f"correction_modes must be distinct values of {MODES}, got {modes}")
    if max_sequences is not None and max_sequences < 1:
        raise InputError(f"max_sequences must be >= 1, got {max_sequences}")
    if data_dir is None:
        test_files(None, None)
    loaded = load_model(checkpoint if checkpoint is not None else scene_name)
    if loaded.meta.scene != scene_name:
        raise InputError(f"checkpoint is for scene {loaded.meta.scene!r}, not {scene_name!r}")
    scene = loaded.meta.load_scene()
    files = test_files(data_dir, scene)
    self_contact = self_contact_default(scene) if self_contact is None else bool(self_contact)
    options = {"self_contact": self_contact}
    if max_sequences is not None:
        files = files[:max_sequences]
    out = ensure_writable_dir(out_dir)
    diagonal = scene.bbox_diagonal()

    t_start = time.perf_counter()
    curves: dict[str, list[np.ndarray]] = {m: [] for m in modes}
    coll: dict[str, list[dict]] = {m: [] for m in ("ground_truth",) + modes}
    per_sequence = []
    for i, path in enumerate(files):
        load_checked_sequence(path, scene)  # InputError naming the file if it is not of this scene
        gt = load_sequence(path)
        rec: dict = {"file": path.name, "frames": int(gt.frames)}
        t0 = time.perf_counter()
        m = sequence_metrics(gt, exact=exact)
        coll["ground_truth"].append(m)
        validity = SurfaceValidity(gt.object_faces, gt.object_positions[0])
        rec["ground_truth"] = {"collisions": m["summary"], "metrics_s": time.perf_counter() - t0,
                               "surface": surface_checks(gt.object_positions, gt.object_faces, validity)}
        for mode in modes:
            t0 = time.perf_counter()
            seq = rollout(loaded, gt.tool_poses, correction=(mode == "corrected"), scene=scene,
                          initial_positions=gt.object_positions[0],
                          predictor_options=options if mode == "corrected" else None)
            t_roll = time.perf_counter() - t0
            finite = bool(np.isfinite(seq.object_positions).all())
            if not finite:
                raise InputError(f"{path.name}: the {mode} rollout is not finite")
            err = rmse_fraction(seq.object_positions, gt.object_positions, diagonal)
            curves[mode].append(err)
            t0 = time.perf_counter()
            m = sequence_metrics(seq, exact=exact)
            coll[mode].append(m)
            totals = {k: int(np.asarray(v).sum()) for k, v in seq.extra.items()
                      if k not in ("step_ms",) and not k.endswith("_ms") and np.asarray(v).dtype.kind in "iu"}
            rec[mode] = {"positions": seq.object_positions, "rmse": [float(e) for e in err],
                         "rmse_all": float(err[1:].mean()) if len(err) > 1 else 0.0,
                         "collisions": m["summary"], "extra_totals": totals,
                         "surface": surface_checks(seq.object_positions, gt.object_faces, validity),
                         "step_ms_median": stats(seq.extra["step_ms"][1:], empty=0.0)["median"],
                         "rollout_s": t_roll, "metrics_s": time.perf_counter() - t0}
        rec["relative"] = _relative_errors(loaded, scene, gt, {m: rec[m].pop("positions") for m in modes}, options)
        per_sequence.append(rec)
        if progress:
            parts = [f"{mode} RMSE all {rec[mode]['rmse_all']:.2e}, N_vf {rec[mode]['collisions']['N_vf_total']:.0f}"
                     for mode in modes]
            print(f"[{i + 1}/{len(files)}] {path.name}: " + "; ".join(parts), flush=True)

    relative = {row: {part: mean_std([r["relative"][row][part] for r in per_sequence])
                      for part in ("all", "contact")} for row in per_sequence[0]["relative"]}
    rows: dict = {"ground_truth": {"rmse": None, "collisions": collision_aggregate(coll["ground_truth"])}}
    for mode in modes:
        rows[mode] = {"rmse": _rmse_summary(curves[mode]), "collisions": collision_aggregate(coll[mode])}
    for key, row in rows.items():
        row["surface"] = {k: sum(r[key]["surface"][k] for r in per_sequence) for k in SURFACE_KEYS}
    result = {
        "scene": scene.name,
        "resolution": scene.resolution,
        "checkpoint": str(checkpoint) if checkpoint is not None else f"shipped:{scene_name}",
        "variant": loaded.meta.variant,
        "data_dir": str(data_dir),
        "exact": bool(exact),
        "modes": list(modes),
        "self_contact": self_contact,
        "sequences": [p.name for p in files],
        "frames": [int(r["frames"]) for r in per_sequence],
        "bbox_diagonal": float(diagonal),
        "rmse_steps": list(RMSE_STEPS),
        "rows": rows,
        "relative": relative,
        "per_sequence": per_sequence,
        "wall_s": time.perf_counter() - t_start,
    }
    if command is not None:  # the report names the command that measured it, the machine and its load
        result["provenance"] = provenance_line(command)
    return write_report(result, out, "metrics", "rmse_over_time.png", format_markdown, plot_rmse)


SURFACE_KEYS = ("checked_frames", "self_intersecting_frames", "invalid_face_frames", "frames",
                "invalid_face_frames_all")


def surface_checks(positions: np.ndarray, faces: np.ndarray, validity: SurfaceValidity,
                   every: int = SURFACE_CHECK_EVERY) -> dict[str, int]:
    """Object-alone validity of frames 0, ``every``, 2 ``every``, ... and the last of ``positions`` [T,N,3] (m):
    {'checked_frames', 'self_intersecting_frames' (ipctk, exact), 'invalid_face_frames' (a flipped, collapsed or
    torn face against ``validity``'s rest)}; and of every frame for the cheap validity test: {'frames',
    'invalid_face_frames_all'} (a run of defective frames between two checked ones counts in full)."""
    frames = sorted(set(range(0, len(positions), every)) | {len(positions) - 1})
    invalid = [bool(validity.invalid(x).any()) for x in positions]
    return {"checked_frames": len(frames),
            "self_intersecting_frames": int(sum(self_intersects(positions[t], faces) for t in frames)),
            "invalid_face_frames": int(sum(invalid[t] for t in frames)),
            "frames": len(positions), "invalid_face_frames_all": int(sum(invalid))}


def _relative_errors(loaded, scene, gt, positions: dict[str, np.ndarray],
                     options: dict | None = None) -> dict[str, dict[str, float]]:
    """Relative displacement error (all vertices, contact region) of one test sequence for every RELATIVE_ROWS row:
    the model's rollouts ``positions`` (mode -> [T,N,3]), the node's defaults and the two trivial baselines, each
    started from the ground truth's frame 0 (the settled rest). ``options``: more Predictor settings of every
    corrected rollout (the self-contact stage)."""
    options = options or {}
    truth = gt.object_positions
    rest = truth[0]
    runs = dict(positions)
    runs["node"] = rollout(loaded, gt.tool_poses, correction=True, scene=scene, initial_positions=rest, limits="data",
                           predictor_options={"rest_relaxation": RECOMMENDED_REST_RELAXATION, **options}
                           ).object_positions
    runs["rest"] = np.repeat(rest[None], len(truth), axis=0)
    runs["rest_correction"] = rollout(rest_baseline(loaded, scene), gt.tool_poses, correction=True, scene=scene,
                                      initial_positions=rest, predictor_options=options).object_positions
    if getattr(loaded.simulator.config, "prior_kind", None):  # what the network adds over its physics prior
        runs["prior_correction"] = rollout(prior_baseline(loaded, scene), gt.tool_poses, correction=True, scene=scene,
                                           initial_positions=rest, predictor_options=options).object_positions
    ids = contact_region(truth, rest)
    return {row: relative_errors(p, truth, ids) for row, p in runs.items()}


def write_report(result: dict, out: Path, stem: str, plot_name: str, markdown, plot) -> dict:
    """Write ``<stem>.md``, the plot and ``<stem>.json`` (last, atomically each) into ``out``; adds
    ``result['files']`` and returns ``result``."""
    files = {"json": out / f"{stem}.json", "markdown": out / f"{stem}.md", "plot": out / plot_name}
    result["files"] = {k: str(v) for k, v in files.items()}
    with atomic_write(files["markdown"], "w") as fh:
        fh.write(markdown(result))
    plot(result, files["plot"])
    with atomic_write(files["json"], "w") as fh:
        json.dump(result, fh, indent=1)
    return result


def _fmt_rmse(s: dict | None) -> str:
    if s is None or s["mean"] is None:
        return "–"
    return f"{100 * s['mean']:.3g} ± {100 * s['std']:.2g}"


def format_markdown(result: dict) -> str:
    """The Markdown report of :func:`evaluate` (RMSE in % of the bbox diagonal, depths in mm)."""
    lines = [f"# colgnn evaluate: {result['scene']} ({result['resolution']})", "",
             *([result["provenance"], ""] if result.get("provenance") else []),
             f"Checkpoint `{result['checkpoint']}` (variant {result['variant']}), "
             f"{len(result['sequences'])} test sequence(s) from `{result['data_dir']}` "
             f"({min(result['frames'])}–{max(result['frames'])} frames), bbox diagonal "
             f"{result['bbox_diagonal']:.4f} m, {'exact CCD oracle' if result['exact'] else 'narrow-phase CCD'}, "
             f"self-contact stage {'on' if result.get('self_contact') else 'off'} in the corrected rollouts.", "",
             "RMSE: % of the bbox diagonal, mean ± std over sequences. N_vf, N_ee: crossings per step; "
             "d: depth on the wrong side at t+1 (mm), mean over all crossing pairs and max. "
             "Intersecting frames: frames with any penetration.", ""]
    head = ["row"] + [f"RMSE@{k} (%)" for k in result["rmse_steps"]] + ["RMSE all (%)", "N_vf", "d_vf mean", "d_vf max",
                                                                        "N_ee", "d_ee mean", "d_ee max",
                                                                        "intersecting frames"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|")
    for key, row in result["rows"].items():
        r, c = row["rmse"], row["collisions"]
        cells = [ROW_LABELS.get(key, key)]
        if r is None:  # ground truth against itself: 0 at every step the sequences reach
            cells += ["0" if max(result["frames"]) > k else "–" for k in result["rmse_steps"]] + ["0"]
        else:
            cells += [_fmt_rmse(r[f"step_{k}"]) for k in result["rmse_steps"]] + [_fmt_rmse(r["all"])]
        for kind in ("vf", "ee"):
            cells += [f"{c[f'N_{kind}']:.2f}", f"{1e3 * c[f'd_{kind}_mean']:.3f}", f"{1e3 * c[f'd_{kind}_max']:.3f}"]
        cells.append(f"{c['intersecting_frames']}/{c['frames']}")
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(format_relative(result["relative"]) + [""] + format_relative_per_sequence(result) + [""]
                     + lines + format_surface(result))


def format_relative_per_sequence(result: dict) -> list[str]:
    """Per test sequence: the corrected model's relative error next to ``rest + correction``, and their ratio (a
    model that is done scores at most 0.5 on every sequence)."""
    per = result.get("per_sequence") or []
    if not per or "corrected" not in per[0]["relative"]:
        return []
    lines = ["Per sequence (corrected model against `rest + correction`; ratio: all vertices).", "",
             "| sequence | frames | corrected, all | corrected, contact | rest + correction, all | "
             "rest + correction, contact | ratio |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in per:
        c, b = r["relative"]["corrected"], r["relative"]["rest_correction"]
        ratio = c["all"] / b["all"] if b["all"] > 0 else float("inf")
        lines.append(f"| {r['file']} | {r['frames']} | {c['all']:.3f} | {c['contact']:.3f} | {b['all']:.3f} | "
                     f"{b['contact']:.3f} | {ratio:.2f} |")
    return lines


def format_surface(result: dict) -> list[str]:
    """The object-alone validity table (every SURFACE_CHECK_EVERY-th frame and the last of each sequence)."""
    rows = {k: r["surface"] for k, r in result["rows"].items() if "surface" in r}
    if not rows:
        return []
    lines = ["", f"Surface validity, object alone (every {SURFACE_CHECK_EVERY}th frame and the last): frames that "
             "intersect themselves (ipctk, exact) and frames with a flipped, collapsed or torn face; the last column "
             "tests every frame for such a face.", "",
             "| row | self-intersecting frames | frames with invalid faces | every frame: invalid faces |",
             "|---|---:|---:|---:|"]
    for key, s in rows.items():
        every = (f"{s['invalid_face_frames_all']}/{s['frames']}" if s.get("frames") else "–")  # older reports
        lines.append(f"| {ROW_LABELS.get(key, key)} | {s['self_intersecting_frames']}/{s['checked_frames']} | "
                     f"{s['invalid_face_frames']}/{s['checked_frames']} | {every} |")
    return lines + [""]


def format_relative(relative: dict) -> list[str]:
    """The relative-displacement table (mean ± std over sequences) as Markdown lines, trivial baselines included."""
    lines = ["Relative displacement error ||X - X_gt|| / ||X_gt - X_rest|| over frames 1.. (1.0 = no better than "
             "\"nothing moves\"; contact region: the 10% of vertices the ground truth moves most), mean ± std over "
             "the test sequences. Lower is better.", "",
             "| row | all vertices | contact region |", "|---|---:|---:|"]
    for key, row in relative.items():
        cells = [f"{row[p]['mean']:.3f} ± {row[p]['std']:.3f}" for p in ("all", "contact")]
        lines.append(f"| {RELATIVE_LABELS.get(key, key)} | " + " | ".join(cells) + " |")
    return lines


def plot_curves(curves: dict[str, tuple], title: str, path: Path, dashed: tuple[str, ...] = ()) -> Path:
    """RMSE over time as a PNG: ``curves`` maps a label to (mean [T], std [T] or None), fractions of the bbox
    diagonal (plotted in %, with a ±std band where given); labels in ``dashed`` are drawn dashed."""
    import matplotlib  # lazy: matplotlib is heavy and only the plots need it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    for label, (mean, std) in curves.items():
        mean = 100 * np.asarray(mean)
        t = np.arange(len(mean))
        ax.plot(t, mean, label=label, linestyle="--" if label in dashed else "-")
        if std is not None:
            std = 100 * np.asarray(std)
            ax.fill_between(t, mean - std, mean + std, alpha=0.25)
    ax.set_xlabel("step")
    ax.set_ylabel("RMSE (% of bbox diagonal)")
    ax.set_title(title)
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return save_png(fig, path)


def plot_rmse(result: dict, path: Path) -> Path:
    """RMSE over time (mean ± std band over sequences) per mode, as a PNG (matplotlib, Agg)."""
    curves = {ROW_LABELS.get(m, m): (result["rows"][m]["rmse"]["curve"]["mean"],
                                     result["rows"][m]["rmse"]["curve"]["std"])
              for m in result["modes"]}
    return plot_curves(curves, f"{result['scene']} ({result['resolution']}): rollout error, "
                       f"{len(result['sequences'])} test sequence(s)", path, dashed=(ROW_LABELS["corrected"],))
