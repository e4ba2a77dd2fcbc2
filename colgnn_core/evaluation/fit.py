"""``colgnn fit NAME``: ground truth -> training -> held-out evaluation of a scene, in one resumable run inside a
time budget.

The budget (``minutes``) is split and the split is printed and recorded (``plan.json``, the report): first 50% for
simulating ground truth, 35% for training, 15% for the evaluation (held-out accuracy against the trivial baselines,
collisions, speed, the picture). Once the first sequences have been simulated, their measured cost re-plans the
rest: the evaluation gets what it is estimated to need (at least 15%), and what is left goes 55:45 to more data
and to training. Within that:

* **data**: the held-out test sequences and one training sequence per worker first; their measured cost sets how
  many more training sequences fit in the rest of the data share (at most ``MAX_TRAIN_SEQUENCES``); when those run
  faster, whole rounds more are simulated while the share lasts (:func:`top_up_sequences`). Sequences are
  simulated by local processes (``jobs``) or on a Dask cluster (``dask``, :mod:`colgnn_core.sim.cluster`);
* **training**: it also takes what the data left unused (:func:`training_share`); a few steps of a throw-away
  run measure the step rate; the real run is planned to end within the training share (its learning-rate schedule
  fits that length), with the share as a hard stop too;
* **evaluation**: :func:`colgnn_core.evaluation.accuracy.evaluate` on the held-out sequences and
  :func:`colgnn_core.evaluation.speed.bench` on one family trajectory.

Everything goes under ``<scene folder>/<NAME>-fit/<resolution>/`` (``data/``, ``train.pt``, ``eval/``,
``plan.json``); the results beside the scene's TOML: ``<NAME>.pt`` (the scene's default model, without training
state), ``<NAME>-report.md`` and ``<NAME>-fit.png``. Run it again after an interruption: finished sequences are
kept, training resumes from its last checkpoint (same plan), a finished stage is not repeated.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from colgnn_core.errors import InputError, SimulationError
from colgnn_core.evaluation.accuracy import evaluate, format_relative
from colgnn_core.evaluation.provenance import provenance_line
from colgnn_core.evaluation.render import render_strip
from colgnn_core.evaluation.speed import bench
from colgnn_core.io import atomic_write, ensure_writable_dir, load_sequence
from colgnn_core.learn.checkpoint import strip_training_state
from colgnn_core.learn.data import read_manifest
from colgnn_core.learn.registry import load_checkpoint
from colgnn_core.learn.train import TrainConfig, train
from colgnn_core.runtime.threads import auto_threads
from colgnn_core.runtime.rollout import rollout
from colgnn_core.scenes import RESOLUTIONS, is_custom, load_scene, scene_file
from colgnn_core.sim.cluster import check_workers
from colgnn_core.sim.dataset import generate_dataset

SHARES = {"data": 0.50, "train": 0.35, "evaluate": 0.15}
DATA_FRACTION_AFTER_PROBE = 0.55   # of what is left once the evaluation is provided for
BENCH_FRAMES = 12
MODEL_STEP_S = 0.05                # a ci model step with the correction, generous on a shared 2-core machine (the
                                   # evaluation's 8 passes over a held-out frame took 0.1-0.15 s at ci in session 58)
MAX_TEST_SEQUENCES = 16
HELD_OUT_DATA_FRACTION = 0.1       # of the data's share, at most, for held-out sequences beyond the first ones
MAX_TRAIN_SEQUENCES = 200
CALIBRATION_STEPS = 45
CALIBRATION_WARM_STEPS = 15        # left out of the measured rate: the first steps run slower (allocation, caches)
MIN_TRAIN_STEPS = 30
MIN_MINUTES = 1.0


def rounded_shares(seconds: dict[str, float], total: float, rest: str = "train") -> dict[str, float]:
    """``seconds`` (stage -> s) in 0.1 s steps, with stage ``rest`` taking what the others leave of ``total`` (s), so
    that the shares add up to ``total`` instead of exceeding it by the rounding (each rounded apart: up to 0.1 s)."""
    out = {k: round(v, 1) + 0.0 for k, v in seconds.items() if k != rest}  # + 0.0: never a printed "-0.0"
    out[rest] = round(total - sum(out.values()), 1) + 0.0
    return {k: out[k] for k in seconds}


@dataclass
class FitPlan:
    """The run's choices, recorded in ``plan.json`` (a resumed run with the same budget keeps them)."""

    minutes: float
    shares_s: dict[str, float]
    frames: int
    test_sequences: int
    train_sequences: int | None = None   # set once the first sequences have been timed
    train_steps: int | None = None       # set once the step rate has been measured
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def plan_budget(minutes: float) -> FitPlan:
    """The split of ``minutes`` between data, training and evaluation, and the sequence length / test count."""
    if not (np.isfinite(minutes) and minutes >= MIN_MINUTES):
        raise InputError(f"--minutes must be at least {MIN_MINUTES:g}, got {minutes}")
    total = 60.0 * float(minutes)
    shares = rounded_shares({k: f * total for k, f in SHARES.items()}, total)
    small = minutes < 10
    return FitPlan(minutes=float(minutes), shares_s=shares, frames=24 if small else 40,
                   test_sequences=1 if small else 3)


