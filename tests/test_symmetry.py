"""Symmetry augmentation: the declared turns map the ring's graph onto itself, and a turned ground-truth
transition is what the IPC solver gives for the turned tool path."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.learn.model import frame_from_sequence
from colgnn_core.learn.symmetry import node_symmetry
from colgnn_core.learn.train import train
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.hard_cases import press_pose
from colgnn_core.sim.dataset import simulate_sequence
from colgnn_core.sim.prior import physics_prior
from tests.helpers import train_data as fx

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def ring():
    scene = load_scene("knife_torus", "ci")
    template = template_from_scene(scene, surface_only=True, world_radius=0.01)
    return scene, template, node_symmetry(scene, template.rest.numpy())


def test_the_ring_declares_one_turn_per_segment_and_each_is_a_node_permutation(ring):
    scene, template, sym = ring
    assert sym.order == 30  # knife_torus ci: 30 segments round the ring
    assert np.allclose(np.diff(sym.angles), 2 * math.pi / 30)
    n = template.num_object_nodes
    pinned = template.pinned.numpy()
    for perm in sym.permutations:
        assert sorted(perm.tolist()) == list(range(n))
        assert np.array_equal(pinned[perm], pinned)  # the glued band turns into itself


def test_the_square_mat_declares_its_quarter_turns():
    scene = load_scene("sphere_mat", "ci")
    template = template_from_scene(scene, surface_only=True, world_radius=0.01)
    sym = node_symmetry(scene, template.rest.numpy())
    assert sym.order == 4 and np.allclose(sym.angles, [math.pi / 2, math.pi, 3 * math.pi / 2])


def test_a_turned_pose_and_its_turned_tool_vertices_agree(ring):
    scene, template, sym = ring
    pose = press_pose(scene, 0.3)
    tool = torch.from_numpy(scene.tool.world_vertices(pose))
    rest = template.rest
    frame, _ = frame_from_sequence(template, np.stack([scene.object.vertices] * 2), torch.stack([tool, tool]).numpy(),
                                   np.stack([pose, pose]), 0)
    turned, x_next, pose_t = sym.turn(frame, rest, pose, 7)
    assert np.abs(scene.tool.world_vertices(pose_t) - turned.tool_t.numpy()).max() < 1e-12
    assert np.allclose(pose_t[:2], [math.cos(sym.angles[7]) * pose[0] - math.sin(sym.angles[7]) * pose[1],
                                    math.sin(sym.angles[7]) * pose[0] + math.cos(sym.angles[7]) * pose[1]])
    assert pose_t[2] == pytest.approx(pose[2])
    # the rest shape turns into itself, node for node
    assert torch.abs(x_next - rest).max() < 1e-9
    assert sym.turn(frame, rest, pose, -1)[0] is frame


def test_a_frame_s_physics_prior_turns_with_it_into_the_prior_of_the_turned_pose(ring):
    """Why --symmetry may train a model with a prior: the edge prior of a turned cut is the turned prior, so a
    turned sample carries the prior its pose would have had (at ci on the unsettled mesh, to rounding)."""
    scene, template, sym = ring
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    prior = physics_prior("edge", scene, rest, template.object_nodes)
    pose = np.array([0.1, 0.003, rest[:, 2].max() - 0.012, 0.0, 0.05, 0.2, 0.0])
    pose[6] = math.sqrt(1.0 - float(pose[3:6] @ pose[3:6]))
    u = prior.displacement(pose)
    assert np.abs(u).max() > 0.01
    tool = scene.tool.world_vertices(pose)
    frame, x_next = frame_from_sequence(template, np.stack([rest] * 2), np.stack([tool, tool]), np.stack([pose] * 2),
                                        0, priors=np.stack([u, u]))
    for k in (4, 17):
        turned, _, _ = sym.turn(frame, x_next, pose, k)
        expect = prior.displacement(sym.turn_pose(pose, sym.angles[k]))
        assert np.abs(turned.prior.numpy() - expect).max() < 1e-12
        assert np.abs(turned.prior.numpy() - u).max() > 0.005   # it did move: other nodes, other directions


def test_turning_a_simulated_press_equals_simulating_the_turned_press(ring):
    """The physics claim behind the augmentation, with the IPC solver as the oracle: turned by 48 and 168 degrees,
    to the solver's tolerance (rounding can change one frame's Newton path: 2% of the motion at 60 degrees)."""
    scene, template, sym = ring
    start = scene.tool_rest_pose
    deep = press_pose(scene, 0.25)
    poses = np.stack([start + s * (deep - start) for s in np.linspace(0.0, 1.0, 6)])
    a = simulate_sequence(scene, poses)
    for k in (3, 13):
        b = simulate_sequence(scene, np.stack([sym.turn_pose(p, sym.angles[k]) for p in poses]))
        for t in range(len(poses) - 1):
            frame, x_next = frame_from_sequence(template, a.object_positions, a.tool_positions, a.tool_poses, t)
            turned, turned_next, _ = sym.turn(frame, x_next, a.tool_poses[t], k)
            expect, expect_next = frame_from_sequence(template, b.object_positions, b.tool_positions, b.tool_poses,
                                                      t)
            assert torch.abs(turned.tool_next - expect.tool_next).max() < 1e-12
            assert torch.abs(turned.x_t - expect.x_t).max() < 1e-3
            motion = float((x_next - template.rest).norm(dim=1).max())
            err = (turned_next - expect_next).norm(dim=1)
            assert float(err.max()) < 0.05 * motion and float(err.mean()) < 0.005 * motion, (k, t, motion)
    assert motion > 0.01  # the press really dents the ring (m)


def test_the_training_domain_holds_every_turn_of_the_tool_positions(ring):
    from colgnn_core.learn.data import FrameDataset
    from colgnn_core.learn.training_common import DOMAIN_POSES, domain_extra

    _, _, sym = ring
    data = FrameDataset(fx.scene(), fx.dataset_dir())  # any dataset: only its tool positions are turned here
    plain = domain_extra(data, 0)["domain_tool_positions"].numpy().astype(np.float64)
    turned = domain_extra(data, 0, sym)["domain_tool_positions"].numpy().astype(np.float64)
    assert len(plain) * sym.order <= DOMAIN_POSES and len(turned) == len(plain) * sym.order
    for p in plain[:3]:  # half a turn away, at the same height and radius
        assert np.linalg.norm(turned - sym.turn_points(p[None], math.pi)[0], axis=1).min() < 1e-6


def test_a_scene_without_the_symmetry_it_declares_is_refused():
    scene = load_scene("cone_bunny", "ci")
    template = template_from_scene(scene, surface_only=True, world_radius=0.01)
    assert node_symmetry(scene, template.rest.numpy()) is None  # declares none
    fake = dataclasses.replace(scene, config={**scene.config, "symmetry": {"kind": "rotation_z", "order": 6}})
    with pytest.raises(InputError, match="not symmetric under a turn by 60.000 deg"):
        node_symmetry(fake, template.rest.numpy())
    bad = dataclasses.replace(scene, config={**scene.config, "symmetry": {"kind": "mirror", "order": 2}})
    with pytest.raises(InputError, match="symmetry.kind"):
        node_symmetry(bad, template.rest.numpy())


def test_training_with_symmetry_on_a_scene_without_one_is_refused(tmp_path):
    cfg = fx.tiny_config(steps=5, symmetry=True)
    with pytest.raises(InputError, match="needs a \\[symmetry\\] table"):
        train(fx.scene(), fx.dataset_dir(), tmp_path / "m.pt", variant="baseline", config=cfg, progress=False,
              log_dir=False)
