"""Bring your own object: `colgnn scene new` + `colgnn fit` end to end on a small shipped mesh, mesh repair and
refusal, the derived scene, and the scene path (COLGNN_SCENE_PATH) seen by every command."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.evaluation.fit import physics_changed
from colgnn_core.geometry.mesh_import import import_surface
from colgnn_core.geometry.tetmesh import check_closed_surface
from colgnn_core.geometry.tools import facet_depth, make_tool
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.custom import parse_material, parse_tool
from colgnn_core.scenes.scene import build_scene
from tests.helpers import own_scene as own

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                   [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def write_obj(path, v, f) -> str:
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n"
                                                                           for a, b, c in f))
    return str(path)


# ----------------------------------------------------------------------------- import and repair

def test_repairs_duplicates_winding_and_holes(tmp_path):
    """A cube with split vertices (an OBJ seam), one face flipped, one face missing and all faces inward: repaired
    into a closed outward surface, scaled to the size, z up from the file's y."""
    v = np.concatenate([CUBE_V, CUBE_V[[0, 1]]])    # vertices 8, 9 duplicate 0, 1
    f = CUBE_F[:, ::-1].copy()                          # all inward
    f[0] = np.where(f[0] == 0, 8, np.where(f[0] == 1, 9, f[0]))
    f[3] = f[3, ::-1]                                   # one face against its neighbours
    f = np.delete(f, 5, axis=0)                         # a hole
    s = import_surface(write_obj(tmp_path / "box.obj", v * 3.0, f), size=0.05)
    text = "; ".join(s.repairs)
    assert "merged 2 duplicate vertices" in text and "closed 1 hole(s)" in text
    assert "winding" in text or "outward" in text
    check_closed_surface(s.vertices, s.faces)
    np.testing.assert_allclose(s.extents, [0.05, 0.05, 0.05], atol=1e-12)
    assert s.up == "y"


@pytest.mark.parametrize("kind, message", [
    ("non_manifold", r"non-manifold surface: 1 edges are shared by more than two triangles"),
    ("flat", r"degenerate mesh: it encloses no volume"),
    ("two_pieces", r"2 separate pieces of similar size"),
    ("empty", r"not a triangle surface"),
])
def test_bad_meshes_are_refused_naming_the_problem(tmp_path, kind, message):
    if kind == "non_manifold":  # a third triangle on one of the cube's edges (a fin)
        v, f = np.concatenate([CUBE_V, [[0.5, -1.0, 0.5]]]), np.concatenate([CUBE_F, [[0, 1, 8]]])
    elif kind == "flat":  # a closed tetrahedron surface squashed flat: no volume
        v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.25, 0.25, 0]])
        f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]])
    elif kind == "two_pieces":
        v, f = np.concatenate([CUBE_V, CUBE_V + 3.0]), np.concatenate([CUBE_F, CUBE_F + 8])
    else:
        v, f = CUBE_V[:3], np.array([[0, 1, 2]])
    with pytest.raises(InputError, match=message):
        import_surface(write_obj(tmp_path / f"{kind}.obj", v, f), size=0.1)


def test_bad_mesh_on_the_command_line_exits_2_and_writes_nothing(tmp_path):
    bad = write_obj(tmp_path / "fin.obj", np.concatenate([CUBE_V, [[0.5, -1.0, 0.5]]]),
                    np.concatenate([CUBE_F, [[0, 1, 8]]]))
    out = tmp_path / "scenes"
    res = subprocess.run([sys.executable, "-m", "colgnn_core", "scene", "new", "fin", "--object", bad, "--size", "0.1",
                          "--tool", "sphere", "--out", str(out)], capture_output=True, text=True, env=own.env(),
                         cwd=own.REPO, timeout=120)
    assert res.returncode == 2, res.stderr
    assert "non-manifold surface: 1 edges are shared by more than two triangles" in res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert not list(out.glob("*")) if out.exists() else True



