"""Predictor: the real-time API (pose validation, jump subdivision, StepResult, rollout through it)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from colgnn_core.collision.exact import self_intersects
from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import axis_angle_quat, quat_multiply
from colgnn_core.io import load_sequence
from colgnn_core.runtime.predictor import (SETTLE_AFTER_STEPS, SETTLE_RAMP_STEPS, Predictor, StepResult,
                                   tool_step_limits)
from colgnn_core.runtime.rollout import rollout
from tests.helpers import train_data as fx
from tests.helpers.correction_cases import make_model, oracle_intersects, oracle_step_free

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def scene():
    return fx.scene()


@pytest.fixture(scope="module")
def ckpt():
    return fx.trained_checkpoint("full")


def _pred(scene, kind="noisy", **kw):
    kw.setdefault("threads", 1)
    return Predictor(make_model(scene, kind), scene, **kw)


def _state(p: Predictor):
    return p.positions, p.graph_positions, p.tool_pose, p.steps, p.net.state.x_prev.numpy().copy()


def _assert_same_state(a, b):
    for x, y in zip(a, b):
        assert np.array_equal(np.asarray(x), np.asarray(y))


def _contact_poses(scene, frames=12):
    from colgnn_core.scenes.trajectories import scripted_poses

    return scripted_poses(scene, "press", frames)


@pytest.mark.parametrize("self_contact", [False, True])
def test_step_result_from_a_trained_checkpoint(scene, ckpt, self_contact):
    from msg_tools.conversions import COLLISION_COUNT_LABELS

    p = Predictor.from_checkpoint(ckpt, threads=1, self_contact=self_contact)
    assert p.scene.name == scene.name and p.correction and (p.self_contact is not None) == self_contact
    poses = _contact_poses(scene, 12)
    for pose in poses[1:]:
        r = p.step(pose)
    assert isinstance(r, StepResult)
    n = scene.object.vertices.shape[0]
    assert r.positions.shape == (n, 3) and np.isfinite(r.positions).all()
    np.testing.assert_array_equal(r.surface_faces, scene.object.faces)
    assert r.surface_vertices.shape == (len(np.unique(scene.object.faces)), 3)
    np.testing.assert_allclose(r.tool_vertices, scene.tool.world_vertices(poses[-1]), atol=1e-15)
    np.testing.assert_allclose(r.tool_pose, poses[-1], atol=1e-12)
    counts = r.collision_counts()
    assert tuple(counts) == COLLISION_COUNT_LABELS
    assert counts["vertex_face_after"] == counts["edge_edge_after"] == counts["penetrating_vertices_after"] == 0
    assert counts["self_pairs_after"] == counts["self_fallback"] == 0
    assert set(r.timings_ms) == {"graph", "gnn", "correction", "self_contact", "total"}
    assert all(v >= 0 for v in r.timings_ms.values())
    ms = r.timings_ms
    assert ms["total"] >= ms["graph"] + ms["gnn"] + ms["correction"] + ms["self_contact"] - 1e-6
    assert (ms["self_contact"] > 0) == self_contact  # the stage runs only when asked
    assert not oracle_intersects(r.positions, scene.object.faces, r.tool_vertices, scene.tool.faces)
    if self_contact:  # without the stage this tiny model's surface does pass through itself (issue 17)
        assert not self_intersects(r.positions, scene.object.faces)
    # reset: back to rest
    p.reset()
    np.testing.assert_array_equal(p.positions, p.rest_mesh)  # the settled rest the ground truth starts from
    np.testing.assert_array_equal(p.tool_pose, scene.tool_rest_pose)


def test_threads_and_no_autograd(scene):
    before = torch.get_num_threads()
    try:
        p = _pred(scene, threads=2)
        assert torch.get_num_threads() == 2 and p.threads == 2
        r = p.step(_contact_poses(scene, 3)[1])
        assert isinstance(r.positions, np.ndarray)
        assert not p.net.state.x_t.requires_grad
    finally:
        torch.set_num_threads(before)
    with pytest.raises(InputError, match="threads"):
        _pred(scene, threads=0)


@pytest.mark.parametrize("bad, match", [
    ("nan", "NaN or inf"),
    ("inf", "NaN or inf"),
    ("quat", "not unit length"),
    ("workspace", "outside the .* workspace"),
    ("jump", "jump too large"),
    ("shape", "7 values"),
])
def test_bad_pose_is_rejected_and_the_state_is_unchanged(scene, bad, match):
    p = _pred(scene)
    twin = _pred(scene)
    poses = _contact_poses(scene, 8)
    for pose in poses[1:5]:
        p.step(pose)
        twin.step(pose)
    before = _state(p)
    pose = poses[5].copy()
    if bad == "nan":
        pose[1] = np.nan
    elif bad == "inf":
        pose[5] = np.inf
    elif bad == "quat":
        pose[3:] *= 1.002
    elif bad == "workspace":
        pose[0] = scene.workspace_max[0] + 0.01
    elif bad == "jump":
        pose[:3] += [0.0, 0.0, (p.max_substeps + 1) * p.max_translation]
        pose[:3] = np.minimum(pose[:3], scene.workspace_max)
        pose[2] = scene.workspace_max[2]
        assert p.substeps_for(pose) > p.max_substeps
    elif bad == "shape":
        pose = pose[:6]
    with pytest.raises(InputError, match=match) as err:
        p.step(pose)
    if bad == "workspace":  # the message names the bounds
        assert f"{scene.workspace_max[0]:.4g}" in str(err.value)
    _assert_same_state(before, _state(p))
    # The next valid step gives exactly what a predictor that never saw the bad pose gives.
    np.testing.assert_array_equal(p.step(poses[5]).positions, twin.step(poses[5]).positions)


def test_slightly_non_unit_quaternion_is_normalised(scene):
    p = _pred(scene)
    pose = _contact_poses(scene, 3)[1].copy()
    pose[3:] *= 1.0005
    r = p.step(pose)
    assert abs(np.linalg.norm(r.tool_pose[3:]) - 1.0) < 1e-12


def test_step_limits_come_from_the_training_family(scene):
    from colgnn_core.scenes.trajectories import sample_poses, split_seeds

    trans, rot = tool_step_limits(scene)
    for seed in split_seeds("train", 3):
        P = sample_poses(scene, seed, 120)
        assert np.linalg.norm(np.diff(P[:, :3], axis=0), axis=1).max() <= trans + 1e-12
    fam = scene.family
    assert trans >= 1.5 * max(fam["speed"]) * max(fam["retract_speed_factor"]) - 1e-12
    assert math.radians(2.0) <= rot < math.radians(45.0)
    assert tool_step_limits(scene, {"tool_step_max_translation": 0.001, "tool_step_max_rotation": 0.01}) == (0.001,
                                                                                                             0.01)


def test_the_correction_budget_comes_from_the_scene_and_an_explicit_one_wins(scene):
    """cylinder_banana asks for 24 correction passes before the fallback (its deep drags need them: the scene
    TOML); other scenes keep the default 12; a bad value is refused by name."""
    import dataclasses

    from colgnn_core.collision.correction import DEFAULT_MAX_ITERATIONS
    from colgnn_core.runtime.predictor import correction_iterations
    from colgnn_core.scenes import load_scene

    assert correction_iterations(load_scene("cylinder_banana", "ci")) == 24
    assert correction_iterations(scene) == DEFAULT_MAX_ITERATIONS == 12
    assert _pred(scene).corrector.max_iterations == 12
    asking = dataclasses.replace(scene, config={**scene.config, "correction": {"max_iterations": 30}})
    assert _pred(asking).corrector.max_iterations == 30
    assert _pred(asking, max_iterations=5).corrector.max_iterations == 5
    for bad in (-1, 2.5, True, "24"):
        wrong = dataclasses.replace(scene, config={**scene.config, "correction": {"max_iterations": bad}})
        with pytest.raises(InputError, match="correction.max_iterations must be an integer >= 0"):
            _pred(wrong)


@pytest.mark.parametrize("key, values, shipped, bad", [
    # knife_torus merges the pushes on a vertex by the largest (its blade's two sides cancel in a mean); the others
    # average.
    ("push_rule", "mean, largest", {"knife_torus": "largest"}, ("max", 1, True)),
    # cylinder_banana keeps the smaller of two corrections (its roller's rim folds the flank when every vertex is
    # projected); the others project every vertex.
    ("project", "all, least", {"cylinder_banana": "least"}, ("unpushed", 1, None)),
])
def test_the_tool_pass_rules_come_from_the_scene(scene, key, values, shipped, bad):
    """Each scene's ``[correction]`` rule as its TOML sets it (the first value elsewhere); the Predictor's tool pass
    uses the scene's rule; a bad value is refused by name."""
    import dataclasses

    from colgnn_core.runtime import predictor as P
    from colgnn_core.scenes import load_scene, scene_names

    read = {"push_rule": P.correction_push_rule, "project": P.correction_project}[key]
    default, other = values.split(", ")
    names = scene_names()
    assert {n: read(load_scene(n, "full")) for n in names} == {n: shipped.get(n, default) for n in names}
    assert getattr(_pred(scene).corrector, key) == default
    asking = dataclasses.replace(scene, config={**scene.config, "correction": {key: other}})
    assert getattr(_pred(asking).corrector, key) == other
    for value in bad:
        wrong = dataclasses.replace(scene, config={**scene.config, "correction": {key: value}})
        with pytest.raises(InputError, match=f"correction.{key} must be one of {values}"):
            _pred(wrong)