class _Progress:
    """One progress display for the whole run: a bar over the time budget, the stage and its detail."""

    def __init__(self, name: str, total_s: float, enabled: bool):
        self.t0 = time.perf_counter()
        self.total = total_s
        self.bar = None
        self.stage = ""
        self.detail = ""
        self.used: dict[str, float] = {}  # stage -> wall seconds spent on it in this run
        self._since = self.t0
        self._stop = threading.Event()
        if enabled:
            from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

            self.bar = tqdm(total=int(round(total_s)), desc=f"fit {name}", unit="s", dynamic_ncols=True,
                            bar_format="{desc} {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s budget {postfix}")
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            self.refresh()

    def refresh(self) -> None:
        if self.bar is not None:
            self.bar.n = min(self.elapsed(), self.total)
            self.bar.set_postfix_str(f"{self.stage}: {self.detail}" if self.detail else self.stage, refresh=False)
            self.bar.refresh()

    def set(self, stage: str, detail: str = "") -> None:
        now = time.perf_counter()
        if self.stage:
            self.used[self.stage] = self.used.get(self.stage, 0.0) + now - self._since
        self._since = now
        self.stage, self.detail = stage, detail
        self.refresh()

    def stage_walls(self) -> dict[str, float]:
        """Wall seconds per stage in this run so far, the current stage's included."""
        walls = dict(self.used)
        if self.stage:
            walls[self.stage] = walls.get(self.stage, 0.0) + time.perf_counter() - self._since
        return walls

    def note(self, detail: str) -> None:
        self.detail = detail
        self.refresh()

    def close(self) -> None:
        self._stop.set()
        if self.bar is not None:
            self.refresh()
            self.bar.close()


def _say(progress: _Progress, text: str, quiet: bool) -> None:
    if quiet:
        return
    if progress.bar is not None:
        progress.bar.write(text)
    else:
        print(text, flush=True)


def _write_json(path: Path, data: dict) -> None:
    with atomic_write(path, "w") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


def _load_plan(path: Path, fresh: FitPlan) -> FitPlan:
    """The recorded plan if it was made for the same budget, else ``fresh``."""
    if not path.is_file():
        return fresh
    try:
        data = json.loads(path.read_text())
        plan = FitPlan(**data)
    except (OSError, ValueError, TypeError):
        return fresh
    return plan if plan.minutes == fresh.minutes else fresh


def start_plan(work: Path, minutes: float, ckpt: Path) -> tuple[FitPlan, bool]:
    """The run's plan: the recorded one for the same budget (a resumed run), else a fresh one. With a different
    budget than the recorded one, the trained ``ckpt`` is removed: the new plan can add data and sets another step
    count and learning-rate schedule, so resuming the old model would train neither plan. Returns (plan, whether a
    recorded plan for another budget was replaced)."""
    path = work / "plan.json"
    fresh = plan_budget(minutes)
    plan = _load_plan(path, fresh)
    rebudgeted = plan is fresh and path.is_file()
    if rebudgeted:
        ckpt.unlink(missing_ok=True)
    return plan, rebudgeted


@dataclass
class FitResult:
    name: str
    resolution: str
    model: Path
    report: Path
    picture: Path
    plan: FitPlan
    metrics: dict
    speed: dict
    wall_s: float