def test_tetrahedralizing_leaves_nothing_in_the_working_folder(tmp_path, monkeypatch):
    from colgnn_core.geometry.tetrahedralize import tetrahedralize_surface

    monkeypatch.chdir(tmp_path)
    mesh = tetrahedralize_surface(CUBE_V, CUBE_F, edge_length_fac=0.5, epsilon=1e-2)
    # fTetWild writes __tracked_surface.stl into the working folder: it goes to a scratch folder instead.
    assert list(tmp_path.iterdir()) == [] and os.getcwd() == str(tmp_path)
    assert len(mesh.tets) >= 5 and np.isclose(mesh.volumes().sum(), 1.0, rtol=1e-2)

def test_tool_and_material_arguments():
    assert parse_tool("sphere").overrides == {}
    assert parse_tool("cone:radius=0.01,tip_radius=0").overrides == {"radius": 0.01, "tip_radius": 0.0}
    with pytest.raises(InputError, match="unknown shape 'hammer'"):
        parse_tool("hammer")
    with pytest.raises(InputError, match="key in radius"):
        parse_tool("sphere:length=0.1")
    with pytest.raises(InputError, match="must be positive"):
        parse_tool("blade:length=-1")
    assert parse_material("gel")[0] == "gel"
    assert parse_material("2e5,0.3,900") == ("custom", (2e5, 0.3, 900.0))
    with pytest.raises(InputError, match="0 <= nu < 0.5"):
        parse_material("1e5,0.5,1000")


def test_the_derived_network_adds_the_physics_prior_that_suits_the_tool():
    from colgnn_core.scenes.custom import derive_model

    class Mesh:
        surface_vertices = np.arange(400)

    meshes, edge = {"ci": Mesh(), "full": Mesh()}, {"ci": 0.006, "full": 0.002}
    sharp = derive_model(False, meshes, edge, "cone", {"radius": 0.01, "height": 0.04})
    assert sharp["tip_prior"] is True and "contact_prior" not in sharp["ci"]          # the bunny's prior, everywhere
    for shape, params in (("sphere", {}), ("cylinder", {}), ("cone", {"tip_radius": 0.002})):
        smooth = derive_model(False, meshes, edge, shape, params)
        assert smooth["ci"]["contact_prior"] is True and "prior_mesh" not in smooth["ci"], shape
        # at full the same prior, solved on the ci mesh (the full mesh's exact prior costs seconds a first contact)
        assert smooth["full"]["contact_prior"] is True and smooth["full"]["prior_mesh"] == "ci", shape
        assert "tip_prior" not in smooth
    blade = derive_model(False, meshes, edge, "blade", {})
    assert "tip_prior" not in blade and "contact_prior" not in blade["ci"]            # not measured: no prior
    loose = derive_model(True, meshes, edge, "sphere", {})
    assert "quasi_static" not in loose and "contact_prior" not in loose["ci"]         # a prior needs quasi-static


def _voxel_mesh(mask: np.ndarray, h: float):
    """A real tet mesh of the filled cells of ``mask`` [nx,ny,nz] (cubes of side h m, 6 tets each, conforming)."""
    from itertools import permutations

    from colgnn_core.geometry.tetmesh import TetMesh

    n = np.array(mask.shape) + 1
    ids = lambda i, j, k: (i * n[1] + j) * n[2] + k  # noqa: E731
    grid = np.stack(np.meshgrid(*(np.arange(m) for m in n), indexing="ij"), -1).reshape(-1, 3) * h
    tets = []
    for i, j, k in zip(*np.nonzero(mask)):
        for order in permutations(range(3)):  # the 6 tets along the cube's main diagonal
            c, path = np.array([i, j, k]), [ids(i, j, k)]
            for axis in order:
                c = c + np.eye(3, dtype=int)[axis]
                path.append(ids(*c))
            tets.append(path)
    used, tets = np.unique(np.array(tets), return_inverse=True)
    return TetMesh.from_tets(grid[used], tets.reshape(-1, 4), orient=True)


