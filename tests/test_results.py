"""``colgnn evaluate --all`` (``make results``) end to end on the tiny trained models and tiny real data."""

import json
import shutil

import pytest
import torch

from colgnn_core.cli import main
from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import finite
from colgnn_core.evaluation.report import model_paths, results
from colgnn_core.evaluation.report_data import ResultsReport
from colgnn_core.evaluation.report_markdown import reduction
from tests.helpers import train_data as fx

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def report():
    models = fx.tmp_dir("results_models")
    shutil.copyfile(fx.trained_checkpoint("full"), models / f"{fx.SCENE}.pt")
    shutil.copyfile(fx.trained_checkpoint("baseline"), models / f"{fx.SCENE}_baseline.pt")
    (models / "frontier" / fx.SCENE).mkdir(parents=True, exist_ok=True)
    shutil.copyfile(fx.trained_checkpoint("no-compact"), models / "frontier" / fx.SCENE / "other.pt")
    data_root = fx.tmp_dir("results_data")
    # The fixture's test sequence is this command's test data (resumed, not re-simulated).
    shutil.copytree(fx.dataset_dir(), data_root / fx.SCENE, dirs_exist_ok=True)
    out = fx.tmp_dir("results_docs")
    return results(out, scenes=[fx.SCENE, "sphere_mat"], data_root=data_root, models_dir=models, test_sequences=1,
                   frames=fx.FRAMES, jobs=1, threads=1, compile=False, hard_frames=12, random_steps=30,
                   progress=False), out


def test_report_has_every_table_and_picture(report):
    rep, out = report
    md = (out / "RESULTS.md").read_text()
    data = json.loads((out / "results.json").read_text())
    assert finite(data)
    assert ResultsReport.from_dict(data).to_dict() == data  # the typed report reads and writes the file as it is
    for heading in ("## Table 1: speed", "## Table 2: collisions", "## Accuracy", "## Speed against error",
                    "## Hard cases", "## Pictures", "## Discussion"):
        assert heading in md
    s = data["scenes"][fx.SCENE]
    assert s["resumed_sequences"] == 1 and "1 sequence(s) resumed" in md
    assert data["code"] not in ("", "unknown") and f"code {data['code']}." in md  # the version it measured
    assert set(s["rows"]) == {"ground_truth", "baseline", "full", "full+correction"}
    assert "| subspace (Holden et al. 2019) | not shipped |" in md and "| no-compact (ablation) | not shipped |" in md
    # rows name their network size (the fixture's tiny model)
    size = "{latent}/{message_passing_steps}/{mlp_layers}".format(**fx.TINY_MODEL)
    assert s["model_sizes"] == {"full": size, "baseline": size}
    assert f"| full + correction (colgnn), {size} |" in md and f"| baseline (MeshGraphNets), {size} |" in md
    assert data["scenes"]["sphere_mat"]["skipped"].startswith("no shipped model")
    for key in ("errors", "comparison"):
        path = out / "img" / f"{fx.SCENE}_{'rmse' if key == 'errors' else key}.png"
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"img/{path.name}" in md
    assert "ablation" not in s["pictures"]  # no no-compact model
    # the IPC column: the solver re-run on the poses the Predictor was timed on
    sp = s["speed"]
    assert sp["ipc_ms"]["median"] > 0 and sp["total_ms"]["median"] > 0 and sp["steps"] == fx.FRAMES - 1
    assert abs(sp["speedup_vs_ipc"] - sp["ipc_ms"]["median"] / sp["total_ms"]["median"]) < 1e-9
    assert f"{sp['speedup_vs_ipc']:.0f}×" in md


def test_accuracy_leads_with_the_relative_error_and_both_trivial_baselines(report):
    """The report's accuracy table: the relative displacement error of each model row next to `rest` (exactly 1.0:
    nothing moves) and `rest + correction`, the same values as the per-model report of `colgnn evaluate`, and a
    discussion line that says whether the model beats them."""
    rep, out = report
    s = rep.scenes[fx.SCENE]
    assert list(s.relative) == ["baseline", "full", "full+correction", "node", "rest", "rest+correction"]
    assert s.relative["rest"]["all"].mean == pytest.approx(1.0) and s.relative["rest"]["contact"].mean == \
        pytest.approx(1.0)
    per_model = json.loads((out / "results" / fx.SCENE / "full" / "metrics.json").read_text())["relative"]
    assert s.relative["full+correction"]["all"].mean == pytest.approx(per_model["corrected"]["all"]["mean"])
    rc_contact = per_model["rest_correction"]["contact"]["mean"]
    assert s.relative["rest+correction"]["contact"].mean == pytest.approx(rc_contact)
    md = (out / "RESULTS.md").read_text()
    rc = s.relative["rest+correction"]
    assert (f"| **rest + correction (no network)** | {rc['all'].mean:.3f} ± {rc['all'].std:.3f} | "
            f"{rc['contact'].mean:.3f} ± {rc['contact'].std:.3f} |") in md
    assert "| rest (nothing moves) | 1.000 ± 0.000 | 1.000 ± 0.000 |" in md
    assert md.index("| rest (nothing moves) |") < md.index("| row | step 1 |")  # relative first, RMSE second
    m = s.relative["full+correction"]["all"].mean
    assert "**Fidelity.** " in md and f"{fx.SCENE}: {m:.2f} / " in md


