"""The colgnn command line: contract fields and exit code 2 on bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest

from colgnn_core.cli import main
from colgnn_core.io import write_poses_csv

CONTRACT_FIELDS = {
    "name", "dt", "object_bbox_min", "object_bbox_max", "tool_shape", "tool_rest_pose",
    "workspace_min", "workspace_max", "object_vertices", "object_faces",
}


def test_scenes_json_has_contract_fields(capsys):
    assert main(["scenes", "--json", "--resolution", "ci"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert sorted(r["name"] for r in rows) == ["cone_bunny", "cylinder_banana", "knife_torus", "sphere_mat"]
    for r in rows:
        assert CONTRACT_FIELDS <= set(r)
        assert r["dt"] == pytest.approx(0.04)
        assert len(r["tool_rest_pose"]) == 7
        assert all(lo < hi for lo, hi in zip(r["object_bbox_min"], r["object_bbox_max"]))


def test_unknown_scene_exits_2(capsys):
    assert main(["generate", "--scene", "jelly_spoon", "--out", "unused", "--resolution", "ci"]) == 2
    err = capsys.readouterr().err
    assert "jelly_spoon" in err and "sphere_mat" in err
    assert len(err.strip().splitlines()) == 1


def test_module_entry_point_exit_code():
    proc = subprocess.run([sys.executable, "-m", "colgnn_core", "render", "missing.npz", "--out", "x.png"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "missing.npz" in proc.stderr


def test_generate_bad_shard_exits_2_with_the_rule(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["generate", "--scene", "sphere_mat", "--resolution", "ci", "--out", str(tmp_path / "o"), "--shard",
              "3/2"])
    assert exc.value.code == 2
    assert "0 <= I < N" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "body, message",
    [
        ("t,px,py,pz,qx,qy,qw\n0,0,0,0,0,0,1\n", "missing column"),
        ("t,px,py,pz,qx,qy,qz,qw\n0,0,0,nan,0,0,0,1\n", "NaN"),
        ("t,px,py,pz,qx,qy,qz,qw\n0,0,0,0,0,0,0.5,0.5\n", "not unit length"),
    ],
)
def test_generate_malformed_poses_exits_2(tmp_path, capsys, body, message):
    (tmp_path / "p.csv").write_text(body)
    code = main(["generate", "--scene", "sphere_mat", "--resolution", "ci", "--out", str(tmp_path / "o"), "--poses",
                 str(tmp_path / "p.csv")])
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_generate_pose_outside_workspace_exits_2(tmp_path, capsys):
    write_poses_csv(tmp_path / "p.csv", np.array([0.0, 0.04]), np.array([[0, 0, 0.3, 0, 0, 0, 1.0], [0, 0, 50.0, 0, 0,
                                                                                                     0, 1.0]]))
    code = main(["generate", "--scene", "sphere_mat", "--resolution", "ci", "--out", str(tmp_path / "o"), "--poses",
                 str(tmp_path / "p.csv")])
    assert code == 2
    assert "workspace" in capsys.readouterr().err


def test_generate_unwritable_output_exits_2(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    code = main(["generate", "--scene", "sphere_mat", "--resolution", "ci", "--out", str(blocker / "o"), "--sequences",
                 "1", "--frames", "2"])
    assert code == 2
    assert "output folder" in capsys.readouterr().err


def test_generate_test_split_only(tmp_path, capsys):
    """`make results` simulates only held-out test sequences: --split test."""
    out = tmp_path / "d"
    assert main(["generate", "--scene", "cone_bunny", "--resolution", "ci", "--split", "test", "--sequences", "1",
                 "--frames", "3", "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in out.glob("*.npz")) == ["test_0000.npz"]
    assert "1 sequence(s)" in capsys.readouterr().out


def test_train_model_options_reach_the_checkpoint(tmp_path, capsys):
    from colgnn_core.learn.registry import load_checkpoint
    from tests.helpers import train_data as fx

    out = tmp_path / "qs.pt"
    assert main(["train", "--scene", fx.SCENE, "--data", str(fx.dataset_dir()), "--out", str(out), "--steps", "3",
                 "--variant", "baseline", "--model", "8/1/1", "--quiet", "--threads", "1",
                 "--model-options", '{"order": 0, "quasi_static": true, "coarse_nodes": 8, "coarse_steps": 1, '
                 '"global_modes": 4, "contact_depth": true, "tip_prior": true}']) == 0
    sim = load_checkpoint(out).simulator
    cfg = sim.config
    assert (cfg.order, cfg.quasi_static, cfg.latent, cfg.message_passing_steps) == (0, True, 8, 1)
    assert (cfg.coarse_nodes, cfg.coarse_steps, cfg.global_modes, cfg.contact_depth) == (8, 1, 4, True)
    assert cfg.tip_prior
    # the modes were fitted to the training displacements and saved: each one a unit-RMS-coefficient field
    norms = sim.global_modes.reshape(4, -1).norm(dim=1)
    assert bool((norms > 0).all()) and norms[0] >= norms[-1]
    # the node's default (compiled) runs such a model: the warm-up keeps the coarse level's edges
    from colgnn_core.runtime.predictor import Predictor

    p = Predictor.from_checkpoint(str(out), threads=1, compile=True)
    assert p.compiled and p.step(p.scene.tool_rest_pose).positions.shape == p.scene.object.vertices.shape
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["train", "--scene", fx.SCENE, "--data", str(tmp_path), "--out", str(out), "--model-options", "[1]"])
    assert "expected a JSON object" in capsys.readouterr().err
    assert main(["train", "--scene", fx.SCENE, "--data", str(fx.dataset_dir()), "--out", str(tmp_path / "b.pt"),
                 "--steps", "2", "--quiet", "--model-options", '{"quasi_static": true, "order": 2}']) == 2
    assert "quasi_static needs order 0" in capsys.readouterr().err


def test_train_learning_rates_reach_the_checkpoint(tmp_path, capsys):
    """``--lr INIT[:FINAL]``: the run's schedule (FINAL defaults to INIT / 100); anything else is refused."""
    from colgnn_core.learn.checkpoint import read_checkpoint
    from tests.helpers import train_data as fx

    base = ["train", "--scene", fx.SCENE, "--data", str(fx.dataset_dir()), "--steps", "2", "--quiet",
            "--threads", "1", "--variant", "baseline", "--model", "8/1/1"]
    for given, want in (("2e-4", (2e-4, 2e-6)), ("3e-4:1e-6", (3e-4, 1e-6))):
        out = tmp_path / f"{given}.pt"
        assert main(base + ["--out", str(out), "--lr", given]) == 0
        cfg = read_checkpoint(out)["extra"]["train_config"]
        assert (cfg["lr_init"], cfg["lr_final"]) == pytest.approx(want)
    for bad in ("0", "1e-3:-1", "fast", "1:2:3"):
        with pytest.raises(SystemExit):
            main(base + ["--out", str(tmp_path / "bad.pt"), "--lr", bad])
        assert "INIT" in capsys.readouterr().err
    assert not (tmp_path / "bad.pt").exists()


def test_train_validity_weight_reaches_the_checkpoint_and_its_command(tmp_path, capsys):
    """``--validity-weight W``: L_valid in the run's loss (logged) and in the model card's rebuilt command."""
    from colgnn_core.evaluation.model_card import read_card
    from colgnn_core.learn.checkpoint import read_checkpoint
    from tests.helpers import train_data as fx

    out = tmp_path / "valid.pt"
    base = ["train", "--scene", fx.SCENE, "--data", str(fx.dataset_dir()), "--steps", "3", "--quiet",
            "--threads", "1", "--variant", "baseline", "--model", "8/1/1"]
    assert main(base + ["--out", str(out), "--validity-weight", "5"]) == 0
    extra = read_checkpoint(out)["extra"]
    assert extra["train_config"]["w_valid"] == 5.0
    assert read_card(out, tmp_path).command.endswith(" --validity-weight 5")
    for bad in ("-1", "inf", "x"):
        with pytest.raises(SystemExit):
            main(base + ["--out", str(tmp_path / "bad.pt"), "--validity-weight", bad])
        assert "--validity-weight" in capsys.readouterr().err
    assert not (tmp_path / "bad.pt").exists()