def test_an_object_on_separate_feet_is_held_up_to_where_they_join():
    """`scene new` glues an object standing on feet (a cow on its legs) up to where they join, as a stand would:
    free, the stiff cow's body tipped 6 mm sideways under a 4 mm press. A table of 1 cm cubes, legs 2 cm high under
    a 3 cm top: its legs join at the top's underside, 2 cm; a slab and an arch whose feet join only above half its
    height keep the plain band."""
    from colgnn_core.scenes.custom import feet_height

    table = np.zeros((5, 1, 5), bool)
    table[[0, 4], :, :2] = True
    table[:, :, 2:] = True
    assert feet_height(_voxel_mesh(table, 0.01), 0.002) == pytest.approx(0.02)
    slab = np.ones((4, 2, 2), bool)
    assert feet_height(_voxel_mesh(slab, 0.01), 0.002) == 0.002
    tall = np.zeros((5, 1, 7), bool)
    tall[[0, 4], :, :6] = True
    tall[:, :, 6] = True  # legs join at 6 of 7 cm: not feet, a shape (an arch); the band is glued
    assert feet_height(_voxel_mesh(tall, 0.01), 0.002) == 0.002


# ----------------------------------------------------------------------------- end to end

def test_scene_new_writes_a_derived_scene_that_every_command_finds():
    res, wall = own.created()
    assert res.returncode == 0, res.stderr
    d = own.scene_dir()
    for f in ("pebble.toml", "pebble-ci.npz", "pebble-full.npz", "pebble-surface.obj", "pebble-scene.png"):
        assert (d / f).is_file(), f
    assert "repairs  none needed" in res.stdout
    assert "tool      sphere: radius 15.0 mm; the solver's mesh 3 subdivisions, its faces within 0." in res.stdout
    assert "dhat of the sphere and turned up to 4.6 degrees from its normal" in res.stdout
    assert "checked   under gravity the object sags" in res.stdout and "settled in" in res.stdout
    cfg = tomllib.loads((d / "pebble.toml").read_text())
    assert cfg["tool"]["radius"] == pytest.approx(0.015, rel=1e-3)          # 0.15 x the longest side
    assert cfg["object"]["pin_height"] > 0 and "ground" not in cfg          # no --ground: the bottom is glued
    assert cfg["family"]["region"] == "surface"
    # Glued: the quasi-static recipe of the glued mat and banana, its coarse level sized per resolution.
    m = cfg["model"]
    assert m["quasi_static"] and m["order"] == 0 and (m["latent"], m["message_passing_steps"]) == (16, 2)
    assert 8 <= m["ci"]["coarse_nodes"] < m["full"]["coarse_nodes"] <= 128 and m["coarse_steps"] == 4
    # on top of the contact prior (a sphere); at full solved on the ci mesh (the full mesh's own first contact costs
    # hundreds of solves)
    assert m["ci"]["contact_prior"] is True and "tip_prior" not in m
    assert m["full"]["contact_prior"] is True and m["full"]["prior_mesh"] == "ci"
    assert 0 < cfg["dhat"] <= 1e-3 * np.linalg.norm([0.1, 0.0667, 0.05]) + 1e-9
    # The truth's tool mesh follows the sphere to within dhat (the default 162 vertices at ci dipped 2.9 dhat).
    tool = make_tool("sphere", {k: cfg["tool"][k] for k in ("radius", "segments")}, "ci")
    assert cfg["tool"]["segments"] >= 3 and facet_depth(tool) <= cfg["dhat"]
    listed = own.colgnn("scenes", "--json", "--resolution", "ci")
    assert listed.returncode == 0, listed.stderr
    rows = {r["name"]: r for r in json.loads(listed.stdout)}
    assert {"cone_bunny", "sphere_mat", "pebble"} <= set(rows)
    p = rows["pebble"]
    assert p["tool_shape"] == "sphere" and 150 <= p["object_vertices"] and p["pinned_vertices"] >= 3
    size = np.subtract(p["object_bbox_max"], p["object_bbox_min"])
    assert size.max() == pytest.approx(0.1, rel=0.03)
    assert np.all(np.array(p["tool_rest_pose"][:3]) >= p["workspace_min"])
    again = own.colgnn("scene", "new", "pebble", "--object", str(own.PEBBLE), "--size", "0.1", "--tool", "sphere",
                       "--out", str(d))
    assert again.returncode == 2 and "exists; pass --force" in again.stderr


