"""``colgnn evaluate --all`` (``make results``): the results report ``docs/RESULTS.md``, end to end.

For every scene with a shipped model (``<scene>.pt``, the scene's default: what the node and ``colgnn rollout``
run) the report is rebuilt from scratch on this machine. The paper's variants are ``<scene>_<variant>.pt`` in the
same folder, each used where it exists; where the shipped model is itself the paper's full variant (and there is no
``<scene>_full.pt``), it fills that slot and the report has no separate "shipped" rows (:func:`model_paths`):

1. **Test data**: ``test_sequences`` held-out family trajectories of ``frames`` frames simulated by the project's
   IPC solver (``colgnn generate --split test``; resumable, so a re-run reuses finished sequences). Their
   per-step solver times are the IPC column of Table 1: the solver on the same poses the models are timed on.
2. **Speed** (Table 1): the Predictor with the shipped model (``threads`` torch threads, optionally
   ``torch.compile``) over the first test sequence; "raw network" is the step without the correction stage
   (everything else the step does is included), "with correction" is the whole published step.
3. **Collisions and accuracy** (Table 2, accuracy table, error-over-time plot):
   :func:`colgnn_core.evaluation.accuracy.evaluate` of every variant (raw), plus the full and the shipped model
   through the correction (the shipped one also as the node runs it), with the exact ipctk oracle.
4. **Hard cases**: :func:`colgnn_core.evaluation.stability.hard_cases` through the Predictor, each frame and step
   checked by ipctk (:func:`colgnn_core.evaluation.stability.check_rollout`).
5. **Speed against error**: :func:`colgnn_core.evaluation.frontier.frontier` where frontier checkpoints are shipped
   (``frontier/<scene>/*.pt`` beside the models).
6. **Pictures**: ground truth / baseline / colgnn strips at the same frames (penetrating vertices red), and the
   ablation strip (full vs no-compact, raw networks).

Everything measured goes into a :class:`~colgnn_core.evaluation.report_data.ResultsReport`, saved as
``results.json``; ``RESULTS.md`` is written from it (:mod:`.report_markdown`), with the paper's figures beside
ours. Nothing in the report comes from an earlier run except resumed test-data sequences (said in the header).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from datetime import datetime, timezone
from pathlib import Path


from colgnn_core.errors import InputError, SimulationError
from colgnn_core.evaluation.accuracy import evaluate, plot_curves
from colgnn_core.evaluation.frontier import frontier, model_size
from colgnn_core.evaluation.measure import stats, test_files
from colgnn_core.evaluation.render import render_strip
from colgnn_core.evaluation.report_data import (RELATIVE_ROWS, ROWS, FrontierResult, FrontierSection, HardCase,
                                                MeanStd, Pictures, ResultsReport, Row, SceneResults, Settings,
                                                SkippedScene, SpeedRow, Stat)
from colgnn_core.evaluation.report_markdown import format_results
from colgnn_core.evaluation.speed import timed_rollout
from colgnn_core.evaluation.stability import check_rollout, hard_cases
from colgnn_core.io import atomic_write, ensure_writable_dir, load_sequence
from colgnn_core.runtime.models import MODEL_DIR, load_model
from colgnn_core.runtime.predictor import REALTIME_INTERIOR, RECOMMENDED_REST_RELAXATION, Predictor
from colgnn_core.runtime.rollout import rollout
from colgnn_core.scenes import load_scene, scene_names
from colgnn_core.sim.dataset import generate_dataset, simulate_sequence
from colgnn_core.evaluation.provenance import code_version, machine

PAPER_VARIANTS = ("subspace", "baseline", "no-compact", "full")
SHIPPED = "shipped"  # the report slot of a scene's default model when it is not the paper's full variant
PICTURE_DPI = 60  # the committed strips stay small (~100-150 KB each)


def model_paths(models_dir: Path, scene_name: str) -> dict[str, Path]:
    """The checkpoints of a scene by report slot, only those that exist: the paper's variants
    (``<scene>_<variant>.pt``) and :data:`SHIPPED`, the scene's default model ``<scene>.pt``. A default model that
    is the paper's full variant fills the ``full`` slot instead, unless ``<scene>_full.pt`` exists."""
    models_dir = Path(models_dir)
    out = {v: models_dir / f"{scene_name}_{v}.pt" for v in PAPER_VARIANTS}
    out = {v: p for v, p in out.items() if p.is_file()}
    default = models_dir / f"{scene_name}.pt"
    if default.is_file():
        if "full" not in out and load_model(default).meta.variant == "full":
            out["full"] = default
        else:
            out[SHIPPED] = default
    return out


