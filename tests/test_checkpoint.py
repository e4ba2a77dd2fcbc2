import random

import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.checkpoint import (CheckpointMeta, capture_rng_state, check_compatible, read_checkpoint,
                                          restore_rng_state, save_checkpoint, simulator_from_payload)
from colgnn_core.learn.losses import loss_q
from colgnn_core.learn.model import Frame, ModelConfig, Simulator
from tests.helpers.learn_meshes import box_and_sphere

torch.set_num_threads(1)

META = CheckpointMeta(scene="box_sphere", resolution="ci", fingerprint="ab" * 32, dt=0.04, variant="full", step=3)


def trained_sim():
    torch.manual_seed(0)
    tpl, verts, tool = box_and_sphere()
    sim = Simulator(tpl, ModelConfig(latent=16, message_passing_steps=2, mlp_layers=1, world_radius=0.03,
                                     noise_std=1e-3))
    rng = np.random.default_rng(0)
    x_prev = torch.from_numpy(verts + rng.normal(scale=1e-3, size=verts.shape))
    x_t = torch.from_numpy(verts + rng.normal(scale=1e-3, size=verts.shape))
    pose = np.array([0.05, 0.05, 0.1, 0, 0, 0, 1.0])
    tn = torch.from_numpy(tool + pose[:3])
    frame = Frame(x_prev, x_t, tn + 0.003, tn, pose)
    opt = torch.optim.Adam(sim.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.99)
    gen = torch.Generator().manual_seed(1)
    for _ in range(3):
        out = sim(frame, 2 * x_t - x_prev, generator=gen)
        loss = loss_q(out.pred_norm, out.target_norm)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return sim, frame, opt, sched, gen


def test_round_trip_gives_same_predictions_and_state(tmp_path):
    sim, frame, opt, sched, gen = trained_sim()
    path = tmp_path / "model.pt"
    save_checkpoint(path, sim, META, optimizer=opt, scheduler=sched, rng=capture_rng_state({"noise": gen}),
                    extra={"epoch": 2})
    assert not list(tmp_path.glob(".*.tmp"))  # atomic write leaves no temp file
    payload = read_checkpoint(path)
    assert CheckpointMeta(**payload["meta"]) == META and payload["extra"] == {"epoch": 2}
    loaded = simulator_from_payload(payload, sim.template)
    assert loaded.config == sim.config
    assert torch.equal(loaded(frame), sim(frame))
    for name in ("acc_sum", "acc_sum_squared", "acc_count"):
        assert torch.equal(getattr(loaded.output_normalizer, name), getattr(sim.output_normalizer, name))
    # optimizer / scheduler state restore
    opt2 = torch.optim.Adam(loaded.parameters(), lr=1e-3)
    opt2.load_state_dict(payload["optimizer"])
    sched2 = torch.optim.lr_scheduler.ExponentialLR(opt2, gamma=0.99)
    sched2.load_state_dict(payload["scheduler"])
    assert opt2.param_groups[0]["lr"] == opt.param_groups[0]["lr"]
    assert torch.equal(opt2.state[next(iter(loaded.parameters()))]["exp_avg"],
                       opt.state[next(iter(sim.parameters()))]["exp_avg"])


def test_strip_training_state(tmp_path):
    from colgnn_core.learn.checkpoint import strip_training_state

    sim, frame, opt, sched, gen = trained_sim()
    save_checkpoint(tmp_path / "train.pt", sim, META, optimizer=opt, scheduler=sched)
    strip_training_state(tmp_path / "train.pt", tmp_path / "ship.pt")
    shipped = read_checkpoint(tmp_path / "ship.pt")
    assert shipped["optimizer"] is None and shipped["rng"] is None
    assert (tmp_path / "ship.pt").stat().st_size < (tmp_path / "train.pt").stat().st_size
    assert torch.equal(simulator_from_payload(shipped, sim.template)(frame), sim(frame))


