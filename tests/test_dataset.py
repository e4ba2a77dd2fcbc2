"""Dataset generation: determinism, files + manifest, resume, shards, custom poses, bad input."""

import copy
import dataclasses
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.io import load_sequence
from colgnn_core.learn.data import check_manifest
from colgnn_core.scenes import load_scene, sample_poses
from colgnn_core.scenes.scene import build_scene
from colgnn_core.sim.dataset import generate_dataset, parse_shard, simulate_sequence

SCENE = "cylinder_banana"  # the cheapest 'ci' scene (~0.1 s per step)
SCENE_DIR = Path(__file__).resolve().parents[1] / "colgnn_core" / "scenes"


def test_same_seed_gives_the_same_sequence():
    scene = load_scene(SCENE, "ci")
    a = simulate_sequence(scene, sample_poses(scene, 3, 5))
    b = simulate_sequence(scene, sample_poses(scene, 3, 5))
    assert np.array_equal(a.object_positions, b.object_positions)
    assert np.array_equal(a.tool_positions, b.tool_positions)
    c = simulate_sequence(scene, sample_poses(scene, 6, 5))
    assert not np.array_equal(a.tool_poses, c.tool_poses)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds")
    manifest = generate_dataset(SCENE, "ci", out, sequences=2, frames=4, test_sequences=1, jobs=2, progress=False)
    return out, manifest


def test_generate_writes_sequences_and_manifest(dataset):
    out, manifest = dataset
    names = sorted(p.name for p in out.glob("*.npz"))
    assert names == ["test_0000.npz", "train_0000.npz", "train_0001.npz"]
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == manifest
    assert manifest["scene"] == SCENE and manifest["resolution"] == "ci"
    seeds = {e["split"]: [] for e in manifest["sequences"].values()}
    for name, entry in manifest["sequences"].items():
        seq = load_sequence(out / name)
        assert seq.frames == entry["frames"] == 4
        assert entry["sha256"] and len(entry["sha256"]) == 64
        assert entry["newton_iterations_max"] >= entry["newton_iterations_mean"] >= 1
        assert entry["ms_per_step_median"] > 0
        for key in ("object_tets", "object_rest", "newton_iterations", "step_ms", "min_distance"):
            assert key in seq.extra
        assert str(seq.extra["physics_fingerprint"]) == load_scene(SCENE, "ci").physics_fingerprint()
        assert seq.extra["newton_iterations"].shape == (4,)
        seeds[entry["split"]].append(entry["seed"])
    assert not set(seeds["train"]) & set(seeds["test"])


