import numpy as np
import pytest
import torch

from colgnn_core.errors import InputError
from colgnn_core.learn.core_model import EdgeSet, EncodeProcessDecode, MultiGraph, make_mlp, sum_to_receivers
from colgnn_core.learn.losses import kl_latent, loss_q
from colgnn_core.learn.model import Frame, ModelConfig, Simulator
from tests.helpers.learn_meshes import box_and_sphere, box_tet_mesh

torch.set_num_threads(1)

SMALL = dict(latent=16, message_passing_steps=2, mlp_layers=1, world_radius=0.03)


def make_frame(verts, tool, centre=(0.05, 0.05, 0.1), seed=0):
    rng = np.random.default_rng(seed)
    x_prev = torch.from_numpy(verts + rng.normal(scale=1e-3, size=verts.shape))
    x_t = torch.from_numpy(verts + rng.normal(scale=1e-3, size=verts.shape))
    pose = np.array([*centre, 0, 0, 0, 1.0])
    tool_next = torch.from_numpy(tool + pose[:3])
    return Frame(x_prev, x_t, tool_next + torch.tensor([0.0, 0.0, 0.004], dtype=torch.float64), tool_next, pose)


def make_sim(seed=0, **cfg):
    torch.manual_seed(seed)
    tpl, verts, tool = box_and_sphere(pinned=cfg.pop("pinned", None))
    return Simulator(tpl, ModelConfig(**{**SMALL, **cfg})), verts, tool


# -- generic core -------------------------------------------------------------------------------------------------
def test_mlp_layout():
    mlp = make_mlp(5, 8, 3, layers=2)
    kinds = [type(m).__name__ for m in mlp]
    assert kinds == ["Linear", "ReLU", "Linear", "ReLU", "Linear", "LayerNorm"]
    assert type(make_mlp(5, 8, 3, 2, layer_norm=False)[-1]).__name__ == "Linear"


def test_sum_aggregation_matches_loop():
    msgs = torch.randn(7, 4)
    recv = torch.tensor([0, 2, 2, 4, 0, 0, 3])
    out = sum_to_receivers(msgs, recv, 6)
    expect = torch.zeros(6, 4)
    for e in range(7):
        expect[recv[e]] += msgs[e]
    torch.testing.assert_close(out, expect)
    assert torch.equal(sum_to_receivers(torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), 3), torch.zeros(3, 4))


def test_core_handles_empty_edge_set_and_exposes_latents_and_decode():
    torch.manual_seed(0)
    core = EncodeProcessDecode(5, {"mesh": 8, "world": 4}, 3, latent=16, message_passing_steps=3, mlp_layers=2)
    assert len(core.processor) == 3
    # separate weights per block
    w = [blk.node_mlp[0].weight for blk in core.processor]
    assert w[0].data_ptr() != w[1].data_ptr() and not torch.equal(w[0], w[1])
    g = MultiGraph(torch.randn(10, 5), {
        "mesh": EdgeSet(torch.randn(12, 8), torch.randint(0, 10, (12,)), torch.randint(0, 10, (12,))),
        "world": EdgeSet(torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long))})
    out, lat = core(g, return_latents=True)
    assert out.shape == (10, 3) and lat.shape == (10, 16) and torch.isfinite(out).all()
    torch.testing.assert_close(core.decode(lat), out)
    out.sum().backward()
    assert core.edge_encoders["world"][0].weight.grad is not None  # zero edges: zero grad, not None/NaN
    assert torch.isfinite(core.edge_encoders["world"][0].weight.grad).all()


def test_residual_connections():
    # With every edge/node MLP's last LayerNorm zeroed, a block is the identity (pure residual).
    torch.manual_seed(0)
    core = EncodeProcessDecode(5, {"mesh": 8}, 3, latent=8, message_passing_steps=2, mlp_layers=1)
    for blk in core.processor:
        for mlp in [blk.node_mlp, *blk.edge_mlps.values()]:
            torch.nn.init.zeros_(mlp[-1].weight)
            torch.nn.init.zeros_(mlp[-1].bias)
    g = MultiGraph(torch.randn(6, 5), {"mesh": EdgeSet(torch.randn(4, 8), torch.tensor([0, 1, 2, 3]),
                                                       torch.tensor([1, 2, 3, 4]))})
    enc = core.encode(g)
    proc = core.process(enc)
    torch.testing.assert_close(proc.node_features, enc.node_features)
    torch.testing.assert_close(proc.edge_sets["mesh"].features, enc.edge_sets["mesh"].features)


