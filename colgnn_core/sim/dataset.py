"""Ground-truth datasets: IPC sequences written as contract ``.npz`` files plus a manifest.

Layout of an output folder::

    train_0000.npz ... train_0019.npz   seeds split_seeds('train', n)
    test_0000.npz  ... test_0004.npz    seeds split_seeds('test', n)   (disjoint from train)
    custom_0000.npz                     a given poses array (``colgnn generate --poses``)
    manifest.json                       one entry per finished sequence (written atomically)

Every sequence file carries, besides the contract keys, ``object_tets``,
``object_rest``, ``newton_iterations`` [T], ``step_ms`` [T], ``min_distance`` [T] (object–tool, m),
``kappa`` [T] (frame 0 has zeros / its initial distance), ``subframes`` [T] (implicit steps
per frame: more than 1 where a failed solve was halved), and ``seed``, ``scene``,
``resolution``, ``split``, ``dhat``, ``dmin``, ``object_fingerprint``, ``physics_fingerprint``
(:meth:`~colgnn_core.scenes.Scene.physics_fingerprint`), ``sim_options`` (JSON)
so the manifest can be rebuilt from the files. Where the straight motion into a frame is not
collision-free, the file records the intermediate states of its collision-free path
(``subframe_frame``, ``subframe_object_positions``, ``subframe_tool_positions``:
:data:`colgnn_core.io.SUBFRAME_KEYS`, :meth:`colgnn_core.io.Sequence.motion`).

Hard motions do not fail: a frame whose solve fails is solved again in halves, and a frame
whose straight motion is not collision-free records its path (:class:`~colgnn_core.sim.ipc.IPCSimulator`).
A family sequence that still fails verification (SimulationError: even 16 sub-frames did
not converge) is replaced by a spare seed of the same split (``max_retries``); the manifest
lists the rejected seeds and why, so any bias this introduces is visible.

Resume: a sequence being simulated locally is saved every minute to ``<file>.partial``
(:mod:`colgnn_core.sim.partial`), and a later run continues it from the saved frame. A sequence
whose file exists, loads, matches the requested scene (its mesh and physics fingerprints) / seed /
frames / solver options and (if the manifest lists it) has the listed sha256, is skipped. Sharding
splits the ordered job list as ``jobs[i::n]`` so several machines can share a dataset;
the manifest is merged (re-read, updated, atomically replaced) after every sequence. On a cluster, ``dask``
(``colgnn generate --dask tcp://host:8786``) sends one task per sequence to a Dask scheduler
(:mod:`colgnn_core.sim.cluster`) and writes the returned sequences here, so resuming works the same way.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from colgnn_core.collision.kernels import use_kernel_threads
from colgnn_core.errors import InputError, SimulationError
from colgnn_core.io import Sequence, atomic_write, ensure_writable_dir, load_sequence, save_sequence
from colgnn_core.scenes import load_scene, sample_poses, split_seeds
from colgnn_core.sim.cluster import check_workers, dask_client
from colgnn_core.sim.ipc import IPCSimulator
from colgnn_core.sim.partial import PARTIAL_EVERY_S, FrameRecord, PartialSaver, partial_key, partial_path

MANIFEST = "manifest.json"
SPLITS = ("train", "test", "both")


def simulate_sequence(scene, poses: np.ndarray, progress: bool = False, partial: str | Path | None = None,
                      partial_every_s: float = PARTIAL_EVERY_S, **sim_options: Any) -> Sequence:
    """Simulate ``poses`` [T,7] (frame 0 = the initial tool pose) with IPC; return a verified Sequence.

    Poses are validated against the scene workspace (InputError naming the row). A frame that
    fails Newton or verification raises SimulationError naming the frame. ``sim_options`` go to
    :class:`colgnn_core.sim.ipc.IPCSimulator` (newton_tol, dhat_scale, dmin_scale, ...).
    ``partial``: a partial file (:mod:`colgnn_core.sim.partial`) saved every ``partial_every_s`` seconds while
    simulating, and continued from when it matches this scene, these poses and options. The caller removes it once
    the sequence is written.
    """
    poses = scene.check_poses(poses)
    if len(poses) < 1:
        raise InputError("poses must have at least one row (frame 0)")
    sim = IPCSimulator(scene, initial_tool_pose=poses[0], **sim_options)
    record = FrameRecord(len(poses), sim.n_obj, sim.n_tool)
    record.first(sim.positions, sim.tool_positions, sim.tool_distance())
    saver = PartialSaver(None if partial is None else Path(partial),
                         partial_key(scene_stamp(scene), poses, sim_options), partial_every_s)
    if saver.path is not None:
        state = record.load(saver.path, saver.key)
        if state is not None:
            sim.restore(state)
    frames = range(record.done + 1, len(poses))
    if progress:
        from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

        frames = tqdm(frames, desc=f"{scene.name} frames", leave=False, unit="frame", initial=record.done,
                      total=len(poses) - 1)
    for k in frames:
        st = sim.step(poses[k])
        record.add(k, sim.positions, sim.tool_positions, st)
        saver.maybe_save(record, sim.state)
    return Sequence(
        object_positions=record.object_positions,
        object_faces=np.asarray(scene.object.faces, dtype=np.int64),
        tool_positions=record.tool_positions,
        tool_faces=np.asarray(scene.tool.faces, dtype=np.int64),
        tool_poses=poses,
        dt=float(scene.dt),
        extra={
            "object_tets": np.asarray(scene.object.tets, dtype=np.int64),
            "object_rest": np.asarray(scene.object.vertices, dtype=np.float64),
            **record.extras(),
            "dhat": np.float64(sim.dhat),
            "dmin": np.float64(sim.dmin),
        },
    )


# ----------------------------------------------------------------------------- jobs
@dataclass(frozen=True)
class _Job:
    scene: str
    resolution: str
    split: str  # train | test | custom
    index: int
    seed: int  # -1 for custom poses
    frames: int
    file: str
    sim_options: tuple  # sorted (key, value) pairs, picklable
    poses: np.ndarray | None = None
    fallback_seeds: tuple = ()  # tried in order if ``seed`` fails (same split's seed class: splits stay disjoint)
    partial_every_s: float = PARTIAL_EVERY_S  # how often a local run saves the sequence's partial file


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _entry(job: _Job, path: Path, seq: Sequence) -> dict:
    """Manifest entry of a finished sequence (statistics read from the file's extras)."""
    it = np.asarray(seq.extra["newton_iterations"])[1:]
    ms = np.asarray(seq.extra["step_ms"])[1:]
    md = np.asarray(seq.extra["min_distance"])
    return {
        "file": job.file,
        "split": job.split,
        "index": job.index,
        "seed": None if job.seed < 0 else job.seed,
        "frames": seq.frames,
        "object_vertices": int(seq.object_positions.shape[1]),
        "newton_iterations_mean": float(it.mean()) if it.size else 0.0,
        "newton_iterations_max": int(it.max()) if it.size else 0,
        "ms_per_step_median": float(np.median(ms)) if ms.size else 0.0,
        "ms_total": float(ms.sum()),
        "min_distance": float(md.min()),
        "dhat": float(seq.extra["dhat"]),
        "dmin": float(seq.extra["dmin"]),
        # frames solved in halves, and frames whose motion is a recorded path (files from before these keys: 0)
        "subframe_frames": int(np.sum(np.asarray(seq.extra.get("subframes", [1])) > 1)),
        "path_frames": int(len(np.unique(seq.extra["subframe_frame"]))) if "subframe_frame" in seq.extra else 0,
        "sha256": _sha256(path),
    }


def _options_key(job: _Job) -> str:
    return json.dumps(dict(job.sim_options), sort_keys=True)


def _failure_key(job: _Job) -> dict:
    """What makes a failed family job's outcome reproducible (compared on resume)."""
    return {"seeds": [int(job.seed), *map(int, job.fallback_seeds)], "frames": int(job.frames),
            "sim_options": _options_key(job)}


def scene_stamp(scene) -> dict[str, str]:
    """What a sequence records about the scene that made it: the object mesh's and the physics' fingerprints."""
    return {"object_fingerprint": scene.object.fingerprint(), "physics_fingerprint": scene.physics_fingerprint()}


def _matches(job: _Job, seq: Sequence, stamp: dict[str, str], accepts_physics: Callable[[str], bool]) -> bool:
    """Was ``seq`` produced by ``job`` (same scene mesh and physics, seed, frames, solver options)? A sequence from
    before the physics fingerprint was recorded is taken on its mesh fingerprint alone."""
    ex = seq.extra
    try:
        return (
            seq.frames == job.frames
            and str(ex["scene"]) == job.scene
            and str(ex["resolution"]) == job.resolution
            and str(ex["object_fingerprint"]) == stamp["object_fingerprint"]
            and ("physics_fingerprint" not in ex or accepts_physics(str(ex["physics_fingerprint"])))
            and str(ex["sim_options"]) == _options_key(job)
            and int(ex["seed"]) in (job.seed, *job.fallback_seeds)
            and (job.poses is None or np.allclose(seq.tool_poses, job.poses))
        )
    except KeyError:
        return False


def simulate_job(job: _Job, scene, partial: bool = False, progress: bool = False) -> dict:
    """Simulate one job's sequence on ``scene`` (a worker's part: no file but the partial one is written). Returns
    ``{"sequence", "seed", "rejected", "wall_s", "load"}`` or, when every seed failed or the poses are bad,
    ``{"error", "rejected", "failure"}`` (``failure``: the job's reproducible failure key, family jobs only).
    ``partial``: save and continue the sequence's partial file beside ``job.file`` (a local run; a Dask worker's
    files would be on its own machine). ``progress``: a progress bar over the frames."""
    rejected: list[dict] = []
    try:
        t0 = time.perf_counter()
        for seed in (job.seed, *job.fallback_seeds):
            poses = job.poses if job.poses is not None else sample_poses(scene, seed, job.frames)
            try:
                seq = simulate_sequence(scene, poses, progress=progress,
                                        partial=partial_path(job.file) if partial else None,
                                        partial_every_s=job.partial_every_s,
                                        **dict(job.sim_options))
                break
            except SimulationError as exc:
                # A trajectory the verified solver cannot do (e.g. a coarse surface snapping past a
                # sharp tip faster than a straight frame-to-frame motion can follow) is not saved;
                # the next seed of the same split replaces it and the manifest records why.
                rejected.append({"seed": int(seed), "error": str(exc)})
                if seed == (job.fallback_seeds[-1] if job.fallback_seeds else job.seed):
                    raise
        return {"sequence": seq, "seed": int(seed), "rejected": rejected, "wall_s": time.perf_counter() - t0,
                "load": os.getloadavg()[0]}
    except (SimulationError, InputError) as exc:
        failure = _failure_key(job) if isinstance(exc, SimulationError) and job.poses is None else None
        return {"error": f"{type(exc).__name__}: {exc}", "rejected": rejected, "failure": failure}


def save_job(job: _Job, result: dict, stamp: dict[str, str]) -> dict:
    """Write a simulated job's sequence atomically (this process); its manifest entry, or the error entry."""
    if "error" in result:
        entry = {"file": Path(job.file).name, "split": job.split, "seed": job.seed, "error": result["error"],
                 "rejected_seeds": result["rejected"]}
        if result["failure"] is not None:
            entry["job"] = result["failure"]  # deterministic: remembered so that a resume does not redo it
        return entry
    seq, seed = result["sequence"], result["seed"]
    seq.extra.update(
        {
            "seed": np.int64(seed),
            "scene": np.asarray(job.scene),
            "resolution": np.asarray(job.resolution),
            "split": np.asarray(job.split),
            **{k: np.asarray(v) for k, v in stamp.items()},
            "sim_options": np.asarray(_options_key(job)),
        }
    )
    path = Path(job.file)
    save_sequence(path, seq)
    partial_path(path).unlink(missing_ok=True)  # the sequence is whole: nothing left to continue
    entry = _entry(job, path, seq)
    entry["file"] = path.name
    entry["seed"] = None if seed < 0 else int(seed)
    entry["rejected_seeds"] = result["rejected"]
    entry["wall_s"] = result["wall_s"]
    entry["load_average_1min"] = result["load"]  # a shared machine inflates ms_per_step_median
    return entry


def _run_job(job: _Job, progress: bool = False) -> dict:
    """Local worker: simulate one sequence (continuing its partial file) and write it atomically. Returns its
    manifest entry or an error."""
    try:
        scene = load_scene(job.scene, job.resolution)
    except InputError as exc:
        return {"file": Path(job.file).name, "split": job.split, "seed": job.seed,
                "error": f"InputError: {exc}", "rejected_seeds": []}
    return save_job(job, simulate_job(job, scene, partial=True, progress=progress), scene_stamp(scene))


def _read_manifest(out_dir: Path) -> dict:
    path = out_dir / MANIFEST
    if not path.is_file():
        return {"sequences": {}}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc}); delete it to rebuild from the sequence files") from exc
    data.setdefault("sequences", {})
    return data