def shipped_slot(ckpts: dict[str, Path]) -> str:
    """The report slot that holds the scene's default model (:func:`model_paths`)."""
    return SHIPPED if SHIPPED in ckpts else "full"


def test_data(scene, out_dir: Path, sequences: int, frames: int, jobs: int, progress: bool) -> tuple[Path, int, str]:
    """Simulate (or resume) the scene's test sequences.

    Returns the folder, how many sequences were already there, and the solver's failure message ('' if none): a
    sequence the solver cannot verify (after its spare seeds) is left out, as in training data, and the report
    says so; with no sequence at all the SimulationError propagates.
    """
    already = len(list(Path(out_dir).glob("test_*.npz"))) if Path(out_dir).is_dir() else 0
    failed = ""
    try:
        generate_dataset(scene.name, scene.resolution, out_dir, sequences=sequences, frames=frames, jobs=jobs,
                         split="test", progress=progress)
    except SimulationError as exc:
        if not list(Path(out_dir).glob("test_*.npz")):
            raise
        failed = str(exc)
    return Path(out_dir), already, failed


def speed(loaded, scene, data_dir: Path, threads: int, compile: bool) -> SpeedRow:
    """Table 1 row: the Predictor and the solver timed on the same poses (the first test sequence), one after
    the other in this run, so that both see the same machine (the data's own solver times may come from a
    shared machine)."""
    first = load_sequence(test_files(data_dir, scene)[0])
    pred = Predictor(loaded, scene, correction=True, threads=threads, compile=compile, interior=REALTIME_INTERIOR)
    timed = timed_rollout(pred, first.tool_poses, first.object_positions[0])
    load = os.getloadavg()[0]
    st = timed["stages"]
    raw = [t - c for t, c in zip(st["total"], st["correction"])]
    ipc = Stat(**stats(simulate_sequence(scene, first.tool_poses).extra["step_ms"][1:]))
    total = Stat(**stats(st["total"]))
    return SpeedRow(vertices=int(len(scene.object.vertices)), surface_vertices=int(len(scene.object.surface_vertices)),
                    edges=int(len(scene.object.edges)), faces=int(len(scene.object.faces)),
                    ipc_ms=ipc, raw_ms=Stat(**stats(raw)), total_ms=total, graph_ms=Stat(**stats(st["graph"])),
                    gnn_ms=Stat(**stats(st["gnn"])), correction_ms=Stat(**stats(st["correction"])),
                    speedup_vs_ipc=ipc.median / total.median, steps=len(st["total"]), load_average_1min=load,
                    ipc_load_average_1min=os.getloadavg()[0], threads=pred.threads, compiled=pred.compiled)


def hard_case_report(loaded, scene, frames: int, random_steps: int, threads: int,
                     progress: bool) -> dict[str, HardCase]:
    """Each hard case of :func:`colgnn_core.evaluation.stability.hard_cases` through the Predictor, checked by
    ipctk."""
    pred = Predictor.from_checkpoint(loaded, scene=scene, threads=threads, limits="data",
                                     rest_relaxation=RECOMMENDED_REST_RELAXATION)
    out = {}
    for name, poses in hard_cases(scene, frames, random_steps, step=pred.max_translation).items():
        t0 = time.perf_counter()
        try:
            case = HardCase(**check_rollout(pred, poses), finite=True)
        except InputError as e:  # a non-finite frame: reported, not hidden
            case = HardCase(finite=False, error=str(e))
        case.wall_s = time.perf_counter() - t0
        out[name] = case
        if progress:
            print(f"  hard case {name!r}: {case.to_dict()}", flush=True)
    return out


def pictures(evals_ckpts: dict, scene, data_dir: Path, img_dir: Path, errors: Path, count: int = 5) -> Pictures:
    """The comparison strip (ground truth / baseline / colgnn) and the ablation strip (full vs no-compact)."""
    gt = load_sequence(test_files(data_dir, scene)[0])
    x0 = gt.object_positions[0]
    run = {}
    for key, (variant, corrected) in {"baseline": ("baseline", False), "colgnn": (shipped_slot(evals_ckpts), True),
                                      "full": ("full", False), "no-compact": ("no-compact", False)}.items():
        if variant in evals_ckpts:
            run[key] = rollout(evals_ckpts[variant], gt.tool_poses, correction=corrected, scene=scene,
                               initial_positions=x0)
    seqs, labels = [gt], ["ground truth"]
    for key, label in (("baseline", "baseline"), ("colgnn", "colgnn")):
        if key in run:
            seqs.append(run[key])
            labels.append(label)
    comparison = render_strip(seqs, labels, img_dir / f"{scene.name}_comparison.png", count=count, dpi=PICTURE_DPI)
    ablation = None
    if "no-compact" in run and "full" in run:
        ablation = str(render_strip([run["full"], run["no-compact"]], ["full", "no-compact"],
                                    img_dir / f"{scene.name}_ablation.png", count=count, dpi=PICTURE_DPI))
    return Pictures(errors=str(errors), comparison=str(comparison), ablation=ablation)