# -- simulator -----------------------------------------------------------------------------------------------------
def test_prediction_is_second_order_integration_of_decoded_acceleration():
    sim, verts, tool = make_sim()
    f = make_frame(verts, tool)
    sim.training_outputs(f, f.x_t)  # fill the normalizers
    x_next = sim(f)
    assert x_next.shape == verts.shape and x_next.dtype == torch.float64
    pred_norm, lat = sim.network(sim.build_graph(f))
    accel = pred_norm.double() * sim.output_normalizer.std() + sim.output_normalizer.mean()
    torch.testing.assert_close(x_next, 2 * f.x_t - f.x_prev + accel)
    torch.testing.assert_close(sim.decode_latent(lat, f.x_t, f.x_prev), x_next)


def test_pinned_nodes_stay_fixed():
    pinned = np.flatnonzero(box_tet_mesh()[0][:, 2] == 0)
    sim, verts, tool = make_sim(pinned=pinned)
    f = make_frame(verts, tool)
    x_next = sim(f)
    torch.testing.assert_close(x_next[pinned], f.x_t[pinned], rtol=0, atol=0)
    assert not torch.allclose(x_next[verts[:, 2] > 0], f.x_t[verts[:, 2] > 0])


def test_training_noise_and_target_correction():
    sim, verts, tool = make_sim(noise_std=2e-3, noise_gamma=0.1)
    f = make_frame(verts, tool)
    x_next = f.x_t + 0.5 * (f.x_t - f.x_prev)
    out = sim(f, x_next, generator=torch.Generator().manual_seed(7))
    eps = out.x_t - f.x_t
    assert 1e-3 < eps.std().item() < 3e-3
    target_accel = sim.output_normalizer.inverse(out.target_norm.double())
    expect = (x_next + 0.9 * eps) - 2 * out.x_t + f.x_prev
    torch.testing.assert_close(target_accel, expect, rtol=1e-5, atol=1e-9)
    # same seed, same noise
    again = sim(f, x_next, generator=torch.Generator().manual_seed(7), accumulate=False)
    assert torch.equal(again.x_t, out.x_t)
    # no noise for pinned nodes
    pinned = np.flatnonzero(verts[:, 2] == 0)
    simp, _, _ = make_sim(noise_std=2e-3, pinned=pinned)
    outp = simp(f, x_next, generator=torch.Generator().manual_seed(7))
    assert torch.equal(outp.x_t[pinned], f.x_t[pinned]) and not outp.loss_mask[pinned].any()


def test_zero_world_edges_give_finite_predictions():
    sim, verts, tool = make_sim()
    far = make_frame(verts, tool, centre=(3.0, 3.0, 3.0))
    out = sim(far, far.x_t, random_latent=True)
    assert out.graph.num_world_pairs == 0
    assert torch.isfinite(sim(far)).all() and torch.isfinite(out.x_next_random).all()
    # world-edge normalizer saw nothing: it stays the identity, later frames with contact stay finite
    assert sim.edge_normalizers["world"].acc_count.item() == 0
    assert torch.isfinite(sim(make_frame(verts, tool))).all()


def test_fixed_seed_gives_same_model_and_outputs():
    a, verts, tool = make_sim(seed=3)
    b, _, _ = make_sim(seed=3)
    f = make_frame(verts, tool)
    assert torch.equal(a(f), b(f))
    c, _, _ = make_sim(seed=4)
    assert not torch.equal(a(f), c(f))


def test_loss_decreases_on_one_transition():
    sim, verts, tool = make_sim(seed=1, latent=32)
    f = make_frame(verts, tool)
    x_next = f.x_t + (f.x_t - f.x_prev) + torch.from_numpy(np.sin(verts * 40.0) * 1e-3)
    opt = torch.optim.Adam(sim.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        out = sim(f, x_next, noise=False)
        loss = loss_q(out.pred_norm, out.target_norm, out.loss_mask) + 0.1 * kl_latent(out.latents)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.3 * losses[0]


# -- losses --------------------------------------------------------------------------------------------------------
def test_loss_q_is_mgn_form():
    pred = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [9.0, 9.0, 9.0]])
    target = torch.zeros(3, 3)
    assert loss_q(pred, target, torch.tensor([True, True, False])).item() == pytest.approx(2.5)
    assert loss_q(pred, target, torch.zeros(3, dtype=torch.bool)).item() == 0.0