def test_rng_state_round_trip(tmp_path):
    sim, _, _, _, gen = trained_sim()
    torch.manual_seed(5), np.random.seed(5), random.seed(5)
    save_checkpoint(tmp_path / "c.pt", sim, META, rng=capture_rng_state({"noise": gen}))
    expect = (torch.rand(3), np.random.rand(3), random.random(), torch.rand(3, generator=gen))
    torch.manual_seed(0), np.random.seed(0), random.seed(0)
    gen2 = torch.Generator()
    restore_rng_state(read_checkpoint(tmp_path / "c.pt")["rng"], {"noise": gen2})
    got = (torch.rand(3), np.random.rand(3), random.random(), torch.rand(3, generator=gen2))
    assert torch.equal(got[0], expect[0]) and np.array_equal(got[1], expect[1]) and got[2] == expect[2]
    assert torch.equal(got[3], expect[3])


def test_corrupt_truncated_and_foreign_files_are_rejected(tmp_path):
    sim, *_ = trained_sim()
    good = tmp_path / "good.pt"
    save_checkpoint(good, sim, META)
    data = good.read_bytes()
    (tmp_path / "trunc.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint at all" * 10)
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    for name, msg in [("trunc.pt", "corrupt or truncated"), ("junk.pt", "corrupt or truncated"),
                      ("foreign.pt", "not a colgnn checkpoint"), ("missing.pt", "no such checkpoint")]:
        with pytest.raises(InputError, match=msg):
            read_checkpoint(tmp_path / name)


def test_wrong_scene_mesh_or_dt_is_rejected():
    check_compatible(META, "box_sphere", "ab" * 32, 0.04)
    with pytest.raises(InputError, match="is for scene 'box_sphere', not 'cone_bunny'"):
        check_compatible(META, "cone_bunny", "ab" * 32, 0.04)
    with pytest.raises(InputError, match="different 'box_sphere' mesh"):
        check_compatible(META, "box_sphere", "cd" * 32, 0.04)
    with pytest.raises(InputError, match="dt=0.04 s, the scene uses dt=0.02 s"):
        check_compatible(META, "box_sphere", "ab" * 32, 0.02)


def test_weights_that_do_not_fit_the_template_are_rejected(tmp_path):
    sim, *_ = trained_sim()
    save_checkpoint(tmp_path / "c.pt", sim, META)
    payload = read_checkpoint(tmp_path / "c.pt")
    pinned_tpl, verts, _ = box_and_sphere(pinned=np.arange(3))  # 3 node types: node encoder input differs
    with pytest.raises(InputError, match="do not match"):
        simulator_from_payload(payload, pinned_tpl)


def test_scene_checkpoint_round_trip_and_wrong_scene(tmp_path):
    from dataclasses import replace

    from colgnn_core.learn.registry import load_checkpoint
    from colgnn_core.learn.graph import template_from_scene
    from colgnn_core.scenes import load_scene

    scene = load_scene("sphere_mat", "ci")
    torch.manual_seed(0)
    config = ModelConfig.from_scene(scene, latent=8, message_passing_steps=1, mlp_layers=1)
    sim = Simulator(template_from_scene(scene), config)
    x = sim.template.rest.clone()
    pose = scene.tool_rest_pose.copy()
    pose[2] = float(x[:, 2].max()) + 0.04 + 0.005  # sphere 5 mm above the mat: world edges exist
    tool = torch.from_numpy(scene.tool.world_vertices(pose))
    frame = Frame(x, x, tool, tool - torch.tensor([0.0, 0.0, 0.003], dtype=torch.float64), pose)
    sim(frame, x, generator=torch.Generator().manual_seed(0))  # accumulate normalizer statistics
    meta = CheckpointMeta.for_scene(scene, "baseline", step=10)
    save_checkpoint(tmp_path / "c.pt", sim, meta)

    loaded = load_checkpoint(tmp_path / "c.pt")  # finds the scene by name and resolution
    assert loaded.meta == meta and loaded.config == config and loaded.meta.variant == "baseline"
    assert torch.equal(loaded.simulator(frame), sim(frame))
    assert sim.build_graph(frame).num_world_pairs > 0

    with pytest.raises(InputError, match="is for scene 'sphere_mat', not 'cone_bunny'"):
        load_checkpoint(tmp_path / "c.pt", load_scene("cone_bunny", "ci"))
    save_checkpoint(tmp_path / "old.pt", sim, replace(meta, fingerprint="0" * 64))  # mesh changed since training
    with pytest.raises(InputError, match="different 'sphere_mat' mesh"):
        load_checkpoint(tmp_path / "old.pt")