def test_an_object_that_does_not_hold_its_shape_is_refused_before_anything_is_written(tmp_path):
    """The settling check of `scene new` (sim.settle) on the pebble: the real solver settles it under gravity; it
    sags a little (accepted by default), and more than a tiny allowed sag is refused naming the fixes; a refusing
    check leaves the output folder empty."""
    from colgnn_core.scenes.custom import create_scene
    from colgnn_core.scenes.scene import build_scene, read_config_file
    from colgnn_core.sim.settle import MAX_SAG_FRACTION, check_settle, settle_report

    res, _ = own.created()
    assert res.returncode == 0, res.stderr
    scene = build_scene(own.NAME, "ci", read_config_file(own.scene_dir() / "pebble.toml"), base_dir=own.scene_dir())
    r = settle_report(scene)
    assert r.converged and 1 <= r.steps < 100
    assert 0 < r.sag_m < MAX_SAG_FRACTION * np.ptp(scene.object.vertices[:, 2])
    assert r.sag_fraction == pytest.approx(r.sag_m / np.ptp(scene.object.vertices[:, 2]))
    assert r.centroid_drop_m > 0  # gravity pulls it down, not up
    assert check_settle(scene).sag_m == pytest.approx(r.sag_m)
    with pytest.raises(InputError, match=r"does not hold its shape.*--ground.*--max-sag 0\.05"):
        check_settle(scene, max_sag_fraction=1e-6)
    with pytest.raises(InputError, match="must be > 0"):
        check_settle(scene, max_sag_fraction=0.0)

    def refuse(sc):
        raise InputError("refused by the check")

    out = tmp_path / "scenes"
    with pytest.raises(InputError, match="refused by the check"):
        create_scene("pebble2", own.PEBBLE, 0.1, "sphere", out_dir=out, check=refuse)
    assert not list(out.glob("*"))


@pytest.mark.timeout(900)
def test_a_refit_after_a_physics_edit_drops_the_trained_model(tmp_path):
    # A user edits the material in the TOML and runs `colgnn fit` again: the model trained on the old physics goes
    # (its data is redone by `generate`, whose sequences record the physics fingerprint).
    scene = load_scene("cylinder_banana", "ci")
    ckpt = tmp_path / "train.pt"
    ckpt.write_bytes(b"weights")
    assert not physics_changed(scene, tmp_path, ckpt)  # first fit: nothing recorded yet
    assert not physics_changed(scene, tmp_path, ckpt) and ckpt.is_file()  # same physics: kept
    cfg = copy.deepcopy(scene.config)
    cfg["material"]["youngs_modulus"] *= 2
    stiffer = build_scene(scene.name, "ci", cfg, own.REPO / "colgnn_core" / "scenes")
    assert physics_changed(stiffer, tmp_path, ckpt) and not ckpt.is_file()
    assert json.loads((tmp_path / "physics.json").read_text())["physics_fingerprint"] == stiffer.physics_fingerprint()


