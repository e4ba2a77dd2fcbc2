"""Raw-network rollout: the contract sequence, input checks, a 500-step trajectory leaving the training range."""

import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import interpolate_poses
from colgnn_core.io import load_sequence, save_sequence
from colgnn_core.learn.model import Frame
from colgnn_core.learn.registry import load_checkpoint
from colgnn_core.runtime.models import settled_rest
from colgnn_core.runtime.rollout import rollout
from colgnn_core.scenes import sample_poses
from tests.helpers import train_data as fx

torch.set_num_threads(1)


def test_rollout_writes_a_contract_sequence(tmp_path):
    scene, ckpt = fx.scene(), fx.trained_checkpoint("full")
    gt = load_sequence(sorted(fx.dataset_dir().glob("test_*.npz"))[0])
    seq = rollout(ckpt, gt.tool_poses, scene=scene)
    T, n = gt.frames, scene.object.vertices.shape[0]
    assert seq.object_positions.shape == (T, n, 3) and seq.tool_positions.shape == gt.tool_positions.shape
    np.testing.assert_array_equal(seq.object_faces, scene.object.faces)
    np.testing.assert_array_equal(seq.tool_faces, scene.tool.faces)
    np.testing.assert_allclose(seq.tool_positions, gt.tool_positions, atol=1e-12)  # same tool placement as the solver
    rest = settled_rest(load_checkpoint(ckpt, scene), scene)  # the ground truth's frame 0
    np.testing.assert_array_equal(seq.object_positions[0], rest)
    assert seq.dt == scene.dt and seq.extra["step_ms"].shape == (T,) and (seq.extra["step_ms"][1:] > 0).all()
    assert np.isfinite(seq.object_positions).all() and not seq.extra["clamped_nodes"].any()
    save_sequence(tmp_path / "r.npz", seq)
    back = load_sequence(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.object_positions, seq.object_positions)
    # the first step is the model's own prediction; pinned vertices never move
    sim = load_checkpoint(ckpt, scene).simulator
    tpl = sim.template
    x0 = torch.from_numpy(rest[tpl.object_nodes])
    tool = [torch.from_numpy(scene.tool.world_vertices(p)) for p in gt.tool_poses[:2]]
    expect = sim.predict(Frame(x0, x0, tool[0], tool[1], gt.tool_poses[1])).detach().numpy()
    np.testing.assert_allclose(seq.object_positions[1, tpl.object_nodes], expect, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(seq.object_positions[:, scene.pinned], np.broadcast_to(
        scene.object.vertices[scene.pinned], (T, len(scene.pinned), 3)))


def test_rollout_rejects_bad_input():
    scene, ckpt = fx.scene(), fx.trained_checkpoint("full")
    poses = sample_poses(scene, 0, 4)
    far = poses.copy()
    far[2, 2] = 5.0
    with pytest.raises(InputError, match="pose 2"):
        rollout(ckpt, far, scene=scene)
    with pytest.raises(InputError, match="initial_positions"):
        rollout(ckpt, poses, scene=scene, initial_positions=np.zeros((3, 3)))
    with pytest.raises(InputError):
        rollout("no-such-checkpoint.pt", poses, scene=scene)
    with pytest.raises(InputError, match="limits"):
        rollout(ckpt, poses, scene=scene, limits="tight")


def long_poses(scene):
    """500 steps: a stroke, far away to the workspace corner, a long hold, back, another stroke."""
    a = sample_poses(scene, 5, 60)
    far = a[-1].copy()
    far[:3] = scene.workspace_max - 0.01
    parts = [a, interpolate_poses(a[-1], far, np.linspace(0, 1, 100)), np.repeat(far[None], 200, 0),
             interpolate_poses(far, a[0], np.linspace(0, 1, 80)), sample_poses(scene, 6, 60)]
    return np.concatenate(parts)


def test_500_steps_leaving_the_training_range_stay_finite_and_data_limits_bound_them():
    scene, ckpt = fx.scene(), fx.trained_checkpoint("full")
    poses = long_poses(scene)
    assert len(poses) == 500
    raw = rollout(ckpt, poses, scene=scene)
    assert np.isfinite(raw.object_positions).all() and not raw.extra["clamped_nodes"].any()
    safe = rollout(ckpt, poses, scene=scene, limits="data")
    stats = load_checkpoint(ckpt, scene).extra["data_stats"]
    rest = settled_rest(load_checkpoint(ckpt, scene), scene)  # the caps refer to the settled rest
    dev = np.linalg.norm(safe.object_positions - rest, axis=2).max()
    assert np.isfinite(safe.object_positions).all() and dev <= 1.5 * stats["max_deviation"] + 1e-9