def test_the_self_contact_default_comes_from_the_scene_and_an_explicit_one_wins(scene):
    """sphere_mat and cylinder_banana turn the self-contact stage on (their models' steps are mostly valid surfaces,
    so the stage is cheap: their TOMLs say what it costs); the others leave it off; an explicit choice wins; a bad
    value is refused by name."""
    import dataclasses

    from colgnn_core.runtime.predictor import correction_iterations, self_contact_default
    from colgnn_core.scenes import load_scene, scene_names

    assert {n: self_contact_default(load_scene(n, "ci")) for n in scene_names()} == {
        "cone_bunny": False, "knife_torus": False, "sphere_mat": True, "cylinder_banana": True}
    assert _pred(scene).self_contact is None
    asking = dataclasses.replace(scene, config={**scene.config, "correction": {"self_contact": True}})
    assert _pred(asking).self_contact is not None
    assert _pred(asking, self_contact=False).self_contact is None
    assert _pred(scene, self_contact=True).self_contact is not None
    assert _pred(asking, correction=False).self_contact is None  # the stage needs the tool pass
    # a [correction.<resolution>] table wins at its resolution only (the bunny's ci test models tear: the stage is
    # slow on them)
    per_res = {"self_contact": False, "max_iterations": 12, "full": {"self_contact": True, "max_iterations": 20},
               "ci": {"max_iterations": 14}}
    for resolution, on, passes in (("ci", False, 14), ("full", True, 20)):
        tuned = dataclasses.replace(scene, resolution=resolution, config={**scene.config, "correction": per_res})
        assert (self_contact_default(tuned), correction_iterations(tuned)) == (on, passes)
    for bad in (1, "true", 0.0):
        wrong = dataclasses.replace(scene, config={**scene.config, "correction": {"self_contact": bad}})
        with pytest.raises(InputError, match="correction.self_contact must be true or false"):
            _pred(wrong)