def fit(name: str, resolution: str = "ci", minutes: float = 30.0, jobs: int = 1, dask: str | None = None,
        progress: bool = True, invocation: str | None = None) -> FitResult:
    """Generate -> train -> evaluate scene ``name`` within ``minutes`` (see the module docstring)."""
    if resolution not in RESOLUTIONS:
        raise InputError(f"unknown resolution {resolution!r}; valid: {', '.join(RESOLUTIONS)}")
    check_workers(jobs, dask)
    scene = load_scene(name, resolution)  # InputError for an unknown scene
    if not is_custom(name):
        raise InputError(f"{name!r} is a built-in scene (its model ships with colgnn); `colgnn fit` trains a scene "
                         "made by `colgnn scene new`")
    folder = scene_file(name).parent
    work = ensure_writable_dir(folder / f"{name}-fit" / resolution)
    ckpt = work / "train.pt"
    plan, rebudgeted = start_plan(work, minutes, ckpt)
    invocation = invocation or f"colgnn fit {name} --resolution {resolution} --minutes {minutes:g}"
    prog = _Progress(name, 60.0 * plan.minutes, progress)
    quiet = not progress
    try:
        _say(prog, f"budget {plan.minutes:g} min: data {plan.shares_s['data'] / 60:.1f} min, training "
             f"{plan.shares_s['train'] / 60:.1f} min, evaluation {plan.shares_s['evaluate'] / 60:.1f} min; "
             f"{plan.test_sequences} held-out sequence(s), {plan.frames} frames each", quiet)
        data = work / "data"
        if rebudgeted:
            _say(prog, "a new budget: the sequences simulated so far are kept, and the model is trained again", quiet)
        if physics_changed(scene, work, ckpt):
            _say(prog, "the scene's physics changed since the last fit (material, support, friction, dt or tool): "
                 "its data is simulated and its model trained again", quiet)
        _data_stage(name, resolution, data, plan, jobs, dask, prog, quiet, work)
        steps_done = _train_stage(scene, data, ckpt, plan, prog, quiet, work)
        prog.set("evaluate", "held-out sequences")
        metrics = evaluate(name, checkpoint=str(ckpt), data_dir=data, out_dir=work / "eval",
                           max_sequences=plan.test_sequences, progress=False)
        prog.set("evaluate", "speed")
        speed = bench(name, checkpoint=str(ckpt), frames=BENCH_FRAMES, threads=auto_threads())
        prog.set("evaluate", "picture")
        picture = _picture(ckpt, scene, data, folder / f"{name}-fit.png")
        model = folder / f"{name}.pt"
        strip_training_state(ckpt, model)
        wall = prog.elapsed()
        report = folder / f"{name}-report.md"
        with atomic_write(report, "w") as fh:
            fh.write(format_report(name, resolution, plan, metrics, speed, steps_done, wall, invocation,
                                   (read_manifest(data) or {}), picture.name, model.name, prog.stage_walls()))
        prog.set("done")
    finally:
        prog.close()
    return FitResult(name, resolution, model, report, picture, plan, metrics, speed, wall)