def _write_manifest(out_dir: Path, header: dict, entries: dict[str, dict], failed: dict[str,
                                                                                        dict] | None = None) -> None:
    """Merge ``entries`` (and ``failed`` jobs) into the manifest on disk (other shards may have added theirs) and
    replace it atomically. A file that now has an entry is dropped from ``failed``."""
    data = _read_manifest(out_dir)
    data.update(header)
    data["sequences"].update(entries)
    data["sequences"] = dict(sorted(data["sequences"].items()))
    failed = {k: v for k, v in {**data.get("failed", {}), **(failed or {})}.items() if k not in data["sequences"]}
    data.pop("failed", None)
    if failed:
        data["failed"] = dict(sorted(failed.items()))
    with atomic_write(out_dir / MANIFEST, "w") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


def _is_done(job: _Job, manifest: dict, stamp: dict[str, str], accepts_physics: Callable[[str], bool]
             ) -> tuple[bool, dict | None]:
    """(complete?, manifest entry to keep) for an existing file."""
    path = Path(job.file)
    if not path.is_file():
        return False, None
    listed = manifest["sequences"].get(path.name)
    try:
        digest = _sha256(path)
        if listed is not None and listed.get("sha256") not in (None, digest):
            return False, None
        seq = load_sequence(path)
    except (InputError, OSError):
        return False, None
    if not _matches(job, seq, stamp, accepts_physics):
        return False, None
    if listed is not None and listed.get("sha256") == digest:
        return True, listed
    entry = _entry(job, path, seq)  # file complete but not (yet) in the manifest: rebuild its entry
    entry["file"] = path.name
    entry["seed"] = int(seq.extra["seed"]) if int(seq.extra["seed"]) >= 0 else None
    return True, entry