def test_large_jump_is_split_into_model_steps(scene):
    p = _pred(scene, "static")
    start = p.tool_pose
    target = start.copy()
    target[2] -= 2.5 * p.max_translation  # down onto the bunny's back
    assert p.substeps_for(target) == 3
    r = p.step(target)
    assert r.substeps == 3 and p.steps == 3
    np.testing.assert_allclose(r.tool_pose, target, atol=1e-12)
    # rotation alone
    q = quat_multiply(axis_angle_quat([1.0, 0.0, 0.0], 3.5 * p.max_rotation), target[3:])
    turned = np.concatenate([target[:3], q])
    assert p.substeps_for(turned) == 4
    assert p.step(turned).substeps == 4


def test_fast_jump_onto_the_object_never_tunnels(scene):
    """A jump of 5 training steps straight into the bunny: split, corrected, no intersection."""
    from colgnn_core.scenes.trajectories import contact_height

    p = _pred(scene, "static")
    q = scene.tool_rest_pose[3:]
    h = contact_height(scene, scene.target[:2], q)
    above = np.concatenate([[*scene.target[:2], h + 0.003], q])
    p.step(above)
    deep = above.copy()
    deep[2] = h - 0.012
    r = p.step(deep)
    assert r.substeps >= 2 and r.vertex_face_before > 0
    assert not oracle_intersects(r.positions, scene.object.faces, r.tool_vertices, scene.tool.faces)