def test_fit_trains_evaluates_and_reports_within_its_budget():
    res, wall = own.fitted()
    assert res.returncode == 0, res.stderr[-3000:]
    d = own.scene_dir()
    for f in ("pebble.pt", "pebble-report.md", "pebble-fit.png"):
        assert (d / f).is_file(), f
    report = (d / "pebble-report.md").read_text()
    assert "| rest (nothing moves) | 1.000 ± 0.000 |" in report
    assert "| rest + correction (no network) |" in report and "IPC solver" in report
    assert "| stage | planned min | used min (this run) | what |" in report and "| **total** |" in report
    plan = json.loads((d / "pebble-fit" / "ci" / "plan.json").read_text())
    assert plan["train_sequences"] >= 1 and plan["train_steps"] >= 30
    # Shares in 0.1 s steps: their float sum may read 120.00000000000001 for a 120 s budget.
    assert sum(plan["shares_s"].values()) <= 60 * own.FIT_MINUTES + 1e-6
    # The budget is a plan, measured on a shared machine: allow the evaluation's overrun, not a runaway.
    assert wall < 60 * own.FIT_MINUTES * 3
    # The TOML's [model] table is what was trained, with the variant that suits it.
    from colgnn_core.learn.registry import load_checkpoint
    from colgnn_core.scenes.scene import build_scene, read_config_file
    cfg = tomllib.loads((d / "pebble.toml").read_text())["model"]
    scene = build_scene(own.NAME, "ci", read_config_file(d / "pebble.toml"), base_dir=d)
    trained = load_checkpoint(d / "pebble.pt", scene)
    assert trained.meta.variant == "baseline" and trained.config.quasi_static and trained.config.contact_prior
    assert "| physics prior + correction (no network) |" in report
    assert (trained.config.latent, trained.config.message_passing_steps, trained.config.coarse_nodes) == (
        cfg["latent"], cfg["message_passing_steps"], cfg["ci"]["coarse_nodes"])
    metrics = json.loads((d / "pebble-fit" / "ci" / "eval" / "metrics.json").read_text())
    assert metrics["relative"]["rest"]["all"]["mean"] == pytest.approx(1.0)
    assert metrics["rows"]["corrected"]["collisions"]["intersecting_frames"] == 0
    # The default model of the scene now answers `rollout --scene pebble` (no checkpoint given).
    poses = d / "poses.csv"
    from colgnn_core.io import load_sequence
    test_seq = load_sequence(sorted((d / "pebble-fit" / "ci" / "data").glob("test_*.npz"))[0])
    rows = [f"{0.04 * i},{','.join(str(x) for x in p)}" for i, p in enumerate(test_seq.tool_poses[:6])]
    poses.write_text("t,px,py,pz,qx,qy,qz,qw\n" + "\n".join(rows) + "\n")
    out = own.colgnn("rollout", "--scene", "pebble", "--poses", str(poses), "--out", str(d / "r.npz"), "--quiet")
    assert out.returncode == 0, out.stderr
    assert load_sequence(d / "r.npz").object_positions.shape[:2] == test_seq.object_positions[:6].shape[:2]
    # A second run finds everything done: nothing is simulated or trained again.
    again = own.colgnn("fit", "pebble", "--minutes", str(own.FIT_MINUTES), "--quiet")
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads((d / "pebble-fit" / "ci" / "plan.json").read_text()) == plan


def test_training_takes_the_time_that_the_data_left_unused():
    from colgnn_core.evaluation.fit import plan_budget, training_share

    plan = plan_budget(30)
    plan.shares_s = {"data": 823.0, "train": 674.0, "evaluate": 270.0}  # session 43's cow, after its first sequences
    # the data took 5 of its 14 minutes: 1,500 s are left, of which the evaluation keeps its 270
    assert training_share(plan, 1500.0) == pytest.approx(1230.0)
    # data that overran its share does not take training's planned time away
    assert training_share(plan, 700.0) == pytest.approx(674.0)


def test_the_held_out_set_grows_to_what_the_budget_affords():
    from colgnn_core.evaluation.fit import MAX_TEST_SEQUENCES, held_out_sequences

    # session 57's cow at ci, 30 minutes: 7.9 s a sequence on each of 2 workers, data 900 s, evaluation 270 s.
    # Sixteen held-out sequences cost 63 s to simulate; 10% of the data share buys 22, the evaluation's share 15.
    assert held_out_sequences(7.9, 2, 900.0, 270.0, 40, 3) == 15
    assert held_out_sequences(7.9, 2, 9000.0, 2700.0, 40, 3) == MAX_TEST_SEQUENCES
    # the full cow, 85 minutes: 339 s a sequence; one more held-out sequence would take 7% of the data share, and
    # the fit keeps its three
    assert held_out_sequences(338.8, 2, 2550.0, 765.0, 40, 3) == 3
    # a tiny budget keeps its single sequence
    assert held_out_sequences(2.0, 1, 90.0, 27.0, 24, 1) == 1


def test_no_share_reads_negative_zero():
    from colgnn_core.evaluation.fit import rounded_shares

    # session 56's 12-minute full fit: nothing left after the evaluation, and its report read "training -0.0 min"
    shares = rounded_shares({"data": 0.0, "train": 0.0, "evaluate": 258.6}, 258.6 - 1e-12)
    assert f"{shares['train'] / 60:.1f}" == "0.0" and f"{shares['data'] / 60:.1f}" == "0.0"