def test_generate_resumes_without_recomputing(dataset):
    out, manifest = dataset
    mtimes = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    again = generate_dataset(SCENE, "ci", out, sequences=2, frames=4, test_sequences=1, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == mtimes
    assert again["sequences"] == manifest["sequences"]


def _variant(scene, **changes):
    """The scene rebuilt from its TOML with ``changes`` ({table: {key: value}}) applied."""
    cfg = copy.deepcopy(scene.config)
    for table, values in changes.items():
        cfg.setdefault(table, {}).update(values)
    return build_scene(scene.name, scene.resolution, cfg, SCENE_DIR)


def test_the_physics_fingerprint_follows_the_physics_not_the_mesh():
    scene = load_scene(SCENE, "ci")
    same = _variant(scene)
    stiffer = _variant(scene, material={"youngs_modulus": 2 * scene.material.youngs_modulus})
    glued = _variant(scene, object={"pin_height": 0.004})
    cfg = copy.deepcopy(scene.config)
    cfg["friction"] = 0.5 + float(scene.friction)  # a top-level key
    rough = build_scene(scene.name, scene.resolution, cfg, SCENE_DIR)
    assert len(glued.pinned) > len(scene.pinned)
    assert same.physics_fingerprint() == scene.physics_fingerprint()
    others = [v.physics_fingerprint() for v in (stiffer, glued, rough)]
    assert len({scene.physics_fingerprint(), *others}) == 4
    # The mesh is the same, so only the physics fingerprint can tell the data apart.
    assert {v.object.fingerprint() for v in (stiffer, glued, rough)} == {scene.object.fingerprint()}


def test_a_dhat_one_ulp_apart_is_the_same_physics_and_the_exact_float_fingerprint_is_still_accepted(dataset, tmp_path):
    """Another numpy build computes the bounding-box diagonal, hence dhat, one ulp apart (session 30's device run):
    the fingerprint must not change. Data recorded before session 30 carries the exact-float fingerprint: training
    and a resumed `generate` accept it."""
    scene = load_scene(SCENE, "ci")
    apart = dataclasses.replace(scene, dhat=float(np.nextafter(scene.dhat, 1.0)))
    assert apart.dhat != scene.dhat and apart.physics_fingerprint() == scene.physics_fingerprint()
    legacy = scene.physics_fingerprint(exact=True)
    assert legacy != scene.physics_fingerprint() and scene.accepts_physics(legacy)
    stiffer = _variant(scene, material={"youngs_modulus": scene.material.youngs_modulus * (1 + 1e-9)})
    assert not scene.accepts_physics(stiffer.physics_fingerprint())
    assert not scene.accepts_physics(stiffer.physics_fingerprint(exact=True))
    out, manifest = dataset
    out = Path(shutil.copytree(out, tmp_path / "data"))
    check_manifest(dict(manifest, physics_fingerprint=legacy), scene, "ds")
    # a resumed generate keeps a sequence that records the exact-float fingerprint
    path = sorted(out.glob("train_*.npz"))[0]
    z = dict(np.load(path, allow_pickle=False))
    z["physics_fingerprint"] = np.asarray(legacy)
    np.savez_compressed(path, **z)
    listed = json.loads((out / "manifest.json").read_text())  # as written then: the file's own digest
    listed["sequences"][path.name]["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    (out / "manifest.json").write_text(json.dumps(listed))
    mtime = path.stat().st_mtime_ns
    m = generate_dataset(SCENE, "ci", out, sequences=2, frames=4, test_sequences=1, progress=False)
    assert path.stat().st_mtime_ns == mtime and path.name in m["sequences"]


def test_training_refuses_data_simulated_with_other_physics(dataset):
    out, manifest = dataset
    scene = load_scene(SCENE, "ci")
    check_manifest(manifest, scene, "ds")  # the scene it was made with
    stiffer = _variant(scene, material={"youngs_modulus": 2 * scene.material.youngs_modulus})
    with pytest.raises(InputError, match="other 'cylinder_banana' physics"):
        check_manifest(manifest, stiffer, "ds")


def test_generate_redoes_a_corrupted_sequence(tmp_path):
    generate_dataset(SCENE, "ci", tmp_path, sequences=1, frames=3, split="train", progress=False)
    path = tmp_path / "train_0000.npz"
    good = path.read_bytes()
    path.write_bytes(good[: len(good) // 2])
    m = generate_dataset(SCENE, "ci", tmp_path, sequences=1, frames=3, split="train", progress=False)
    assert load_sequence(path).frames == 3
    assert m["sequences"]["train_0000.npz"]["sha256"] != ""


def test_shards_split_the_jobs(tmp_path):
    m = generate_dataset(SCENE, "ci", tmp_path, sequences=2, frames=3, split="train", shard=(1, 2), progress=False)
    assert sorted(m["sequences"]) == ["train_0001.npz"]
    assert parse_shard("1/2") == (1, 2)
    for bad in ("2/2", "x", "1/0", "-1/3"):
        with pytest.raises(InputError):
            parse_shard(bad)


def test_generate_from_given_poses(tmp_path):
    scene = load_scene(SCENE, "ci")
    poses = sample_poses(scene, 9, 4)
    m = generate_dataset(SCENE, "ci", tmp_path, poses=poses, progress=False)
    seq = load_sequence(tmp_path / "custom_0000.npz")
    assert np.allclose(seq.tool_poses, poses)
    assert m["sequences"]["custom_0000.npz"]["seed"] is None


def test_poses_outside_the_workspace_are_rejected(tmp_path):
    scene = load_scene(SCENE, "ci")
    poses = sample_poses(scene, 0, 3)
    poses[2, 2] = scene.workspace_max[2] + 0.5
    with pytest.raises(InputError, match="workspace"):
        simulate_sequence(scene, poses)
    with pytest.raises(InputError, match="workspace"):
        generate_dataset(SCENE, "ci", tmp_path, poses=poses, progress=False)
    assert not list(tmp_path.glob("*.npz"))


def test_bad_arguments_are_input_errors(tmp_path):
    with pytest.raises(InputError):
        generate_dataset("no_such_scene", "ci", tmp_path, progress=False)
    with pytest.raises(InputError):
        generate_dataset(SCENE, "huge", tmp_path, progress=False)
    with pytest.raises(InputError):
        generate_dataset(SCENE, "ci", tmp_path, frames=1, progress=False)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(InputError):
        generate_dataset(SCENE, "ci", blocker / "sub", progress=False)


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_folder_is_an_input_error(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    with pytest.raises(InputError):
        generate_dataset(SCENE, "ci", ro, sequences=1, frames=2, progress=False)


def test_failing_sequences_are_replaced_then_reported(tmp_path):
    from colgnn_core.errors import SimulationError

    # One Newton iteration per step cannot settle the banana: every seed fails, none is saved.
    with pytest.raises(SimulationError, match="train_0000.npz"):
        generate_dataset(SCENE, "ci", tmp_path, sequences=1, frames=3, split="train", progress=False,
                         sim_options={"max_newton": 1}, max_retries=1)
    assert not list(tmp_path.glob("*.npz"))
    failed = json.loads((tmp_path / "manifest.json").read_text())["failed"]["train_0000.npz"]
    assert len(failed["job"]["seeds"]) == 2 and len(failed["rejected_seeds"]) == 2


def test_a_failed_job_is_remembered_and_not_simulated_again(tmp_path):
    from colgnn_core.errors import SimulationError

    args = dict(sequences=1, frames=3, split="train", progress=False, sim_options={"max_newton": 1}, max_retries=0)
    with pytest.raises(SimulationError) as first:
        generate_dataset(SCENE, "ci", tmp_path, **args)
    assert "recorded in" not in str(first.value)
    with pytest.raises(SimulationError, match="recorded in manifest.json"):
        generate_dataset(SCENE, "ci", tmp_path, **args)          # skipped: same seeds, frames and options
    with pytest.raises(SimulationError) as again:
        generate_dataset(SCENE, "ci", tmp_path, retry_failed=True, **args)
    assert "recorded in" not in str(again.value)
    # Different settings are a different job: simulated, and its success clears the failure record.
    generate_dataset(SCENE, "ci", tmp_path, sequences=1, frames=3, split="train", progress=False)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert "failed" not in manifest and "train_0000.npz" in manifest["sequences"]


def _partial_done(path: Path) -> int:
    """The last frame saved in a partial file; -1 while it is absent or being replaced."""
    try:
        with np.load(path) as z:
            return int(z["done"])
    except (OSError, ValueError, KeyError, EOFError):
        return -1


def test_an_interrupted_generate_continues_from_its_partial_file(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    from colgnn_core.io import write_poses_csv
    from colgnn_core.sim.partial import partial_path

    scene = load_scene(SCENE, "ci")
    poses = sample_poses(scene, 4, 24)
    csv = tmp_path / "poses.csv"
    write_poses_csv(csv, np.arange(len(poses)) * scene.dt, poses)
    out = tmp_path / "out"
    partial = partial_path(out / "custom_0000.npz")
    # A real process, killed without warning once it has saved a few frames (as a session's end kills a solver).
    proc = subprocess.Popen([sys.executable, "-m", "colgnn_core", "generate", "--scene", SCENE, "--resolution", "ci",
                             "--poses", str(csv), "--out", str(out), "--save-every", "0", "--quiet"])
    try:
        deadline = time.monotonic() + 120
        while _partial_done(partial) < 3 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    saved = _partial_done(partial)
    assert 3 <= saved < len(poses) - 1 and not (out / "custom_0000.npz").exists()
    with np.load(partial) as z:
        saved_ms = z["step_ms"].copy()

    m = generate_dataset(SCENE, "ci", out, poses=poses, progress=False)
    seq = load_sequence(out / "custom_0000.npz")
    assert not partial.exists() and m["sequences"]["custom_0000.npz"]["frames"] == len(poses)
    # Frames up to the saved one were taken from the file, not solved again (their solve times are the saved ones).
    assert np.array_equal(seq.extra["step_ms"][: saved + 1], saved_ms)
    assert np.all(seq.extra["step_ms"][saved + 1:] > 0)
    whole = simulate_sequence(scene, poses)
    assert np.array_equal(seq.object_positions[: saved + 1], whole.object_positions[: saved + 1])
    # After the restart: the same trajectory to the linear solver's tolerance (far below the 1e-3 m contact scale).
    assert np.abs(seq.object_positions - whole.object_positions).max() < 1e-6
    assert np.allclose(seq.tool_positions, whole.tool_positions)


def test_a_partial_file_of_other_poses_is_not_continued(tmp_path):
    from colgnn_core.sim.partial import partial_path

    scene = load_scene(SCENE, "ci")
    partial = partial_path(tmp_path / "seq.npz")
    a, b = sample_poses(scene, 3, 4), sample_poses(scene, 6, 4)
    simulate_sequence(scene, a, partial=partial, partial_every_s=0)
    assert _partial_done(partial) == 3
    got = simulate_sequence(scene, b, partial=partial, partial_every_s=0)
    assert np.array_equal(got.object_positions, simulate_sequence(scene, b).object_positions)
    # A whole saved sequence of the same poses is taken as it is: no frame is solved again.
    again = simulate_sequence(scene, b, partial=partial)
    assert np.array_equal(again.extra["step_ms"], got.extra["step_ms"])
    partial.write_bytes(b"not an npz")
    assert np.array_equal(simulate_sequence(scene, b, partial=partial).object_positions, got.object_positions)
    with pytest.raises(InputError, match="partial_every_s"):
        generate_dataset(SCENE, "ci", tmp_path, poses=b, progress=False, partial_every_s=-1)


def worker_thread_counts(_: int) -> tuple[int, int, int, int]:
    """In a worker: the thread counts of ipctk, numba, torch and the BLAS pools (the largest)."""
    import ipctk
    import numba
    import torch
    from threadpoolctl import threadpool_info

    blas = max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
    return ipctk.get_num_threads(), numba.get_num_threads(), torch.get_num_threads(), blas


def test_local_workers_share_the_cores_out():
    import multiprocessing as mp

    from colgnn_core.sim.dataset import limit_worker_threads, worker_threads

    assert worker_threads(2, cpu_count=2) == 1 and worker_threads(3, cpu_count=2) == 1
    assert worker_threads(2, cpu_count=16) == 8 and worker_threads(1, cpu_count=4) == 4
    # a spawned worker as `generate --jobs` starts it: every pool the solver uses is down to its share
    with mp.get_context("spawn").Pool(1, initializer=limit_worker_threads, initargs=(1,)) as pool:
        assert pool.map(worker_thread_counts, [0]) == [(1, 1, 1, 1)]