def test_rollout_with_correction_goes_through_the_predictor(scene, ckpt):
    gt = load_sequence(sorted(fx.dataset_dir().glob("test_*.npz"))[0])
    seq = rollout(ckpt, gt.tool_poses, correction=True, scene=scene)
    raw = rollout(ckpt, gt.tool_poses, correction=False, scene=scene)
    T = gt.frames
    assert seq.object_positions.shape == raw.object_positions.shape
    for key in ("vertex_face_before", "edge_edge_before", "vertex_face_after", "edge_edge_after", "fallback",
                "substeps", "total_ms", "correction_ms"):
        assert seq.extra[key].shape == (T,)
    assert not seq.extra["vertex_face_after"].any() and not seq.extra["edge_edge_after"].any()
    F, TF = seq.object_faces, seq.tool_faces
    for k in range(1, T):
        assert not oracle_intersects(seq.object_positions[k], F, seq.tool_positions[k], TF)
        assert oracle_step_free(seq.object_positions[k - 1], seq.object_positions[k], F, seq.tool_positions[k - 1],
                                seq.tool_positions[k], TF)
    # The same network: away from contact the corrected rollout is the raw one, bit for bit.
    np.testing.assert_array_equal(seq.object_positions[1], raw.object_positions[1])


def test_from_checkpoint_needs_a_model(scene, tmp_path, monkeypatch):
    import colgnn_core.runtime.models

    monkeypatch.setattr(colgnn_core.runtime.models, "MODEL_DIR", tmp_path)  # a package without models
    with pytest.raises(InputError, match="no shipped model for scene 'knife_torus'"):
        Predictor.from_checkpoint("knife_torus")
    with pytest.raises(InputError, match="no such checkpoint"):
        Predictor.from_checkpoint(str(tmp_path / "missing.pt"))
    with pytest.raises(InputError, match="max_substeps"):
        _pred(scene, max_substeps=0)


def test_warm_up_reaches_contact_and_leaves_no_trace(scene, ckpt):
    """warm_up=True (what the node asks for) steps into contact and back, then resets: the predictor starts from
    the same state and steps exactly like one that was not warmed up."""
    cold = Predictor.from_checkpoint(ckpt, threads=1)
    warm = Predictor.from_checkpoint(ckpt, threads=1, warm_up=True)
    assert warm.warm_up_s > 0 and cold.warm_up_s == 0
    _assert_same_state(_state(cold), _state(warm))
    for pose in _contact_poses(scene, 8)[1:]:
        a, b = cold.step(pose), warm.step(pose)
        np.testing.assert_array_equal(a.positions, b.positions)
    # the warm-up's deepest pose is in contact with the rest shape: the correction's contact path ran
    from colgnn_core.geometry.transforms import pose_path
    from colgnn_core.runtime.predictor import WARM_UP_DEPTH
    from colgnn_core.scenes.hard_cases import press_pose
    probe = Predictor.from_checkpoint(ckpt, threads=1)
    rest = np.asarray(scene.tool_rest_pose)
    bottom = press_pose(scene, WARM_UP_DEPTH)
    res = [probe.step(p) for p in pose_path(rest, bottom, 0.9 * probe.max_translation)]
    assert sum(r.collision_counts()["vertex_face_before"] + r.collision_counts()["edge_edge_before"] for r in res) > 0


def test_compiled_network_matches_eager(scene, ckpt):
    """compile=True: the same trajectory within float32 rounding of the eager network, and the
    compiled function is the one in use (no silent fallback)."""
    eager = Predictor.from_checkpoint(ckpt, threads=1, correction=False)
    fast = Predictor.from_checkpoint(ckpt, threads=1, correction=False, compile=True)
    assert fast.compiled and not eager.compiled
    assert fast.model.core_outputs.failure is None
    scale = scene.bbox_diagonal()
    for pose in _contact_poses(scene, 8)[1:]:
        a, b = eager.step(pose), fast.step(pose)
        assert np.abs(a.positions - b.positions).max() < 1e-5 * scale
    assert fast.model.core_outputs.failure is None


