"""Ground truth for every valid trajectory (issue 14, item 2): the hard trajectories simulate on every scene.

Each frame is verified by the solver itself (object–tool and self intersection included); the tests check the files
again with the exact oracle: no object–tool intersection at any frame, and the motion into every frame (straight,
or the recorded path of intermediate states) collision-free by ipctk's default step check, the criterion the
Predictor's published steps meet.
"""

from __future__ import annotations

import numpy as np
import pytest

from colgnn_core.collision.exact import tool_intersects, tool_step_free
from colgnn_core.collision.metrics import sequence_metrics
from colgnn_core.io import SUBFRAME_KEYS, load_sequence, save_sequence
from colgnn_core.runtime.predictor import tool_step_limits
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.hard_cases import HARD_KINDS, hard_trajectories
from colgnn_core.sim.dataset import simulate_sequence
from colgnn_core.sim.ipc import IPCSimulator

SCENES = ("cone_bunny", "knife_torus", "sphere_mat", "cylinder_banana")
# Short versions for the default run (ci meshes): 4 model steps per ordinary frame, 12 per fast one, half way to
# the deepest valid pose, a drag of 8% of the object each way, 2 frames of settling.
CI_HARD = dict(pace=4.0, jump=12.0, depth=0.5, drag=0.08, settle=2)


def check_sequence(seq, scene) -> int:
    """Every frame intersection-free, every frame's motion collision-free by the exact oracle; returns the number
    of frames whose motion is a recorded path."""
    F, TF = scene.object.faces, scene.tool.faces
    paths = 0
    for t in range(1, seq.frames):
        X, T = seq.object_positions[t], seq.tool_positions[t]
        assert not tool_intersects(X, F, T, TF), f"frame {t} intersects the tool"
        states = seq.motion(t)
        paths += len(states) > 2
        for (x0, t0), (x1, t1) in zip(states[:-1], states[1:]):
            assert tool_step_free(x0, x1, F, t0, t1, TF), f"the motion into frame {t} crosses the tool"
    return paths


@pytest.mark.parametrize("name", SCENES)
def test_the_hard_trajectories_simulate_at_ci(name):
    scene = load_scene(name, "ci")
    step = tool_step_limits(scene)[0]
    for kind, poses in hard_trajectories(scene, step, **CI_HARD).items():
        seq = simulate_sequence(scene, poses)
        assert seq.frames == len(poses), kind
        check_sequence(seq, scene)
        assert seq.extra["subframes"].shape == (len(poses),)
    assert set(HARD_KINDS) == {"fast plunge", "press and drag", "tilted slice", "jitter", "release and settle"}


def test_a_failed_solve_is_solved_again_in_halves():
    """Newton capped at 12 iterations: the plunge's first frame (3 cm down, 1.5 cm into the bunny) does not converge
    in one step; it does in sub-frames, each verified, and the frame ends exactly on its pose."""
    scene = load_scene("cone_bunny", "ci")
    poses = hard_trajectories(scene, tool_step_limits(scene)[0], kinds=["fast plunge"])["fast plunge"][:2]
    seq = simulate_sequence(scene, poses, max_newton=12)
    assert seq.extra["subframes"].max() > 1
    np.testing.assert_array_equal(seq.tool_positions[-1], scene.tool.world_vertices(poses[-1]))
    check_sequence(seq, scene)


def test_a_frame_whose_straight_motion_fails_records_a_collision_free_path(monkeypatch, tmp_path):
    """The path machinery on a frame the test declares unfit: the straight motion from frame 1 to frame 2 is
    refused, so the file must carry intermediate states whose pieces all pass the real check."""
    scene = load_scene("knife_torus", "ci")
    poses = hard_trajectories(scene, tool_step_limits(scene)[0], pace=2.0, depth=0.3,
                              kinds=["release and settle"])["release and settle"][:3]
    real = IPCSimulator.motion_free
    refused = {}

    def motion_free(self, x0, x1):
        if self.frame == 1 and not refused:  # the first check of frame 2 is its straight motion
            refused["x"] = (x0, x1)
            return False
        return real(self, x0, x1)

    monkeypatch.setattr(IPCSimulator, "motion_free", motion_free)
    seq = simulate_sequence(scene, poses)
    assert refused and np.array_equal(refused["x"][1][: len(seq.object_positions[2])], seq.object_positions[2])
    assert set(SUBFRAME_KEYS) <= set(seq.extra) and set(seq.extra["subframe_frame"]) == {2}
    save_sequence(tmp_path / "s.npz", seq)
    back = load_sequence(tmp_path / "s.npz")
    assert len(back.motion(2)) > 2 and len(back.motion(1)) == 2
    assert check_sequence(back, scene) == 1
    m = sequence_metrics(back, tool=scene.tool)  # the Table 2 metric follows the path
    assert m["steps"]["N_vf"] == [0, 0] and m["steps"]["N_ee"] == [0, 0]


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENES)
def test_the_hard_trajectories_simulate_at_full_resolution(name):
    """The set of the default run at full resolution (hours: a knife_torus frame in deep contact takes 30-60 s). The
    longer default trajectories of the issue's failures (press and drag, fast plunge) were run by hand: see
    docs/COLLISION_GUARANTEE.md."""
    scene = load_scene(name, "full")
    step = tool_step_limits(scene)[0]
    for kind, poses in hard_trajectories(scene, step, **CI_HARD).items():
        seq = simulate_sequence(scene, poses)
        print(name, kind, len(poses), "frames; sub-frames", seq.extra["subframes"].tolist(), "paths",
              sorted(set(seq.extra.get("subframe_frame", np.zeros(0, int)).tolist())))
        check_sequence(seq, scene)