def parse_shard(text: str) -> tuple[int, int]:
    """'I/N' -> (I, N) with 0 <= I < N; InputError otherwise."""
    try:
        i, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        raise InputError(f"--shard must look like I/N (e.g. 0/4), got {text!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise InputError(f"--shard I/N needs 0 <= I < N, got {text!r}")
    return i, n


def generate_dataset(
    scene_name: str,
    resolution: str,
    out_dir: str | Path,
    sequences: int = 20,
    frames: int = 40,
    jobs: int = 1,
    shard: tuple[int, int] = (0, 1),
    split: str = "both",
    progress: bool = True,
    test_sequences: int | None = None,
    poses: np.ndarray | None = None,
    sim_options: dict | None = None,
    max_retries: int = 2,
    retry_failed: bool = False,
    dask: str | None = None,
    on_entry=None,
    partial_every_s: float = PARTIAL_EVERY_S,
) -> dict:
    """Simulate a dataset of a scene into ``out_dir``; returns the manifest (dict).

    Args:
        scene_name, resolution: scene registry keys ('full' | 'ci').
        sequences: number of sequences of ``split`` ('train' or 'test'); with split='both',
            the number of train sequences, plus ``test_sequences`` test ones (default
            ceil(sequences/4), at least 1: 20 train -> 5 test).
        frames: frames per sequence (frame 0 = rest).
        jobs: worker processes (spawn; each simulates whole sequences).
        shard: (i, n): this process does jobs[i::n] of the ordered job list.
        poses: a given trajectory [T,7] instead of the family (written as ``custom_0000.npz``;
            ``sequences``/``frames``/``split`` are then ignored). Validated against the workspace.
        sim_options: IPCSimulator keyword arguments (accuracy knobs).
        max_retries: a family sequence whose simulation fails verification is replaced by up to
            this many spare seeds of the same split (listed under ``rejected_seeds`` in the
            manifest); given ``poses`` are never replaced.
        retry_failed: simulate again jobs whose every seed failed in an earlier run (the manifest's ``failed``
            section); by default they are skipped and reported as failures again, since the solver is
            deterministic.
        dask: simulate on a Dask cluster instead of local processes: a scheduler address (``tcp://host:8786``)
            or ``local:N`` (:mod:`colgnn_core.sim.cluster`); one task per sequence, written here.
        on_entry: called with each finished sequence's manifest entry (or error entry), e.g. for a progress display.
        partial_every_s: how often (s) a local run saves the sequence in progress to ``<file>.partial``, from which
            an interrupted run continues (:mod:`colgnn_core.sim.partial`).

    Raises InputError for bad arguments (unknown scene, poses outside the workspace, unwritable
    folder) and SimulationError, after finishing the other sequences, if any sequence failed.
    """
    scene = load_scene(scene_name, resolution)
    if split not in SPLITS:
        raise InputError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    check_workers(jobs, dask)
    i_shard, n_shard = (int(v) for v in shard)
    if not (n_shard >= 1 and 0 <= i_shard < n_shard):
        raise InputError(f"shard must satisfy 0 <= i < n, got {i_shard}/{n_shard}")
    out = ensure_writable_dir(out_dir)
    opts = tuple(sorted((sim_options or {}).items()))
    if poses is not None:
        poses = scene.check_poses(poses)
        all_jobs = [_Job(scene_name, resolution, "custom", 0, -1, len(poses), str(out / "custom_0000.npz"), opts,
                         poses)]
    else:
        all_jobs = _family_jobs(scene_name, resolution, out, opts, split, sequences, test_sequences, frames,
                                max_retries)
    if not float(partial_every_s) >= 0:
        raise InputError(f"partial_every_s must be >= 0 seconds, got {partial_every_s}")
    my_jobs = [dataclasses.replace(j, partial_every_s=float(partial_every_s)) for j in all_jobs[i_shard::n_shard]]

    header = {
        "scene": scene_name,
        "resolution": resolution,
        "dt": float(scene.dt),
        **scene_stamp(scene),
        "sim_options": dict(opts),
    }
    manifest = _read_manifest(out)
    if manifest.get("scene", scene_name) != scene_name or manifest.get("resolution", resolution) != resolution:
        raise InputError(f"{out / MANIFEST} belongs to {manifest.get('scene')}/{manifest.get('resolution')}, "
                         f"not {scene_name}/{resolution}")
    stamp = scene_stamp(scene)
    done, todo, failures = _triage(my_jobs, manifest, stamp, retry_failed, scene.accepts_physics)
    _write_manifest(out, header, done)

    bar = None
    if progress:
        from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

        bar = tqdm(total=len(my_jobs), initial=len(done), desc=f"{scene_name}/{resolution}", unit="seq")

    def record(entry: dict) -> None:
        if "error" in entry:
            failures.append(f"{entry['file']}: {entry['error']}")
            if "job" in entry:
                _write_manifest(out, header, {}, {entry["file"]: entry})
        else:
            _write_manifest(out, header, {entry["file"]: entry})
        if bar is not None:
            bar.update(1)
            if "ms_per_step_median" in entry:
                bar.set_postfix(ms_step=f"{entry['ms_per_step_median']:.0f}",
                                newton=f"{entry['newton_iterations_mean']:.1f}")
        if on_entry is not None:
            on_entry(entry)

    if dask is not None and todo:
        _run_on_dask(todo, scene, stamp, dask, record)
    else:
        _run_jobs(todo, int(jobs), record, progress)
    if bar is not None:
        bar.close()
    manifest = _read_manifest(out)
    if failures:
        raise SimulationError(f"{len(failures)} sequence(s) failed: " + "; ".join(failures))
    return manifest


def _split_counts(split: str, sequences: int, test_sequences: int | None) -> dict[str, int]:
    """Sequences per split: ``split='both'`` gives ``sequences`` train and ``test_sequences`` test ones (default
    ceil(sequences/4), at least 1)."""
    if int(sequences) < 0:
        raise InputError(f"sequences must be >= 0, got {sequences}")
    counts = {"train": 0, "test": 0}
    if split == "both":
        counts["train"] = int(sequences)
        counts["test"] = int(test_sequences) if test_sequences is not None else max(1, -(-int(sequences) // 4))
    else:
        counts[split] = int(sequences)
    return counts


def _family_jobs(scene_name: str, resolution: str, out: Path, opts: tuple, split: str, sequences: int,
                 test_sequences: int | None, frames: int, max_retries: int) -> list[_Job]:
    """The ordered job list of the scene's trajectory family: per split, one job per sequence index with its seed
    and ``max_retries`` spare seeds of the same split."""
    if int(frames) < 2:
        raise InputError(f"frames must be >= 2, got {frames}")
    jobs: list[_Job] = []
    for sp_name, count in _split_counts(split, sequences, test_sequences).items():
        # Seeds count.. of the split's own seed class serve as replacements (max_retries per index).
        spare = split_seeds(sp_name, count + count * int(max_retries))[count:]
        for i, seed in enumerate(split_seeds(sp_name, count)):
            fallback = tuple(spare[i * int(max_retries) : (i + 1) * int(max_retries)])
            jobs.append(_Job(scene_name, resolution, sp_name, i, seed, int(frames), str(out / f"{sp_name}_{i:04d}.npz"),
                             opts, None, fallback))
    return jobs


def _triage(my_jobs: list[_Job], manifest: dict, stamp: dict[str, str], retry_failed: bool,
            accepts_physics: Callable[[str], bool]) -> tuple[dict[str, dict], list[_Job], list[str]]:
    """(finished sequences' manifest entries, jobs to simulate, known failures): a finished file is kept, a job
    whose every seed failed before is reported again (unless ``retry_failed``), the rest is to do."""
    done: dict[str, dict] = {}
    todo: list[_Job] = []
    failures: list[str] = []
    for job in my_jobs:
        ok, entry = _is_done(job, manifest, stamp, accepts_physics)
        known = manifest.get("failed", {}).get(Path(job.file).name)
        if ok:
            done[Path(job.file).name] = entry
        elif known is not None and not retry_failed and known.get("job") == _failure_key(job):
            # Every seed of this job failed verification before; simulating them again gives the same result.
            failures.append(f"{known['file']}: {known['error']} (recorded in {MANIFEST}; retry_failed / "
                            "--retry-failed simulates it again)")
        else:
            todo.append(job)
    return done, todo, failures


def _run_on_dask(todo: list[_Job], scene, stamp: dict[str, str], address: str, record) -> None:
    """Simulate ``todo`` on a Dask cluster (one task per sequence; the scene is sent once); write and ``record``
    each sequence here as it arrives."""
    from distributed import as_completed  # lazy: only runs that ask for Dask import it

    with dask_client(address) as client:
        scene_on_workers = client.scatter(scene, broadcast=True)
        futures = {client.submit(simulate_job, job, scene_on_workers, pure=False, key=f"colgnn-{Path(job.file).stem}-"
                                 f"{os.getpid()}-{time.time_ns()}"): job for job in todo}
        try:
            for fut in as_completed(futures):
                record(save_job(futures[fut], fut.result(), stamp))
        finally:
            client.cancel(list(futures))


def _run_jobs(todo: list[_Job], jobs: int, record, progress: bool = False) -> None:
    """Simulate ``todo`` in this process (``progress``: a bar over each sequence's frames), or in ``jobs`` spawned
    worker processes; ``record`` each entry."""
    if jobs == 1 or len(todo) <= 1:
        for job in todo:
            record(_run_job(job, progress))
        return
    ctx = mp.get_context("spawn")
    workers = min(jobs, len(todo))
    with ctx.Pool(processes=workers, initializer=limit_worker_threads, initargs=(worker_threads(workers),)) as pool:
        for entry in pool.imap_unordered(_run_job, todo):
            record(entry)


def worker_threads(workers: int, cpu_count: int | None = None) -> int:
    """Threads for each of ``workers`` local solver processes: the cores shared out, at least 1.

    Why: each library in a solver step (ipctk's TBB broad phase, numba's parallel kernels, CHOLMOD's and BLAS's
    OpenMP) otherwise starts a thread per core in every worker; numpy's OpenBLAS threads spin after each call and
    take a core from the other worker (docs/GROUND_TRUTH.md, session 57)."""
    n = int(cpu_count if cpu_count is not None else (os.cpu_count() or 1))
    return max(1, n // max(1, int(workers)))


def limit_worker_threads(threads: int) -> None:
    """A spawned worker's initializer: every thread pool that the solver uses gets ``threads``."""
    import ipctk
    import scipy.sparse.linalg  # noqa: F401 (loaded first: threadpoolctl limits only the libraries loaded)
    import torch
    from threadpoolctl import threadpool_limits

    try:
        import cholespy  # noqa: F401 (CHOLMOD's OpenMP, when the optional factoriser is installed)
    except ImportError:
        pass
    threadpool_limits(threads)  # every BLAS and OpenMP pool loaded by now
    use_kernel_threads(threads)  # numba's parallel kernels
    ipctk.set_num_threads(threads)
    torch.set_num_threads(threads)