def test_stability_report_short_run(ckpt):
    """colgnn bench --stability on a short run: the report's fields, no object-tool intersection, and a
    hand-checked rigid shape error (a rotated, shifted rest shape is at rest)."""
    from colgnn_core.geometry.transforms import quat_to_matrix
    from colgnn_core.evaluation.stability import format_stability, rigid_shape_error, stability

    r = stability(str(ckpt), steps=30, settle=5, check_every=5, memory_every=10, threads=1, progress=False)
    assert r["steps_done"] == 30 + r["leave_and_settle_steps"] and r["leave_and_settle_steps"] >= 6
    assert r["checked_frames"] >= 7 and r["tool_intersecting_frames"] == 0
    assert r["rss_mb_start"] > 0 and len(r["rss_mb_samples"]) >= 4
    assert 0 <= r["rest_rmse_fraction"] <= r["rest_max_fraction"]
    assert "object-tool intersecting frames 0" in format_stability(r)
    rest = fx.scene().object.vertices
    moved = rest @ quat_to_matrix(axis_angle_quat([0.3, 1, 0.2], 0.7)).T + [0.1, -0.2, 0.05]
    assert rigid_shape_error(moved, rest)[1] < 1e-12
    dented = rest.copy()
    dented[0] += [0.0, 0.0, 0.003]
    rmse, worst = rigid_shape_error(dented, rest)
    assert 0 < rmse < worst <= 0.003 + 1e-12


def test_from_checkpoint_data_limits(ckpt):
    """limits='data': the caps come from the checkpoint's training-data statistics; explicit values win."""
    from colgnn_core.runtime.models import DATA_DEVIATION_FACTOR, DATA_STEP_FACTOR, load_model

    stats = load_model(str(ckpt)).extra["data_stats"]
    p = Predictor.from_checkpoint(ckpt, threads=1, limits="data")
    assert p.net.max_displacement == pytest.approx(DATA_STEP_FACTOR * stats["max"])
    assert p.net.max_deviation == pytest.approx(DATA_DEVIATION_FACTOR * stats["max_deviation"])
    p = Predictor.from_checkpoint(ckpt, threads=1, limits="data", max_deviation=0.5)
    assert p.net.max_deviation == 0.5
    assert Predictor.from_checkpoint(ckpt, threads=1).net.max_deviation is None
    with pytest.raises(InputError, match="limits must be"):
        Predictor.from_checkpoint(ckpt, threads=1, limits="tight")


def test_rest_relaxation_pulls_a_released_object_back_to_rest_only_when_the_tool_is_out_of_reach(scene):
    from colgnn_core.scenes.trajectories import scripted_poses

    rest = scene.object.vertices
    bent = rest + 2e-3 * np.sin(40.0 * rest[:, [1, 2, 0]])  # a smooth deformation, a few mm
    dev0 = np.abs(bent - rest).max()
    held = _pred(scene, "static", correction=False)
    relaxed = _pred(scene, "static", correction=False, rest_relaxation=0.1)
    for p in (held, relaxed):
        p.reset(positions=bent)
        for _ in range(150):
            p.step(scene.tool_rest_pose)
    # the zero-acceleration network keeps the shape; relaxed, it is back at rest
    nodes = held.template.object_nodes  # graph nodes (interior vertices are interpolated from them)
    assert np.abs(held.graph_positions - bent[nodes]).max() < 1e-12
    assert held.relaxation_rate() == 0.0 and held.relaxed_steps == 0
    # after 150 free steps the settle ramp has reached 1: exactly the rest shape
    assert SETTLE_AFTER_STEPS + SETTLE_RAMP_STEPS <= 150 and relaxed.relaxation_rate() == 1.0
    assert np.abs(relaxed.graph_positions - rest[nodes]).max() < 1e-12
    assert relaxed.relaxed_steps == 150
    # before the ramp: x_{n+1} - rest = (1 - a) (2 (x_n - rest) - (x_{n-1} - rest)), complex roots of modulus
    # sqrt(1 - a): a damped decay, nothing more
    early = _pred(scene, "static", correction=False, rest_relaxation=0.1)
    early.reset(positions=bent)
    for _ in range(SETTLE_AFTER_STEPS):
        early.step(scene.tool_rest_pose)
    assert early.relaxation_rate() == 0.1
    dev = np.abs(early.graph_positions - rest[nodes]).max()
    assert 1e-4 * dev0 < dev < 2 * 0.9 ** (SETTLE_AFTER_STEPS / 2) * dev0
    # in contact (world edges present) nothing is relaxed
    press = scripted_poses(scene, "press", 40)
    relaxed.reset()
    touching = 0
    for pose in press[1:]:
        relaxed.step(pose)
        touching += relaxed.net.world_edges > 0
    assert touching > 0 and relaxed.relaxed_steps == len(press) - 1 - touching
    with pytest.raises(InputError, match="rest_relaxation"):
        _pred(scene, rest_relaxation=1.0)