def test_a_budget_that_the_first_sequences_overrun_is_called_too_small():
    from colgnn_core.evaluation.fit import overrun_note

    # session 56's 12-minute full cow fit: its first 5 sequences took 17.9 minutes on 2 workers
    note = overrun_note(17.9 * 60, 12)
    assert "17.9 min, 149% of the 12-minute budget" in note and "--minutes 90 or more" in note


def test_the_report_gives_each_stages_plan_against_its_wall_time():
    from colgnn_core.evaluation.fit import budget_table, fit_verdict, plan_budget

    plan = plan_budget(30)  # 900 / 630 / 270 s
    rows = budget_table(plan, {"data": 1200.0, "train": 300.0}, 1830.0, 5, 3, 412)
    assert rows[2] == ("| data | 15.0 | 20.0 | 5 training + 3 held-out sequences of 40 frames (IPC ground truth) |")
    assert rows[3] == "| training | 10.5 | 5.0 | 412 steps |"
    assert rows[4].startswith("| evaluation | 4.5 | 0.0 |") and rows[5] == "| **total** | 30 | 30.5 | |"
    assert fit_verdict(0.30, 0.94).startswith("clearly beats")
    assert "**not clearly**" in fit_verdict(0.925, 0.968)
    assert fit_verdict(1.05, 0.94).startswith("does **not** beat")


def test_data_time_left_by_fast_sequences_buys_whole_rounds_of_them():
    from colgnn_core.evaluation.fit import top_up_sequences

    # today's full cow fit: 2 workers, the latest round 190 and 150 s, 762 s of the data's share left
    assert top_up_sequences([340.0, 190.0, 150.0], 2, 762.0, 200) == 8  # 4 rounds of 187 s
    assert top_up_sequences([340.0, 190.0, 150.0], 2, 762.0, 5) == 5    # at most MAX_TRAIN_SEQUENCES in all
    assert top_up_sequences([190.0, 150.0], 2, 180.0, 200) == 0         # no whole round fits
    assert top_up_sequences([], 2, 1e4, 200) == 0


def test_the_training_rate_is_measured_after_the_first_steps():
    from colgnn_core.evaluation.fit import steady_rate

    # 5 slow first steps (0.1 s each), then 20 steps/s: the rate over all 45 steps would read 13.8
    stamps = [(5, 0.5), (10, 0.75), (15, 1.0), (20, 1.25), (25, 1.5), (30, 1.75), (35, 2.0), (40, 2.25), (45, 2.5)]
    assert steady_rate(stamps, 15) == pytest.approx(20.0)
    assert steady_rate(stamps[:3], 15) is None and steady_rate([], 15) is None


def test_a_new_budget_keeps_the_data_and_trains_again(tmp_path):
    import dataclasses

    from colgnn_core.evaluation.fit import plan_budget, start_plan

    ckpt = tmp_path / "train.pt"
    plan, rebudgeted = start_plan(tmp_path, 30, ckpt)  # a first run: nothing recorded
    assert not rebudgeted and plan.minutes == 30
    recorded = dataclasses.replace(plan_budget(30), train_sequences=15, train_steps=36829)
    (tmp_path / "plan.json").write_text(json.dumps(recorded.to_dict()))
    ckpt.write_bytes(b"a trained model")
    plan, rebudgeted = start_plan(tmp_path, 30, ckpt)  # the same budget resumes the recorded plan and model
    assert not rebudgeted and plan == recorded and ckpt.is_file()
    plan, rebudgeted = start_plan(tmp_path, 120, ckpt)  # a larger budget: a fresh plan, the model trained again
    assert rebudgeted and plan.minutes == 120 and plan.train_sequences is None and not ckpt.exists()


def test_rounded_shares_add_up_to_the_budget():
    from colgnn_core.evaluation.fit import rounded_shares

    # rounded apart, 78.38 / 26.454 / 15.166 s of a 120 s budget read 78.4 + 26.5 + 15.2 = 120.1 s
    shares = rounded_shares({"data": 78.38, "train": 26.454, "evaluate": 15.166}, 120.0)
    assert shares == {"data": 78.4, "train": 26.4, "evaluate": 15.2}
    assert list(shares) == ["data", "train", "evaluate"]
    assert sum(shares.values()) == pytest.approx(120.0, abs=1e-9)