def plot_errors(scene_name: str, rows: dict[str, Row], path: Path) -> Path:
    """RMSE over time of every row (mean over the test sequences), one PNG."""
    labels = dict(ROWS)
    return plot_curves({labels[k]: (rows[k].rmse.curve.mean, None) for k, _ in ROWS
                        if k in rows and rows[k].rmse is not None},
                       f"{scene_name}: rollout error on the test sequences", path,
                       dashed=(labels["full+correction"],))


def accuracy_rows(scene_name: str, ckpts: dict[str, Path], data_dir: Path, out: Path, progress: bool
                  ) -> tuple[dict[str, Row], dict[str, dict[str, MeanStd]], list[str], list[int]]:
    """(rows in ROWS order, relative displacement errors in RELATIVE_ROWS order, test sequence names, their frame
    counts): every slot evaluated raw, the full and the shipped model also through the correction, the shipped
    one also as the node runs it, next to the two trivial baselines; the per-model reports go to
    ``out/results/<scene>/<slot>``."""
    rows: dict[str, Row] = {}
    relative: dict[str, dict] = {}
    sequences: list[str] | None = None
    frames: list[int] | None = None
    shipped = shipped_slot(ckpts)
    for variant, path in ckpts.items():
        modes = ("raw", "corrected") if variant in ("full", shipped) else ("raw",)
        e = evaluate(scene_name, checkpoint=path, data_dir=data_dir, out_dir=out / "results" / scene_name / variant,
                     correction_modes=modes, progress=progress)
        rows.setdefault("ground_truth", Row.from_dict(e["rows"]["ground_truth"]))  # rmse None: the reference
        rows[variant] = Row.from_dict(e["rows"]["raw"])
        relative[variant] = e["relative"]["raw"]
        if "corrected" in modes:
            rows[f"{variant}+correction"] = Row.from_dict(e["rows"]["corrected"])
            relative[f"{variant}+correction"] = e["relative"]["corrected"]
        if variant == shipped:
            relative.update({"node": e["relative"]["node"], "rest": e["relative"]["rest"],
                             "rest+correction": e["relative"]["rest_correction"]})
        sequences = sequences if sequences is not None else e["sequences"]
        frames = frames if frames is not None else e["frames"]
    rel = {k: {part: MeanStd.from_dict(relative[k][part]) for part in ("all", "contact")}
           for k, _ in RELATIVE_ROWS if k in relative}
    return {k: rows[k] for k, _ in ROWS if k in rows}, rel, sequences, frames


def frontier_section(scene_name: str, ckpts: dict[str, Path], models_dir: Path, data_dir: Path, out: Path,
                     steps: int, test_sequences: int, threads: int, compile: bool,
                     progress: bool) -> FrontierSection | None:
    """The speed/error frontier of the shipped frontier checkpoints (``frontier/<scene>/*.pt`` beside the models)
    with the scene's shipped, full and baseline models; None when none are shipped."""
    front = sorted((models_dir / "frontier" / scene_name).glob("*.pt"))
    if not front:
        return None
    f = frontier(scene_name, [str(p) for p in front] + [str(ckpts[k]) for k in (SHIPPED, "full", "baseline")
                                                          if k in ckpts], data_dir,
                 out / "results" / scene_name / "frontier", steps=steps, max_sequences=test_sequences,
                 ipc_sequences=1, threads=threads, compile=compile, progress=progress)
    img = out / "img" / f"{scene_name}_frontier.png"
    shutil.copyfile(f["files"]["plot"], img)
    return FrontierSection(result=FrontierResult.from_dict({k: v for k, v in f.items() if k != "per_sequence"}),
                           plot=str(img))