def test_kl_matches_closed_form():
    torch.manual_seed(0)
    z = torch.randn(500, 6, dtype=torch.float64) * torch.tensor([0.5, 1.0, 2.0, 1.0, 0.1, 3.0]) + \
        torch.tensor([0.0, 1.0, -2.0, 0.0, 0.3, 0.0])
    mu, var = z.mean(0), z.var(0, unbiased=False)
    closed = torch.distributions.kl_divergence(torch.distributions.Normal(mu, var.sqrt()),
                                               torch.distributions.Normal(0.0, 1.0)).mean()
    assert kl_latent(z, eps=0.0).item() == pytest.approx(closed.item(), rel=1e-12)
    manual = (0.5 * (mu ** 2 + var - 1 - torch.log(var))).mean()
    assert kl_latent(z, eps=0.0).item() == pytest.approx(manual.item(), rel=1e-12)
    # standardised latents: KL ~ 0; mask selects rows
    zs = (z - mu) / var.sqrt()
    assert kl_latent(zs, eps=0.0).item() == pytest.approx(0.0, abs=1e-12)
    mask = torch.arange(500) < 250
    assert kl_latent(z, mask).item() == pytest.approx(kl_latent(z[:250]).item())
    # differentiable
    zg = z.clone().requires_grad_(True)
    kl_latent(zg).backward()
    assert torch.isfinite(zg.grad).all()


def test_frame_from_sequence_picks_graph_nodes_and_times():
    from colgnn_core.learn.model import frame_from_sequence

    tpl, verts, tool = box_and_sphere(surface_only=True)
    T = 4
    obj = np.stack([verts + 0.001 * k for k in range(T)])
    tools = np.stack([tool + [0.05, 0.05, 0.1 - 0.002 * k] for k in range(T)])
    poses = np.array([[0.05, 0.05, 0.1 - 0.002 * k, 0, 0, 0, 1] for k in range(T)])
    f, x_next = frame_from_sequence(tpl, obj, tools, poses, 2)
    nodes = tpl.object_nodes
    assert f.x_t.shape == (len(nodes), 3)
    np.testing.assert_array_equal(f.x_prev.numpy(), obj[1, nodes])
    np.testing.assert_array_equal(f.x_t.numpy(), obj[2, nodes])
    np.testing.assert_array_equal(x_next.numpy(), obj[3, nodes])
    np.testing.assert_array_equal(f.tool_t.numpy(), tools[2])
    np.testing.assert_array_equal(f.tool_next.numpy(), tools[3])
    np.testing.assert_array_equal(f.pose_next, poses[3])
    f0, _ = frame_from_sequence(tpl, obj, tools, poses, 0)
    assert torch.equal(f0.x_prev, f0.x_t)  # starts at rest
    with pytest.raises(ValueError):
        frame_from_sequence(tpl, obj, tools, poses, 3)


def test_split_first_edge_layer_equals_concatenated_form():
    """edge_mlp_input is the first Linear applied to [h_s, h_r, e], without the concatenation."""
    import torch
    from colgnn_core.learn.core_model import EdgeSet, edge_mlp_input

    g = torch.Generator().manual_seed(3)
    h = torch.randn(7, 5, generator=g, dtype=torch.float64)
    feats = torch.randn(11, 5, generator=g, dtype=torch.float64)
    senders = torch.randint(0, 7, (11,), generator=g)
    receivers = torch.randint(0, 7, (11,), generator=g)
    first = torch.nn.Linear(15, 4).double()
    expect = first(torch.cat([h[senders], h[receivers], feats], dim=-1))
    got = edge_mlp_input(first, h, EdgeSet(feats, senders, receivers))
    torch.testing.assert_close(got, expect, rtol=1e-12, atol=1e-12)
    empty = EdgeSet(feats[:0], senders[:0], receivers[:0])
    assert edge_mlp_input(first, h, empty).shape == (0, 4)


