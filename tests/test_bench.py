"""colgnn bench: the contract fields, measured on a tiny trained model against the IPC solver in one run."""

import json
import math

import numpy as np
import pytest

from colgnn_core.cli import main
from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import rmse_fraction
from colgnn_core.evaluation.speed import bench, format_bench, timed_rollout
from colgnn_core.evaluation.speed_page import speed_markdown
from tests.helpers import train_data as fx

CONTRACT = ("total_ms", "graph_ms", "gnn_ms", "correction_ms", "ipc_ms")


def test_bench_reports_the_contract_fields():
    r = bench(fx.SCENE, checkpoint=str(fx.trained_checkpoint("full")), frames=6, threads=1)
    for key in CONTRACT:
        assert set(r[key]) == {"median", "p95"} and 0 <= r[key]["median"] <= r[key]["p95"]
    assert r["total_ms"]["median"] >= r["gnn_ms"]["median"] > 0
    assert r["ipc_ms"]["median"] > 0
    assert r["speedup_vs_ipc"] == pytest.approx(r["ipc_ms"]["median"] / r["total_ms"]["median"])
    assert all(math.isfinite(v) and v >= 0 for v in r["rollout_rmse"].values())
    scene = fx.scene()
    assert (r["vertices"], r["edges"], r["faces"], r["threads"]) == (
        len(scene.object.vertices), len(scene.object.edges), len(scene.object.faces), 1)
    assert r["crossings_after_correction"] == 0
    assert r["kernel_threads_reduced_steps"] == 0  # one thread asked for: nothing to reduce
    assert "speedup vs IPC" in format_bench(r)
    json.dumps(r)  # JSON-ready


def test_bench_warms_up_as_the_node_does_and_the_warm_up_changes_no_result():
    """The timed steps follow a warm-up (the node's, before it serves) unless asked cold; the warm-up resets the
    Predictor, so both runs publish the same shapes and counts."""
    warm = bench(fx.SCENE, checkpoint=str(fx.trained_checkpoint("full")), frames=5, threads=1, rollouts=3)
    cold = bench(fx.SCENE, checkpoint=str(fx.trained_checkpoint("full")), frames=5, threads=1, warm_up=False)
    assert warm["warm_up_s"] > 0 and cold["warm_up_s"] == 0.0
    assert warm["rollouts"] == 3 and len(warm["rollout_medians_ms"]) == 3 and cold["rollout_medians_ms"] == [
        cold["total_ms"]["median"]]
    assert min(warm["rollout_medians_ms"]) <= warm["total_ms"]["median"] <= max(warm["rollout_medians_ms"])
    for key in ("relative_displacement_error", "rollout_rmse", "crossings_before_correction",
                "crossings_after_correction", "fallbacks"):
        assert warm[key] == cold[key], key
    page = speed_markdown([warm], "colgnn bench")
    assert "warmed up right before its timed steps" in page and "timed over 3 passes" in page
    lo, hi = min(warm["rollout_medians_ms"]), max(warm["rollout_medians_ms"])
    assert f"; passes {lo:.1f}-{hi:.1f} |" in page
    assert "timed cold" in speed_markdown([cold], "colgnn bench --cold")
    with pytest.raises(InputError, match="rollouts must be >= 1"):
        bench(fx.SCENE, checkpoint=str(fx.trained_checkpoint("full")), frames=5, rollouts=0)


def test_timed_passes_of_one_trajectory_publish_the_same_shapes():
    """``bench --rollouts``: each pass restarts from frame 0, and the Predictor is deterministic, so every pass
    times the same steps."""
    from colgnn_core.evaluation.measure import family_poses
    from colgnn_core.runtime.predictor import Predictor

    p = Predictor.from_checkpoint(str(fx.trained_checkpoint("full")), threads=1)
    poses = family_poses(p.scene, 6)
    first, second = (timed_rollout(p, poses, p.rest_mesh) for _ in range(2))
    np.testing.assert_array_equal(first["positions"], second["positions"])
    assert first["crossings_before"] == second["crossings_before"]


def test_rmse_fraction_by_hand():
    truth = np.zeros((2, 2, 3))
    pred = truth.copy()
    pred[1, 0] = [3.0, 4.0, 0.0]  # one of two vertices off by 5 m at frame 1
    np.testing.assert_allclose(rmse_fraction(pred, truth, 10.0), [0.0, np.sqrt(25 / 2) / 10])


def test_bench_bad_input(capsys):
    with pytest.raises(InputError, match="unknown scene"):
        bench("jelly", frames=5)
    assert main(["bench", "--scene", "cone_bunny", "--checkpoint", str(fx.trained_checkpoint("full")),
                 "--frames", "2"]) == 2
    assert "frames must be >= 3" in capsys.readouterr().err