def test_resume_continues_bit_for_bit(tmp_path):
    def steps(sim, opt, sched, gen, frame, n):
        for _ in range(n):
            out = sim(frame, 2 * frame.x_t - frame.x_prev, generator=gen, random_latent=True)
            loss = loss_q(out.pred_norm, out.target_norm) + out.x_next_random.square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()

    sim, frame, opt, sched, gen = trained_sim()
    save_checkpoint(tmp_path / "c.pt", sim, META, optimizer=opt, scheduler=sched, rng=capture_rng_state({"g": gen}))
    steps(sim, opt, sched, gen, frame, 3)

    payload = read_checkpoint(tmp_path / "c.pt")
    sim2 = simulator_from_payload(payload, sim.template).train()
    opt2 = torch.optim.Adam(sim2.parameters(), lr=1e-3)
    opt2.load_state_dict(payload["optimizer"])
    sched2 = torch.optim.lr_scheduler.ExponentialLR(opt2, gamma=0.99)
    sched2.load_state_dict(payload["scheduler"])
    gen2 = torch.Generator()
    restore_rng_state(payload["rng"], {"g": gen2})
    steps(sim2, opt2, sched2, gen2, frame, 3)
    for (k, a), (_, b) in zip(sim.state_dict().items(), sim2.state_dict().items()):
        assert torch.equal(a, b), k


def test_model_cards_of_the_shipped_models_and_the_readme_table_match_the_files(tmp_path, capsys):
    """`colgnn models`: the values come from the checkpoint files, the rebuilt train command carries the non-default
    model settings, and the models README's generated table is the one the files give today."""
    from colgnn_core.cli import main
    from colgnn_core.evaluation.model_card import SECTION, model_cards, models_markdown
    from colgnn_core.runtime.models import MODEL_DIR

    cards = {c.file: c for c in model_cards(MODEL_DIR)}
    bunny = cards["cone_bunny_full.pt"]
    assert (bunny.scene, bunny.resolution, bunny.variant, bunny.size, bunny.steps) == \
        ("cone_bunny", "full", "full", "16/3/1", 8000)
    assert bunny.sequences == 19 and bunny.options == {} and 300 < bunny.wall_s < 400
    shipped = cards["cone_bunny.pt"]
    assert (shipped.variant, shipped.size, shipped.steps, shipped.sequences) == ("baseline", "16/2/1", 24000, 38)
    assert shipped.options == {"order": 0, "coarse_nodes": 128, "coarse_steps": 4, "quasi_static": True,
                               "tip_prior": True}
    qs = cards["experiments/knife_torus_ci_quasi_static.pt"]
    assert qs.resolution == "ci" and qs.size == "64/4/2" and qs.sequences == 100
    assert qs.options == {"order": 0, "coarse_nodes": 32, "coarse_steps": 3, "quasi_static": True}
    assert qs.command.endswith("--model 64/4/2 --model-options "
                               "'{\"order\": 0, \"coarse_nodes\": 32, \"coarse_steps\": 3, \"quasi_static\": true}'")
    assert cards["experiments/knife_torus_full_quasi_static_16-2-1_sym10.pt"].command.endswith(" --symmetry")
    assert not qs.command.endswith(" --symmetry")
    assert cards["sphere_mat_subspace.pt"].size.startswith("PCA ") and "--model" not in \
        cards["sphere_mat_subspace.pt"].command
    readme = (MODEL_DIR / "README.md").read_text()
    block = readme.split(f"<!-- begin {SECTION} -->\n", 1)[1].split(f"<!-- end {SECTION} -->", 1)[0]
    fresh = models_markdown(list(cards.values()), "colgnn models")
    assert block.split("\n", 1)[1] == fresh.split("\n", 1)[1], \
        "the models README is stale: run `colgnn models --markdown colgnn_core/assets/models/README.md`"
    page = tmp_path / "M.md"
    assert main(["models", "--markdown", str(page)]) == 0 and "wrote" in capsys.readouterr().out
    text = page.read_text()
    assert "| `knife_torus_full.pt` | knife_torus (full) | full | 16/2/1 |" in text  # the paper's variant
    shipped = "| `knife_torus.pt` | knife_torus (full) | baseline | 16/2/1 | order 0, coarse_nodes 128, "
    assert shipped in text  # the quasi-static model the scene ships
    assert main(["models", "--dir", str(tmp_path / "nope")]) == 2
    assert "no such models folder" in capsys.readouterr().err