def test_global_modes_span_the_training_displacements_and_add_to_every_node():
    sim, verts, tool = make_sim(order=0, quasi_static=True, global_modes=3)
    z = verts[:, 2:3] - verts[:, 2].min()
    bend = np.hstack([z ** 2, np.zeros_like(z), -0.1 * z])       # the whole box bending sideways
    squash = np.hstack([np.zeros_like(z), np.zeros_like(z), -z])  # ... and squashed
    frames = np.stack([a * bend + b * squash for a, b in [(0, 0), (1, 0), (0, 1), (2, 1), (-1, 3)]])
    assert sim.set_global_modes(frames) == pytest.approx(1.0)
    basis = sim.global_modes.reshape(3, -1).T.numpy()            # [3N, K]
    for field in (bend, squash):
        coef, *_ = np.linalg.lstsq(basis, field.ravel(), rcond=None)
        np.testing.assert_allclose(basis @ coef, field.ravel(), atol=1e-12)

    f = make_frame(verts, tool)
    sim.training_outputs(f, f.x_t)  # fill the normalizers
    last = sim.global_head[-1]
    with torch.no_grad():  # the head says "one unit of mode 0", whatever the latents
        last.weight.zero_()
        last.bias.copy_(torch.tensor([1.0, 0.0, 0.0]))
    pred_norm, latents = sim.network(sim.build_graph(f))
    added = (pred_norm - sim.core.decode(latents)).double() * sim.output_normalizer.std()
    torch.testing.assert_close(added, sim.global_modes[0], rtol=1e-5, atol=1e-9)
    assert bool((added.norm(dim=1)[z[:, 0] > 0] > 0).all())      # every node off the base, near the tool or not

    copy = Simulator(sim.template, sim.config)
    copy.load_state_dict(sim.state_dict())                         # the modes travel with the weights
    torch.testing.assert_close(copy.global_modes, sim.global_modes)
    with pytest.raises(InputError, match="global_modes needs order 0"):
        make_sim(order=2, global_modes=3)


def test_contact_depth_sees_a_sharp_tool_between_the_nodes():
    """A needle 10 mm under the box's top face, in the middle of a cell: the nearest nodes are 2.4 cm away, so the
    SDF at the nodes says nothing; the tool-side depth reads the 10 mm."""
    from colgnn_core.learn.model import CONTACT_FEATURES, RestSurface

    verts, _, faces = box_tet_mesh()  # 0.1 x 0.1 x 0.067 m, nodes every 33 mm
    top = verts[:, 2].max()
    surface = RestSurface(verts, faces)
    needle = np.array([[0.05, 0.05, top + 0.02 - 0.003 * k] for k in range(11)])  # tip 10 mm under the top
    depth, point = surface.penetration(needle)
    assert depth == pytest.approx(0.010, abs=1e-9) and point == pytest.approx(needle[-1])
    depth, _ = surface.penetration(needle + [0.0, 0.0, 0.1])  # lifted off: minus the gap to the nearest node
    assert depth == pytest.approx(-np.linalg.norm(needle[-1] + [0, 0, 0.1] - [0.1 / 3, 0.1 / 3, top]))
    beside = np.array([[0.13, 0.05, 0.03]])                   # level with the side, outside: not under the surface
    assert surface.penetration(beside)[0] < -0.02

    sim, verts, tool = make_sim(order=0, quasi_static=True, contact_depth=True)
    f = make_frame(verts, tool, centre=(0.05, 0.05, top + 0.02))
    g = sim.build_graph(f)
    feats = g.node_features[: sim.template.num_object_nodes, -CONTACT_FEATURES:]
    expected, q = surface.penetration(f.tool_next.numpy())
    torch.testing.assert_close(feats[:, 3], torch.full_like(feats[:, 3], expected))
    torch.testing.assert_close(feats[:, :3], sim.settled_rest - torch.as_tensor(q))
    with pytest.raises(InputError, match="contact_depth needs quasi_static"):
        make_sim(contact_depth=True)



def test_a_quasi_static_graph_encodes_its_rest_edges_once_and_never_serves_stale_ones():
    sim, verts, tool = make_sim(order=0, quasi_static=True, coarse_nodes=8, coarse_steps=1)
    f = make_frame(verts, tool)
    for _ in range(2):
        sim.training_outputs(f, f.x_t)  # fill the normalizers

    def outputs(cached: bool) -> torch.Tensor:
        with torch.set_grad_enabled(not cached):  # with a gradient (training) every edge set is encoded afresh
            g = sim.build_graph(f)
            assert g.encoded == (("mesh", "coarse") if cached else ())
            return sim.network(g)[0].detach()

    first = outputs(True)
    torch.testing.assert_close(first, outputs(False), rtol=1e-6, atol=1e-6)
    with torch.no_grad():
        assert sim.static_edges() is sim.static_edges()  # one entry, reused
        sim.core.edge_encoders["mesh"][0].weight.mul_(1.5)  # as a training step changes the encoder ...
    second = outputs(True)
    assert not torch.allclose(first, second)
    torch.testing.assert_close(second, outputs(False), rtol=1e-6, atol=1e-6)  # ... the entry follows it
    copy = Simulator(sim.template, sim.config)
    copy.load_state_dict(sim.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(copy.network(copy.build_graph(f))[0], outputs(True))
        with pytest.raises(ValueError, match="cannot accumulate"):
            sim.network(sim.build_graph(f), accumulate=True)