def _data_stage(name, resolution, data: Path, plan: FitPlan, jobs: int, dask, prog: _Progress, quiet: bool,
                work: Path) -> None:
    """Test sequences plus one training sequence per worker, timed; then as many more as the data share allows."""
    parallel = int(jobs) if dask is None else _dask_workers_hint(dask)
    done = {"n": 0}
    walls: list[float] = []  # wall seconds of the sequences simulated by this run, in order

    def on_entry(entry: dict) -> None:
        done["n"] += 1
        if "wall_s" in entry:
            walls.append(float(entry["wall_s"]))
        prog.note(f"{done['n']} sequence(s) simulated" + (f", {entry['file']} failed" if "error" in entry else ""))

    def run(train_sequences: int) -> None:
        prog.set("data", f"simulating {train_sequences} + {plan.test_sequences} sequences")
        try:
            generate_dataset(name, resolution, data, sequences=train_sequences, frames=plan.frames, jobs=jobs,
                             test_sequences=plan.test_sequences, progress=False, dask=dask, on_entry=on_entry)
        except SimulationError as exc:  # failed seeds were replaced where possible; go on with what there is
            _say(prog, f"some sequences could not be verified and were left out: {exc}", quiet)

    if plan.train_sequences is None:
        first = max(1, parallel)
        t0 = time.perf_counter()
        run(first)
        manifest = (read_manifest(data) or {})
        first_walls = [e.get("wall_s", 0.0) for e in manifest.get("sequences", {}).values()]
        per_seq = float(np.mean(first_walls)) if first_walls else time.perf_counter() - t0
        first_wall, data_share, tested = time.perf_counter() - t0, plan.shares_s["data"], plan.test_sequences
        _replan(plan, per_seq, 60.0 * plan.minutes - prog.elapsed(), parallel)
        if first_wall > data_share:
            plan.notes.append(overrun_note(first_wall, plan.minutes))
            _say(prog, plan.notes[-1], quiet)
        for_training = plan.shares_s["data"] - (plan.test_sequences - tested) * per_seq / max(parallel, 1)
        more = int(max(for_training, 0.0) / max(per_seq, 1e-3) * max(parallel, 1))
        plan.train_sequences = int(min(MAX_TRAIN_SEQUENCES, first + more))
        plan.notes.append(f"one sequence took {per_seq:.1f} s on a worker ({parallel} worker(s)): evaluation "
                          f"{plan.shares_s['evaluate']:.0f} s on {plan.test_sequences} held-out sequences, more "
                          f"data {plan.shares_s['data']:.0f} s ({plan.train_sequences} training sequences in all), "
                          f"training {plan.shares_s['train']:.0f} s")
        _write_json(work / "plan.json", plan.to_dict())
        _say(prog, plan.notes[-1], quiet)
        data_end = prog.elapsed() + plan.shares_s["data"]
        run(plan.train_sequences)
        # The first round's cost can overstate the rest (cold caches, a busy start, resumed sequences): sequences
        # that finish early leave data time, which goes to more sequences while whole rounds still fit.
        while (more := top_up_sequences(walls, parallel, data_end - prog.elapsed(),
                                        MAX_TRAIN_SEQUENCES - plan.train_sequences)) > 0:
            plan.train_sequences += more
            plan.notes.append(f"the sequences ran faster than planned: {more} more in the "
                              f"{data_end - prog.elapsed():.0f} s left of the data's share "
                              f"({plan.train_sequences} training sequences in all)")
            _write_json(work / "plan.json", plan.to_dict())
            _say(prog, plan.notes[-1], quiet)
            timed = len(walls)
            run(plan.train_sequences)
            if len(walls) == timed:  # nothing new was simulated (every seed failed): no point in asking again
                break
    else:
        run(plan.train_sequences)
    if not list(data.glob("train_*.npz")) or not list(data.glob("test_*.npz")):
        raise SimulationError(f"no verified training or test sequence in {data}: see its manifest.json")


