"""``colgnn evaluate`` on the tiny trained model and tiny real dataset of tests.helpers.train_data."""

import json
import math

import numpy as np
import pytest
import torch

from colgnn_core.cli import main
from colgnn_core.errors import InputError
from colgnn_core.evaluation.accuracy import evaluate
from colgnn_core.evaluation.measure import finite, rmse_fraction
from colgnn_core.io import load_sequence
from colgnn_core.runtime.rollout import rollout
from tests.helpers import train_data as fx

torch.set_num_threads(1)

CROSSING = ("N_vf", "d_vf_mean", "d_vf_max", "N_ee", "d_ee_mean", "d_ee_max")


@pytest.fixture(scope="module")
def result():
    out = fx.tmp_dir("evaluate")
    return evaluate(fx.SCENE, checkpoint=fx.trained_checkpoint("full"), data_dir=fx.dataset_dir(), out_dir=out,
                    progress=False)


def test_evaluate_reports_finite_metrics_and_writes_the_files(result):
    for key in ("json", "markdown", "plot"):
        assert (fx.tmp_dir("evaluate") / result["files"][key].split("/")[-1]).is_file()
    data = json.loads((fx.tmp_dir("evaluate") / "metrics.json").read_text())
    assert data["scene"] == fx.SCENE and data["resolution"] == "ci" and data["modes"] == ["raw", "corrected"]
    assert data["sequences"] == [p.name for p in sorted(fx.dataset_dir().glob("test_*.npz"))]
    assert set(data["rows"]) == {"ground_truth", "raw", "corrected"}
    assert finite(data)
    for key, row in data["rows"].items():
        c = row["collisions"]
        for k in CROSSING + ("intersecting_frames", "frames", "steps"):
            assert k in c and np.isfinite(c[k]) and c[k] >= 0
        if key == "ground_truth":
            assert row["rmse"] is None
            continue
        r = row["rmse"]
        for k in ("step_1", "step_10", "all"):
            assert np.isfinite(r[k]["mean"]) and np.isfinite(r[k]["std"]) and r[k]["n"] == len(data["sequences"])
        assert r["step_50"]["n"] == 0 and r["step_50"]["mean"] is None  # FRAMES < 51
        assert len(r["curve"]["mean"]) == fx.FRAMES
    # the solver's ground truth never crosses or penetrates the tool
    gt = data["rows"]["ground_truth"]["collisions"]
    assert gt["N_vf_total"] == 0 and gt["N_ee_total"] == 0 and gt["intersecting_frames"] == 0
    md = (fx.tmp_dir("evaluate") / "metrics.md").read_text()
    assert "| ground truth |" in md and "| raw network |" in md and "| corrected |" in md and "RMSE@10" in md
    assert (fx.tmp_dir("evaluate") / "rmse_over_time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_surface_validity_is_checked_every_10th_frame_and_catches_a_fold(result):
    from colgnn_core.collision.surface_validity import SurfaceValidity
    from colgnn_core.evaluation.accuracy import SURFACE_CHECK_EVERY, surface_checks

    frames = fx.FRAMES
    expected = len(set(range(0, frames, SURFACE_CHECK_EVERY)) | {frames - 1}) * len(result["sequences"])
    gt = result["rows"]["ground_truth"]["surface"]
    every = frames * len(result["sequences"])
    assert gt == {"checked_frames": expected, "self_intersecting_frames": 0, "invalid_face_frames": 0,
                  "frames": every, "invalid_face_frames_all": 0}
    for mode in ("raw", "corrected"):
        s = result["rows"][mode]["surface"]
        assert s["checked_frames"] == expected and s["frames"] == every
        assert s["invalid_face_frames"] <= s["invalid_face_frames_all"] <= every
    md = (fx.tmp_dir("evaluate") / "metrics.md").read_text()
    assert f"| ground truth | 0/{expected} | 0/{expected} | 0/{every} |" in md and "| ratio |" in md
    # a fold: one surface vertex pushed through the object to the far side flips its faces and crosses the surface
    seq = load_sequence(sorted(fx.dataset_dir().glob("test_*.npz"))[0])
    x = seq.object_positions[:11].copy()
    faces = seq.object_faces
    v = int(faces[0, 0])
    centre = x[0].mean(0)
    x[10, v] = centre + 1.5 * (centre - x[0, v])
    x[3, v] = x[10, v]  # the same fold at frame 3, between two checked frames: only the every-frame test sees it
    checks = surface_checks(x, faces, SurfaceValidity(faces, x[0]))
    assert checks == {"checked_frames": 2, "self_intersecting_frames": 1, "invalid_face_frames": 1, "frames": 11,
                      "invalid_face_frames_all": 2}


def test_rmse_matches_a_hand_computation(result):
    scene, ckpt = fx.scene(), fx.trained_checkpoint("full")
    step1 = []
    for path, rec in zip(sorted(fx.dataset_dir().glob("test_*.npz")), result["per_sequence"]):
        gt = load_sequence(path)
        seq = rollout(ckpt, gt.tool_poses, scene=scene, initial_positions=gt.object_positions[0])
        err = rmse_fraction(seq.object_positions, gt.object_positions, scene.bbox_diagonal())
        assert rec["file"] == path.name and rec["raw"]["rmse"][0] == 0.0  # same frame 0 by construction
        np.testing.assert_allclose(rec["raw"]["rmse"][1], err[1], rtol=1e-12, atol=0)
        np.testing.assert_allclose(rec["raw"]["rmse_all"], err[1:].mean(), rtol=1e-12, atol=0)
        step1.append(err[1])
    raw = result["rows"]["raw"]["rmse"]
    assert raw["curve"]["mean"][0] == 0.0 and raw["step_1"]["mean"] == pytest.approx(np.mean(step1), rel=1e-12)
    assert raw["step_1"]["std"] == pytest.approx(np.std(step1), rel=1e-9, abs=1e-15)


def test_missing_data_is_an_input_error(tmp_path, capsys):
    with pytest.raises(InputError, match="--data"):
        evaluate(fx.SCENE, checkpoint=fx.trained_checkpoint("full"), data_dir=None, out_dir=tmp_path)
    with pytest.raises(InputError, match="no such dataset folder"):
        evaluate(fx.SCENE, checkpoint=fx.trained_checkpoint("full"), data_dir=tmp_path / "nope", out_dir=tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="test_XXXX"):
        evaluate(fx.SCENE, checkpoint=fx.trained_checkpoint("full"), data_dir=empty, out_dir=tmp_path)
    with pytest.raises(InputError, match="not 'sphere_mat'"):
        evaluate("sphere_mat", checkpoint=fx.trained_checkpoint("full"), data_dir=fx.dataset_dir(), out_dir=tmp_path)
    rc = main(["evaluate", "--scene", fx.SCENE, "--checkpoint", str(fx.trained_checkpoint("full")),
               "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "no such dataset folder" in capsys.readouterr().err
    rc = main(["evaluate", "--scene", fx.SCENE, "--checkpoint", str(fx.trained_checkpoint("full")),
               "--out", str(tmp_path / "o")])
    assert rc == 2 and "--data" in capsys.readouterr().err


def test_cli_raw_only_narrow_phase(tmp_path, capsys):
    rc = main(["evaluate", "--scene", fx.SCENE, "--checkpoint", str(fx.trained_checkpoint("full")),
               "--data", str(fx.dataset_dir()), "--out", str(tmp_path), "--no-exact", "--no-correction",
               "--max-sequences", "1", "--quiet"])
    assert rc == 0 and "| raw network |" in capsys.readouterr().out
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["modes"] == ["raw"] and not data["exact"] and len(data["sequences"]) == 1
    assert set(data["rows"]) == {"ground_truth", "raw"} and (tmp_path / "rmse_over_time.png").is_file()
    # the report names the command that measured it, the machine and the load
    md = (tmp_path / "metrics.md").read_text()
    assert data["provenance"] in md and "Generated by `colgnn evaluate --scene cone_bunny" in md and " cores" in md


def test_frontier_points_table_and_plot(tmp_path, capsys):
    """--frontier: a raw and a corrected point per checkpoint plus the solver points, measured in one run."""
    ckpts = [str(fx.trained_checkpoint("full")), str(fx.trained_checkpoint("baseline"))]
    out = tmp_path / "frontier"
    assert main(["evaluate", "--frontier", "--scene", fx.SCENE, "--data", str(fx.dataset_dir()), "--out", str(out),
                 "--checkpoints", *ckpts, "--steps", "6", "--max-sequences", "1", "--threads", "1", "--quiet"]) == 0
    r = json.loads((out / "frontier.json").read_text())
    kinds = [p["kind"] for p in r["points"]]
    assert kinds == ["raw", "corrected", "raw", "corrected", "baseline", "ipc", "ipc", "ipc"]
    for p in r["points"]:
        assert p["ms_median"] > 0 and math.isfinite(p["rmse_last"]) and p["rmse_last"] >= 0
        assert 0 <= p["relative"] < 10 and 0 <= p["relative_contact"] < 10
    data_ipc = r["points"][5]
    assert data_ipc["label"] == "IPC (data settings)" and data_ipc["rmse_last"] < 1e-6  # it is the reference
    assert data_ipc["relative"] < 1e-6
    # the baseline point is the evaluate table's `rest + correction` row on the same frames
    base = r["points"][4]
    from colgnn_core.evaluation.measure import relative_displacement_error
    from colgnn_core.runtime.models import load_model, rest_baseline
    gt = load_sequence(sorted(fx.dataset_dir().glob("test_*.npz"))[0])
    loaded = load_model(ckpts[0])
    seq = rollout(rest_baseline(loaded, fx.scene()), gt.tool_poses[:7], correction=True, scene=fx.scene(),
                  initial_positions=gt.object_positions[0])
    truth = gt.object_positions[:7]
    assert base["label"] == "rest + correction (no network)"
    assert base["relative"] == pytest.approx(relative_displacement_error(seq.object_positions, truth, truth[0]),
                                             rel=1e-9)
    assert all(p["crossings"] == 0 and p["intersecting_frames"] == 0 for p in r["points"] if p["kind"] != "raw")
    assert (out / "frontier.png").stat().st_size > 10_000
    assert "| method | ms/step" in (out / "frontier.md").read_text() and "wrote" in capsys.readouterr().out
    with pytest.raises(InputError, match="at least one checkpoint"):
        from colgnn_core.evaluation.frontier import frontier

        frontier(fx.SCENE, [], fx.dataset_dir(), tmp_path)


def test_the_self_contact_stage_follows_the_scene_unless_asked(tmp_path):
    """cone_bunny leaves the self-contact stage off at ci (its TOML); --self-contact runs it in every corrected rollout,
    and the report says which was measured."""
    args = ["evaluate", "--scene", fx.SCENE, "--checkpoint", str(fx.trained_checkpoint("full")),
            "--data", str(fx.dataset_dir()), "--no-exact", "--max-sequences", "1", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "default")]) == 0
    assert main(args + ["--out", str(tmp_path / "on"), "--self-contact"]) == 0
    default, on = (json.loads((tmp_path / k / "metrics.json").read_text()) for k in ("default", "on"))
    assert default["self_contact"] is False and on["self_contact"] is True
    assert "self-contact stage off" in (tmp_path / "default" / "metrics.md").read_text()
    assert "self-contact stage on" in (tmp_path / "on" / "metrics.md").read_text()