def test_collision_bench_cli_reports_both_timings_and_no_missed_hit(capsys):
    """`colgnn bench --collision`: ours vs ipctk on the same step, in one run (timings only reported)."""
    assert main(["bench", "--collision", "--scene", "cone_bunny", "--resolution", "ci", "--repeats", "3",
                 "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["ipctk_hits_culled_by_filter"] == 0
    assert sum(r["candidates"].values()) > 0 and r["crossings"] == r["ipctk_hits"]
    assert 0 < r["broad_ms"] < r["ours_ms"] and r["ipctk_pairs_ms"] > 0
    assert r["speedup_vs_ipctk_pairs"] == pytest.approx(r["ipctk_pairs_ms"] / r["ours_ms"])
    assert main(["bench", "--collision", "--scene", "cone_bunny", "--resolution", "ci", "--repeats", "2"]) == 0
    assert "speed-up vs ipctk same pairs" in capsys.readouterr().out


def test_bench_markdown_writes_the_speed_page_from_its_own_run(tmp_path, capsys):
    page = tmp_path / "SPEED.md"
    assert main(["bench", "--scene", fx.SCENE, "--checkpoint", str(fx.trained_checkpoint("full")), "--frames", "4",
                 "--threads", "1", "--json", "--markdown", str(page)]) == 0
    out = capsys.readouterr().out
    r = json.loads((tmp_path / "bench" / f"{fx.SCENE}.json").read_text())
    assert json.loads(out[: out.rindex("}") + 1]) == r  # the page's JSON is the run's, not an older one
    text = page.read_text()
    assert "Generated by `colgnn bench --scene cone_bunny" in text and "--markdown" in text and " cores" in text
    assert f"**{r['total_ms']['median']:.1f}** ({r['total_ms']['p95']:.1f}) ms" in text
    assert f"{r['speedup_vs_ipc']:.0f}×" in text and text.count(f"| `{fx.SCENE}` (") == 1
    assert "collision kernels ran on 1 thread" not in text  # 1 thread asked for: nothing was reduced
    busy = dict(r, kernel_threads_reduced_steps=2)
    assert f"ran on 1 thread in `{fx.SCENE}` 2 of 3 steps" in speed_markdown([busy], "colgnn bench")
    assert main(["bench", "--scene", "all", "--frames", "4"]) == 2  # all scenes only into a page
    assert "--scene all needs --markdown" in capsys.readouterr().err


def test_stability_markdown_writes_one_row_per_scene_and_keeps_the_prose(tmp_path, capsys):
    """`colgnn bench --stability --markdown`: the scene's JSON (with its command and code version) beside the page,
    and the page's generated block rebuilt from every JSON there; hand-written prose outside the block stays."""
    page = tmp_path / "README.md"
    page.write_text("# Stability\n\nProse that stays.\n\n<!-- begin stability -->\nold table\n<!-- end stability -->\n"
                    "\nClosing prose.\n")
    (tmp_path / "other.json").write_text(json.dumps({
        "scene": "other", "resolution": "ci", "random_steps": 5, "leave_and_settle_steps": 2,
        "tool_intersecting_frames": 0, "checked_frames": 3, "self_intersecting_frames": 1, "fallbacks": 0,
        "rss_mb_start": 100.0, "rss_mb_end": 101.0, "rss_mb_per_1000_steps": 0.5, "rest_rmse_fraction": 0.001,
        "rest_max_fraction": 0.002, "step_ms_median": 3.0, "threads": 1, "wall_s": 60.0}))
    assert main(["bench", "--stability", "--scene", fx.SCENE, "--checkpoint", str(fx.trained_checkpoint("full")),
                 "--steps", "12", "--threads", "1", "--json", "--markdown", str(page)]) == 0
    out = capsys.readouterr().out
    r = json.loads((tmp_path / f"{fx.SCENE}.json").read_text())
    assert r["command"].startswith("colgnn bench --stability --scene cone_bunny") and r["code"] != "unknown"
    assert r["steps_done"] == json.loads(out[: out.rindex("}") + 1])["steps_done"]
    text = page.read_text()
    assert text.startswith("# Stability\n\nProse that stays.\n") and text.rstrip().endswith("Closing prose.")
    assert "old table" not in text and text.count("<!-- begin stability -->") == 1
    assert f"| `{fx.SCENE}` (ci) | no | 12 + {r['leave_and_settle_steps']} |" in text
    assert f"| {r['tool_intersecting_frames']} ({r['checked_frames']}) |" in text
    assert "| `other` (ci) | no | 5 + 2 | 0 (3) | 1 | – |" in text and "not recorded" in text
    assert r["machine"].endswith(" cores)") and f"| {r['machine']} | {r['code']} " in text  # each row its machine
    assert main(["bench", "--stability", "--scene", "all", "--markdown", str(page)]) == 2
    assert "one scene at a time" in capsys.readouterr().err


def test_the_code_version_stays_the_one_the_process_started_with(tmp_path):
    """A long run stamps its page at the end: a commit made meanwhile is not the code it ran."""
    import subprocess

    from colgnn_core.evaluation.provenance import code_version

    def git(*a):
        return subprocess.run(["git", "-C", str(tmp_path), *a], capture_output=True, text=True, check=True).stdout

    git("init", "-q")
    git("config", "user.email", "t@example.com")
    git("config", "user.name", "t")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("commit", "-q", "-m", "one")
    first = code_version(tmp_path)
    assert first == git("rev-parse", "--short", "HEAD").strip()
    (tmp_path / "a.py").write_text("x = 2\n")
    git("commit", "-q", "-am", "two")
    assert git("rev-parse", "--short", "HEAD").strip() != first
    assert code_version(tmp_path) == first