def top_up_sequences(walls: list[float], workers: int, left_s: float, room: int) -> int:
    """How many more training sequences fit in ``left_s`` seconds of the data's share: whole rounds of ``workers``
    sequences, each round costing the mean of the latest round's walls (``walls``, in order) with a 10% margin;
    at most ``room``. 0 when no round fits or nothing has been timed."""
    if not walls or room <= 0:
        return 0
    per_seq = 1.1 * float(np.mean(walls[-max(1, workers):]))
    rounds = int(left_s // per_seq) if per_seq > 0 else 0
    return int(min(room, max(0, rounds) * max(1, workers)))


def held_out_sequences(per_seq: float, workers: int, data_s: float, evaluate_s: float, frames: int,
                       least: int) -> int:
    """How many held-out sequences a fit judges its model on: as many as cost at most ``HELD_OUT_DATA_FRACTION``
    of the data's share ``data_s`` to simulate (``per_seq`` s each on one of ``workers``) and whose evaluation fits
    the evaluation's share ``evaluate_s``; at least ``least``, at most ``MAX_TEST_SEQUENCES``.

    Why: three held-out presses decide nothing on an object whose response turns sharply with the contact point.
    Session 57's cow at ci scored 0.671 on its three (one press on the spine: 1.03) and 0.383 on sixteen; a ci
    sequence costs seconds, so the fit can afford a verdict that does not hang on one draw."""
    by_data = int(HELD_OUT_DATA_FRACTION * data_s / max(per_seq / max(workers, 1), 1e-6))
    by_eval = int((evaluate_s - 20.0) // (frames * 8 * MODEL_STEP_S))
    return int(max(least, min(MAX_TEST_SEQUENCES, by_data, by_eval)))


def _replan(plan: FitPlan, per_seq: float, left: float, workers: int = 1) -> None:
    """Shares of the time ``left`` once a sequence's cost is known: the evaluation's estimate (held-out rollouts
    and their exact collision checks, the speed run's solver steps, the picture) first, then data and training.
    The held-out set grows to what the shares afford (:func:`held_out_sequences`)."""
    base_evaluate = SHARES["evaluate"] * 60.0 * plan.minutes
    plan.test_sequences = held_out_sequences(per_seq, workers, SHARES["data"] * 60.0 * plan.minutes, base_evaluate,
                                             plan.frames, plan.test_sequences)
    per_frame = per_seq / plan.frames
    estimate = (BENCH_FRAMES * per_frame + plan.test_sequences * plan.frames * 8 * MODEL_STEP_S
                + 2 * plan.frames * MODEL_STEP_S + 20.0)
    evaluate_s = max(base_evaluate, estimate)
    rest = max(left - evaluate_s, 0.0)
    plan.shares_s = rounded_shares({"data": DATA_FRACTION_AFTER_PROBE * rest,
                                    "train": (1 - DATA_FRACTION_AFTER_PROBE) * rest, "evaluate": evaluate_s},
                                   rest + evaluate_s)


def overrun_note(first_wall_s: float, minutes: float) -> str:
    """What the report says when the first sequences alone took more than the data's share of the budget: the
    budget is too small for this scene and resolution, and training is cut to its minimum. The suggested budget is
    a rule of thumb: five times the first round's wall time leaves the data about twice that round again and the
    training about as long, after the evaluation's share."""
    first_min = first_wall_s / 60.0
    suggest = int(5 * np.ceil(first_min))  # 5x the first round, rounded up to whole 5 minutes
    return (f"the first sequences alone took {first_min:.1f} min, {100 * first_min / minutes:.0f}% of the "
            f"{minutes:g}-minute budget, more than its data share: the budget is too small for this scene at this "
            f"resolution, and training is cut short. Run again with --minutes {suggest} or more: the sequences "
            "simulated so far are kept")


def _dask_workers_hint(address: str) -> int:
    """Workers of a ``local:N`` cluster; 4 for a remote one (only sizes the first round)."""
    return int(address.split(":")[1]) if address.startswith("local:") else 4


def physics_changed(scene, work: Path, ckpt: Path) -> bool:
    """Whether the scene's physics fingerprint differs from the one the work folder's last fit recorded. If so the
    trained checkpoint is removed (the data's sequences record the fingerprint, so `generate` redoes them); either
    way the current fingerprint is recorded."""
    path = work / "physics.json"
    now = scene.physics_fingerprint()
    before = None
    if path.is_file():
        try:
            before = json.loads(path.read_text()).get("physics_fingerprint")
        except (OSError, json.JSONDecodeError, AttributeError):
            before = None
    changed = before is not None and not scene.accepts_physics(before)
    if changed:
        ckpt.unlink(missing_ok=True)
    _write_json(path, {"physics_fingerprint": now})
    return changed


def fit_variant(scene) -> str:
    """The training variant of a fit: 'baseline' (the data loss alone) for a quasi-static network, as the shipped
    quasi-static models of the glued mat and banana were trained; the paper's 'full' otherwise. The correction,
    not the loss, keeps the published shape off the tool."""
    return "baseline" if scene.model.get("quasi_static") else "full"


def training_share(plan: FitPlan, left_s: float) -> float:
    """The seconds training gets when it starts with ``left_s`` of the budget left: its planned share, or all but
    the evaluation's share when the data finished early. The data's share is set from the first sequences' cost,
    which can run slower than the rest (session 43's cow: 10.7 s a sequence beside other jobs planned 155 sequences
    in 14 min; they ran faster, and the fit ended after 15.6 of its 30 minutes)."""
    return max(float(plan.shares_s["train"]), float(left_s) - float(plan.shares_s["evaluate"]))


def steady_rate(stamps: list[tuple[int, float]], warm_steps: int) -> float | None:
    """Training steps per second between the first and the last ``(step, perf_counter s)`` stamp at or after step
    ``warm_steps``; None with fewer than two such stamps. The full cow's fit planned its training from 15 steps that
    ran at 16 steps/s; the run itself went at 20, so it ended 13 minutes inside its share."""
    steady = [(s, t) for s, t in stamps if s >= warm_steps]
    if len(steady) < 2 or steady[-1][1] <= steady[0][1]:
        return None
    return (steady[-1][0] - steady[0][0]) / (steady[-1][1] - steady[0][1])


def _train_stage(scene, data: Path, ckpt: Path, plan: FitPlan, prog: _Progress, quiet: bool, work: Path) -> int:
    """Measure the step rate on a throw-away run, then train (or resume) to the planned step count."""
    share = plan.shares_s["train"]
    variant = fit_variant(scene)
    stage_start = time.perf_counter()
    if plan.train_steps is None:
        used = prog.elapsed()
        grown = training_share(plan, prog.total - used)
        if grown > share + 1.0:
            plan.notes.append(f"the data finished {grown - share:.0f} s early: training gets {grown:.0f} s")
            # the data's share becomes what it took, and training gets the rest: the shares still add up to the budget
            plan.shares_s = rounded_shares({**plan.shares_s, "data": used}, prog.total)
            share = plan.shares_s["train"]
            _say(prog, plan.notes[-1], quiet)
        prog.set("train", "measuring the step rate")
        probe = work / "calibration.pt"
        cfg = TrainConfig(steps=CALIBRATION_STEPS, warmup_steps=3, log_every=5, checkpoint_every=10_000)
        stamps: list[tuple[int, float]] = []
        t0 = time.perf_counter()
        res = train(scene, data, probe, variant, config=cfg, progress=False, log_dir=False, threads=auto_threads(),
                    on_step=lambda s, n: stamps.append((s, time.perf_counter())))
        setup = time.perf_counter() - t0 - res.wall_s
        probe.unlink(missing_ok=True)
        rate = steady_rate(stamps, CALIBRATION_WARM_STEPS) or res.step / max(res.wall_s, 1e-6)
        plan.train_steps = int(max(MIN_TRAIN_STEPS, 0.9 * rate * max(share - (time.perf_counter() - t0) - setup, 0)))
        plan.notes.append(f"training ({variant} variant) runs {rate:.1f} steps/s: {plan.train_steps} steps planned")
        _write_json(work / "plan.json", plan.to_dict())
        _say(prog, plan.notes[-1], quiet)
    steps = int(plan.train_steps)
    done = 0
    if ckpt.is_file():
        done = int(load_checkpoint(ckpt).meta.step)
    if done >= steps:
        return done
    left = max(share - (time.perf_counter() - stage_start), 10.0)
    cfg = TrainConfig(steps=steps, warmup_steps=min(200, max(10, steps // 10)),
                      checkpoint_every=max(25, steps // 20), log_every=max(1, min(25, steps // 40)))
    prog.set("train", f"step {done}/{steps}")
    res = train(scene, data, ckpt, variant, resume=done > 0, steps=steps, config=cfg, time_budget_s=left,
                progress=False, log_dir=False, threads=auto_threads(), on_step=lambda s, n: prog.note(f"step {s}/{n}"))
    if res.stopped == "time budget":
        _say(prog, f"training stopped by the time budget at step {res.step}/{steps}", quiet)
    return int(res.step)


def _picture(ckpt: Path, scene, data: Path, out: Path) -> Path:
    """Ground truth against the model (with the correction) on the first held-out sequence."""
    gt = load_sequence(sorted(data.glob("test_*.npz"))[0])
    pred = rollout(str(ckpt), gt.tool_poses, correction=True, scene=scene, initial_positions=gt.object_positions[0])
    return render_strip([gt, pred], ["ground truth (IPC)", "model + correction"], out, count=5)


def fit_verdict(model_error: float, baseline_error: float) -> str:
    """How the corrected model compares with the better trivial baseline (relative displacement errors): clearly
    better means at most half its error, the bar that the project's accuracy targets use."""
    if model_error <= 0.5 * baseline_error:
        return "clearly beats both trivial baselines (at most half the error of the better one)"
    if model_error < baseline_error:
        return ("beats the trivial baselines, but **not clearly** (more than half the error of the better one): "
                "give the fit a larger budget")
    return "does **not** beat the trivial baselines: it is no better than predicting that nothing moves"


def budget_table(plan: FitPlan, used_s: dict[str, float], wall: float, n_train: int, n_test: int,
                 steps: int) -> list[str]:
    """Markdown rows: each stage's planned share of the budget against the wall time it took in this run."""
    rows = ["| stage | planned min | used min (this run) | what |", "|---|---:|---:|---|"]
    what = {"data": f"{n_train} training + {n_test} held-out sequences of {plan.frames} frames (IPC ground truth)",
            "train": f"{steps} steps", "evaluate": "held-out accuracy, collisions, speed, picture"}
    for key, label in (("data", "data"), ("train", "training"), ("evaluate", "evaluation")):
        rows.append(f"| {label} | {plan.shares_s[key] / 60:.1f} | {used_s.get(key, 0.0) / 60:.1f} | {what[key]} |")
    rows.append(f"| **total** | {plan.minutes:g} | {wall / 60:.1f} | |")
    return rows


def format_report(name: str, resolution: str, plan: FitPlan, metrics: dict, speed: dict, steps: int, wall: float,
                  invocation: str, manifest: dict, picture: str, model: str,
                  used_s: dict[str, float] | None = None) -> str:
    """``<NAME>-report.md``: what was run, held-out accuracy against the trivial baselines, collisions, speed."""
    seqs = manifest.get("sequences", {})
    n_train = sum(1 for e in seqs.values() if e.get("split") == "train")
    n_test = sum(1 for e in seqs.values() if e.get("split") == "test")
    rel = metrics["relative"]
    model_row = rel["corrected"]["all"]["mean"]
    best_base = min(rel["rest"]["all"]["mean"], rel["rest_correction"]["all"]["mean"])
    verdict = fit_verdict(model_row, best_base)
    lines = [f"# {name}: fitted model ({resolution})", "", provenance_line(invocation), "",
             f"Budget {plan.minutes:g} min, used {wall / 60:.1f} min.", ""]
    lines += budget_table(plan, used_s or {}, wall, n_train, n_test, steps)
    lines += ["", " ".join(n[0].upper() + n[1:] + "." for n in plan.notes),
             "", f"Model: `{model}` (the scene's default model). On the held-out sequences the corrected model "
             f"{verdict} (relative displacement error {model_row:.3f} against {best_base:.3f}).", "",
             "## Accuracy on held-out sequences", ""]
    lines += format_relative(rel)
    lines += ["", "## Collisions", "", "Crossings per step over [t, t+1] (exact CCD) and frames where the object "
              "intersects the tool.", "", "| row | N_vf | N_ee | intersecting frames |", "|---|---:|---:|---:|"]
    for key, label in (("ground_truth", "ground truth (IPC)"), ("raw", "raw network"),
                       ("corrected", "model + correction")):
        c = metrics["rows"][key]["collisions"]
        lines.append(f"| {label} | {c['N_vf']:.2f} | {c['N_ee']:.2f} | {c['intersecting_frames']}/{c['frames']} |")
    s = speed
    lines += ["", "## Speed", "", f"One family trajectory, {s['frames'] - 1} steps, {s['threads']} threads, load "
              f"{s['load_average_1min']:.1f}.", "", "| stage | median ms | p95 ms |", "|---|---:|---:|"]
    for label, key in (("model step (total)", "total_ms"), ("graph", "graph_ms"), ("network", "gnn_ms"),
                       ("correction", "correction_ms"), ("IPC solver", "ipc_ms")):
        lines.append(f"| {label} | {s[key]['median']:.2f} | {s[key]['p95']:.2f} |")
    lines += ["", f"Speed-up over the solver: {s['speedup_vs_ipc']:.0f}x; crossings after the correction: "
              f"{s['crossings_after_correction']}, fallbacks {s['fallbacks']}.", "",
              f"![ground truth against the model]({picture})", ""]
    return "\n".join(lines)
