"""Clearance over a step (collision/clearance.py) against ipctk's step check with its default line-search clearance.

The Predictor's guarantee is stated with ipctk's ``is_step_collision_free`` (Tight-Inclusion CCD, conservative
rescaling 0.8: a pair closer than min(0.2 d0, 1e-4 m) mid-step is a collision). StepClearance must flag every step
that check flags (it proves a stronger clearance), including near misses that never touch.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from colgnn_core.collision.broad_phase import Surface, ToolSDFBound, step_candidates
from colgnn_core.collision.clearance import CLEARANCE, StepClearance
from colgnn_core.collision.exact import tool_step_free
from colgnn_core.runtime.predictor import Predictor
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.hard_cases import hard_trajectories
from tests.helpers.correction_cases import make_model

torch.set_num_threads(1)


def _clearance(faces, n, scene) -> StepClearance:
    return StepClearance(Surface.from_faces(faces, n, "object"), Surface.from_faces(scene.tool.faces,
                         len(scene.tool.vertices), "tool"), ToolSDFBound(scene.tool))


def _tip_pass(height: float):
    """A small tetrahedron whose top face rises from z = 0 to 0.1 mm, and the cone's tip passing over it at
    ``height`` (m), from 2 mm on one side to 2 mm on the other: both ends are about 1 mm away or more."""
    scene = load_scene("cone_bunny", "ci")
    X = np.array([[-1e-3, -1e-3, 0.0], [1e-3, -1e-3, 0.0], [0.0, 1.2e-3, 1e-4], [0.0, 0.0, -1.5e-3]])
    F = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])
    pose0 = np.concatenate([[-2e-3, 0.0, height], scene.tool_rest_pose[3:]])  # the cone's tip is its origin
    pose1 = pose0.copy()
    pose1[0] = 2e-3
    return scene, X, F, pose0, pose1


@pytest.mark.parametrize("height, flagged", [(0.08e-3, True), (0.15e-3, True), (0.3e-3, False)])
def test_a_tip_passing_close_mid_step_is_flagged_like_the_oracle(height, flagged):
    scene, X, F, pose0, pose1 = _tip_pass(height)
    T0, T1 = scene.tool.world_vertices(pose0), scene.tool.world_vertices(pose1)
    res = _clearance(F, len(X), scene).check(X, X, T0, T1, pose0, pose1)
    assert (res.violations > 0) == flagged
    if flagged:  # a tool vertex over an object face, found mid-step, at or below the threshold
        assert len(res.fv) >= 1 and 0.2 < res.t["fv"].min() < 0.8 and res.d["fv"].min() <= CLEARANCE + 1e-7
    # The oracle: a near miss is a "collision" for the default check within 0.1 mm (and where the swept boxes
    # meet: the top face reaches z = 0.1 mm); nothing ever touches.
    assert tool_step_free(X, X, F, T0, T1, scene.tool.faces) == (height > 1e-4)
    assert tool_step_free(X, X, F, T0, T1, scene.tool.faces, contact_only=True)


def test_the_broad_phase_clearance_widens_the_candidates():
    scene, X, F, pose0, pose1 = _tip_pass(0.3e-3)
    T0, T1 = scene.tool.world_vertices(pose0), scene.tool.world_vertices(pose1)
    surf = Surface.from_faces(F, len(X), "object")
    tool = Surface.from_faces(scene.tool.faces, len(T0), "tool")
    kw = dict(tool_bound=ToolSDFBound(scene.tool), tool_pose_t0=pose0, tool_pose_t1=pose1)
    assert step_candidates(X, X, surf, T0, T1, tool, **kw).total() == 0             # cannot touch
    assert step_candidates(X, X, surf, T0, T1, tool, clearance=4e-4, **kw).total() > 0  # may come within 0.4 mm


def test_every_step_the_oracle_flags_is_flagged_on_a_raw_rollout():
    """The raw (uncorrected) network pushed through a press-and-drag: StepClearance flags a superset of the steps
    ipctk's default check flags."""
    scene = load_scene("cylinder_banana", "ci")
    pred = Predictor(make_model(scene, "noisy"), scene, correction=False, threads=1, max_deviation=0.004)
    poses = hard_trajectories(scene, pred.max_translation, pace=0.9, drag=0.1, depth=0.6,
                              kinds=["press and drag"])["press and drag"]
    F, TF = scene.object.faces, scene.tool.faces
    check = _clearance(F, len(scene.object.vertices), scene)
    pred.reset(tool_pose=poses[0])
    prev, prev_tool, prev_pose = pred.positions, scene.tool.world_vertices(poses[0]), poses[0]
    flagged = oracle = 0
    for pose in poses[1:]:
        r = pred.step(pose)
        free = tool_step_free(prev, r.positions, F, prev_tool, r.tool_vertices, TF)
        res = check.check(prev, r.positions, prev_tool, r.tool_vertices, prev_pose, r.tool_pose)
        assert free or res.violations > 0
        flagged += res.violations > 0
        oracle += not free
        prev, prev_tool, prev_pose = r.positions, r.tool_vertices, r.tool_pose
    assert oracle > 0 and flagged >= oracle and flagged < len(poses) - 1


def test_a_check_that_reuses_a_broad_phase_for_unchanged_primitives_finds_what_a_full_check_finds():
    """``StepClearance.check(known=...)``: the broad phase of the same step ending elsewhere, for the primitives that
    did not move since; the rest gets its own. Same violations, times and distances as a check from scratch, on
    the raw network's press-and-drag with some vertices then moved (as the correction's pushes move them)."""
    scene = load_scene("cylinder_banana", "ci")
    pred = Predictor(make_model(scene, "noisy"), scene, correction=False, threads=1, max_deviation=0.004)
    poses = hard_trajectories(scene, pred.max_translation, pace=0.9, drag=0.1, depth=0.6,
                              kinds=["press and drag"])["press and drag"]
    check = _clearance(scene.object.faces, len(scene.object.vertices), scene)
    surf, tool = check.surface, check.tool_surface
    rng = np.random.default_rng(0)
    pred.reset(tool_pose=poses[0])
    prev, prev_tool, prev_pose = pred.positions, scene.tool.world_vertices(poses[0]), poses[0]
    compared = 0
    for pose in poses[1:]:
        r = pred.step(pose)
        ref = step_candidates(prev, r.positions, surf, prev_tool, r.tool_vertices, tool,
                              tool_bound=check.tool_bound, tool_pose_t0=prev_pose, tool_pose_t1=r.tool_pose,
                              clearance=check.clearance)
        for moved in (0, 5, 40):
            x1 = r.positions.copy()
            ids = rng.choice(surf.vertices, size=moved, replace=False)
            x1[ids] += rng.normal(scale=5e-4, size=(moved, 3))
            args = (prev, x1, prev_tool, r.tool_vertices, prev_pose, r.tool_pose)
            full, reused = check.check(*args), check.check(*args, known=(ref, r.positions))
            for kind in ("vf", "fv", "ee"):
                np.testing.assert_array_equal(getattr(full, kind), getattr(reused, kind))
                for stat in ("t", "d", "d0"):
                    np.testing.assert_array_equal(getattr(full, stat)[kind], getattr(reused, stat)[kind])
            compared += full.violations > 0
        prev, prev_tool, prev_pose = r.positions, r.tool_vertices, r.tool_pose
    assert compared > 0