def test_frontier_section_from_the_shipped_frontier_checkpoints(report):
    rep, out = report
    f = rep.scenes[fx.SCENE].frontier.result
    # the frontier checkpoint plus the scene's full and baseline models, raw and corrected; 3 solver settings
    assert [p.kind for p in f.points].count("raw") == 3 and [p.kind for p in f.points].count("ipc") == 3
    assert f.steps == fx.FRAMES - 1 and f.ipc_sequences == f.sequences[:1]
    assert all(p.crossings == 0 and p.intersecting_frames == 0 for p in f.points if p.kind != "raw")
    md = (out / "RESULTS.md").read_text()
    assert f"img/{fx.SCENE}_frontier.png" in md and (out / "img" / f"{fx.SCENE}_frontier.png").is_file()


def test_reported_reductions_match_the_measured_rows(report):
    rep, out = report
    rows = rep.scenes[fx.SCENE].rows
    base, full = rows["baseline"].collisions, rows["full"].collisions
    md = (out / "RESULTS.md").read_text()
    if base.N_vf > 0:
        r = reduction(full.N_vf, base.N_vf)
        assert abs(r - 100 * (base.N_vf - full.N_vf) / base.N_vf) < 1e-9
        assert f"{full.N_vf:.3f} ({-r:+.0f}%)" in md
    assert reduction(1.0, 4.0) == 75.0 and reduction(0.0, 0.0) is None and reduction(2.0, 1.0) == -100.0


def test_correction_row_and_hard_cases_are_clean(report):
    rep, _ = report
    s = rep.scenes[fx.SCENE]
    c = s.rows["full+correction"].collisions
    assert c.N_vf_total == 0 and c.N_ee_total == 0 and c.intersecting_frames == 0
    assert set(s.hard_cases) == {"test sequence", "3x faster", "grazing", "jitter", "leave and re-enter",
                                 "press and drag", "fast plunge", "random with tilts"}
    for case, h in s.hard_cases.items():
        assert h.finite and h.intersecting == 0 and h.crossing == 0 and h.after_nonzero == 0, (case, h)
    assert s.hard_cases["random with tilts"].steps == 30
    assert s.hard_cases["fast plunge"].substeps > s.hard_cases["fast plunge"].steps  # split into model steps
    steps = sum(h.steps for h in s.hard_cases.values())
    md = (report[1] / "RESULTS.md").read_text()
    assert ("ipctk's exact step check found 0 crossing steps (of which 0 touch) and 0 intersecting frames in "
            f"{steps} published steps") in md


def test_model_paths_and_bad_arguments(tmp_path):
    """The default model `<scene>.pt` fills the paper's `full` slot when it is that variant; any other default model
    (the quasi-static networks) gets a `shipped` slot of its own, next to a `<scene>_full.pt`."""
    full, other = tmp_path / f"{fx.SCENE}.pt", tmp_path / f"{fx.SCENE}_full.pt"
    shutil.copyfile(fx.trained_checkpoint("full"), full)
    (tmp_path / f"{fx.SCENE}_subspace.pt").write_bytes(b"x")
    (tmp_path / f"{fx.SCENE}_other.pt").write_bytes(b"x")
    assert model_paths(tmp_path, fx.SCENE) == {"subspace": tmp_path / f"{fx.SCENE}_subspace.pt", "full": full}
    shutil.copyfile(fx.trained_checkpoint("full"), other)
    assert model_paths(tmp_path, fx.SCENE) == {"subspace": tmp_path / f"{fx.SCENE}_subspace.pt", "full": other,
                                               "shipped": full}
    other.unlink()
    shutil.copyfile(fx.trained_checkpoint("baseline"), full)
    assert set(model_paths(tmp_path, fx.SCENE)) == {"subspace", "shipped"}
    with pytest.raises(InputError, match="unknown scene"):
        results(tmp_path / "docs", scenes=["nope"])
    assert main(["evaluate", "--out", str(tmp_path / "o")]) == 2  # neither --scene nor --all


def test_a_shipped_model_apart_from_the_papers_variants_gets_its_own_rows(tmp_path):
    """A scene whose default model is not the paper's full variant: the report measures both, marks the shipped
    one "(colgnn)", judges fidelity and times, checks and pictures that one, and lists no missing row for it."""
    models = tmp_path / "models"
    models.mkdir()
    shutil.copyfile(fx.trained_checkpoint("baseline"), models / f"{fx.SCENE}.pt")
    shutil.copyfile(fx.trained_checkpoint("full"), models / f"{fx.SCENE}_full.pt")
    data_root = tmp_path / "data"
    shutil.copytree(fx.dataset_dir(), data_root / fx.SCENE)
    rep = results(tmp_path / "docs", scenes=[fx.SCENE], data_root=data_root, models_dir=models, test_sequences=1,
                  frames=fx.FRAMES, jobs=1, threads=1, compile=False, hard_frames=6, random_steps=6, progress=False)
    s = rep.scenes[fx.SCENE]
    assert s.checkpoints == {"full": str(models / f"{fx.SCENE}_full.pt"), "shipped": str(models / f"{fx.SCENE}.pt")}
    assert set(s.rows) == {"ground_truth", "full", "full+correction", "shipped", "shipped+correction"}
    assert list(s.relative) == ["full", "full+correction", "shipped", "shipped+correction", "node", "rest",
                                "rest+correction"]
    assert s.colgnn_key() == "shipped+correction"
    c = s.rows["shipped+correction"].collisions
    assert c.N_vf_total == 0 and c.N_ee_total == 0 and c.intersecting_frames == 0
    md = (tmp_path / "docs" / "RESULTS.md").read_text()
    size = "{latent}/{message_passing_steps}/{mlp_layers}".format(**fx.TINY_MODEL)
    assert f"| **shipped model + correction (no caps, no rest relaxation) (colgnn), {size}** |" in md
    assert f"| full + correction, {size} |" in md and "| shipped model | not shipped |" not in md
    m = s.relative["shipped+correction"]["all"].mean
    assert f"{fx.SCENE}: {m:.2f} / " in md  # the fidelity verdict is about the shipped model