def scene_results(scene_name: str, out: Path, data_root: Path, models_dir: Path, *, test_sequences: int,
                  frames: int, jobs: int, threads: int, compile: bool, hard_frames: int, random_steps: int,
                  progress: bool) -> SceneResults | SkippedScene:
    """Everything the report says about one scene (see the module docstring)."""
    default = models_dir / f"{scene_name}.pt"
    if not default.is_file():  # a `<scene>_full.pt` alone is a comparison model, not what the scene ships
        return SkippedScene(scene_name, f"no shipped model ({default})")
    ckpts = model_paths(models_dir, scene_name)
    loaded = load_model(default)
    scene = load_scene(scene_name, loaded.meta.resolution)
    t0 = time.perf_counter()
    data_dir, resumed, failed = test_data(scene, data_root / scene_name, test_sequences, frames, jobs, progress)
    model_sizes = {v: model_size(load_model(p)) for v, p in ckpts.items()}
    test_data_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    speed_row = speed(loaded, scene, data_dir, threads, compile)
    speed_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    rows, relative, sequences, seq_frames = accuracy_rows(scene_name, ckpts, data_dir, out, progress)
    evaluate_s = time.perf_counter() - t0
    img = ensure_writable_dir(out / "img")
    errors = plot_errors(scene_name, rows, img / f"{scene_name}_rmse.png")
    pics = pictures(ckpts, scene, data_dir, img, errors)
    t0 = time.perf_counter()
    hard = hard_case_report(loaded, scene, hard_frames, random_steps, threads, progress)
    hard_s = time.perf_counter() - t0
    # The whole test sequences: the relative error needs their contact, and the bunny's first one touches only from
    # frame 40 (a 40-step window scored every bunny model at 4.7-6.3, "rest + correction" at 4.3; session 50).
    front = frontier_section(scene_name, ckpts, models_dir, data_dir, out, min(seq_frames) - 1,
                             test_sequences, threads, compile, progress)
    return SceneResults(scene=scene_name, resolution=scene.resolution, data_dir=str(data_dir),
                        resumed_sequences=resumed, solver_failures=failed,
                        checkpoints={v: str(p) for v, p in ckpts.items()}, model_sizes=model_sizes,
                        test_data_s=test_data_s, speed=speed_row, speed_s=speed_s, sequences=sequences,
                        frames=seq_frames, evaluate_s=evaluate_s, rows=rows, pictures=pics, hard_cases=hard,
                        hard_cases_s=hard_s, frontier=front, relative=relative)


def results(out_dir="docs", *, scenes=None, data_root="data/results", models_dir=None, test_sequences: int = 2,
            frames: int = 51, jobs: int = 2, threads: int = 2, compile: bool = True, hard_frames: int = 40,
            random_steps: int = 2000, progress: bool = True) -> ResultsReport:
    """Rebuild ``<out_dir>/RESULTS.md``, ``results.json`` and the pictures in ``<out_dir>/img``.

    Args:
        scenes: scene names (default: all).
        data_root: where the test data is simulated (``<data_root>/<scene>``; resumable).
        models_dir: shipped checkpoints (default: the package's ``assets/models``).
        test_sequences, frames: test data size (frames ≥ 51 gives RMSE at step 50).
        jobs: solver processes for the test data.
        threads, compile: the Predictor's torch threads and torch.compile for the timings.
        hard_frames, random_steps: length of the short hard cases and of the random motion with tilts.

    Returns:
        The report, with ``files`` (the Markdown and JSON paths) set.
    """
    names = list(scenes) if scenes else list(scene_names())
    unknown = [n for n in names if n not in scene_names()]
    if unknown:
        raise InputError(f"unknown scene(s) {unknown}; valid scenes: {', '.join(scene_names())}")
    if test_sequences < 1 or frames < 3:
        raise InputError(f"need test_sequences >= 1 and frames >= 3, got {test_sequences} and {frames}")
    out = ensure_writable_dir(out_dir)
    models = Path(models_dir) if models_dir is not None else MODEL_DIR
    t_start = time.perf_counter()
    report = ResultsReport(generated=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), machine=machine(),
                           settings=Settings(test_sequences=test_sequences, frames=frames, threads=threads,
                                             compile=compile, hard_frames=hard_frames, random_steps=random_steps),
                           scenes={}, code=code_version())
    for name in names:
        if progress:
            print(f"== {name}", flush=True)
        report.scenes[name] = scene_results(name, out, Path(data_root), models, test_sequences=test_sequences,
                                            frames=frames, jobs=jobs, threads=threads, compile=compile,
                                            hard_frames=hard_frames, random_steps=random_steps, progress=progress)
    report.wall_s = time.perf_counter() - t_start
    with atomic_write(out / "results.json", "w") as fh:
        json.dump(report.to_dict(), fh, indent=1)
    with atomic_write(out / "RESULTS.md", "w") as fh:
        fh.write(format_results(report, out))
    report.files = {"markdown": str(out / "RESULTS.md"), "json": str(out / "results.json")}
    return report