def test_interior_vertices_inside_the_tool_are_moved_out_of_the_published_mesh(scene):
    """A tool deep in the object can hold interior (interpolated) vertices while the surface is clean; the
    published mesh has none inside, and nothing else moves."""
    from colgnn_core.geometry.transforms import quat_to_matrix
    from colgnn_core.learn.graph import lift_to_mesh

    p = _pred(scene, "static")
    ids = p.template.interior_ids
    assert ids is not None and len(ids) > 0
    pose = np.asarray(scene.tool_rest_pose, dtype=np.float64).copy()
    # the tool's centroid on the deepest interior vertex that keeps the pose in the workspace
    center = quat_to_matrix(pose[3:]) @ scene.tool.vertices.mean(0)
    best = 0
    for v in ids:
        trial = pose.copy()
        trial[:3] = scene.object.vertices[v] - center
        lo_ok = np.all(trial[:3] >= scene.workspace_min) and np.all(trial[:3] <= scene.workspace_max)
        inside = int((scene.tool.sdf(scene.object.vertices[ids], trial) < 0).sum()) if lo_ok else 0
        if inside > best:
            best, deep = inside, trial
    assert best >= 2
    p.reset(tool_pose=deep)
    x_graph = scene.object.vertices[p.template.object_nodes]
    raw = lift_to_mesh(p.template, x_graph)
    res = StepResult(positions=raw, surface_faces=p.surface_faces, surface_vertex_ids=p.surface_vertex_ids,
                     tool_vertices=None, tool_faces=p.tool_faces, tool_pose=deep)
    mesh = p.lift(x_graph, res)
    d = scene.tool.sdf(mesh[ids], deep)
    assert res.interior_cleared == best and d.min() >= 0.999 * p.corrector.margin
    moved = np.flatnonzero(np.any(mesh != raw, axis=1))
    assert set(moved) <= set(ids) and len(moved) == best
    # without the correction the lift is the plain interpolation
    assert np.array_equal(_pred(scene, "static", correction=False).lift(x_graph), raw)


def test_a_static_tool_out_of_reach_of_the_rest_shape_releases_the_object(scene):
    """World edges to a tool that has left (a displaced object brushing it) do not stop the return to rest while
    the tool stands still out of reach of the rest shape; a moving tool there does."""
    p = _pred(scene, "static", correction=False, rest_relaxation=0.1)
    rest = scene.object.vertices
    nodes = p.template.object_nodes
    tool = scene.tool.world_vertices(scene.tool_rest_pose)
    d = np.linalg.norm(rest[nodes][:, None, :] - tool[None, :, :], axis=2)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    assert d[i, j] > p.template.world_radius  # at rest the tool is out of reach
    # shift the object until its closest node is half a world radius from the tool
    shift = (tool[j] - rest[nodes][i]) * (1 - 0.5 * p.template.world_radius / d[i, j])
    p.reset(positions=rest + shift)
    p.step(scene.tool_rest_pose)
    assert p.net.world_edges > 0 and p.relaxed_steps == 1   # in reach of the shifted object, yet released
    for _ in range(SETTLE_AFTER_STEPS + SETTLE_RAMP_STEPS):
        p.step(scene.tool_rest_pose)
    assert np.abs(p.graph_positions - rest[nodes]).max() < 1e-12
    moving = _pred(scene, "static", correction=False, rest_relaxation=0.1)
    moving.reset(positions=rest + shift)
    pose = np.asarray(scene.tool_rest_pose, dtype=np.float64).copy()
    pose[:3] += 1e-4 * np.sign(shift)  # a small move, the object still in reach
    moving.step(pose)
    assert moving.net.world_edges > 0 and moving.relaxed_steps == 0
