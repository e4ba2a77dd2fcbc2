import numpy as np
import pytest
import torch

from colgnn_core.learn.normalizer import Normalizer

torch.set_num_threads(1)


def test_statistics_match_numpy():
    rng = np.random.default_rng(0)
    batches = [rng.normal(loc=[1.0, -2.0, 0.5], scale=[0.1, 3.0, 1e-3], size=(n, 3)) for n in (5, 17, 1, 40)]
    norm = Normalizer(3)
    for b in batches:
        norm.accumulate(torch.from_numpy(b))
    data = np.concatenate(batches)
    np.testing.assert_allclose(norm.mean().numpy(), data.mean(0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(norm.std().numpy(), data.std(0), rtol=1e-9)
    assert norm.acc_count.item() == len(data) and norm.num_accumulations.item() == len(batches)
    x = torch.from_numpy(rng.normal(size=(7, 3)))
    np.testing.assert_allclose(norm(x).numpy(), (x.numpy() - data.mean(0)) / data.std(0), rtol=1e-9)
    np.testing.assert_allclose(norm.inverse(norm(x)).numpy(), x.numpy(), rtol=1e-12, atol=1e-12)


def test_forward_accumulates_first_and_keeps_dtype():
    norm = Normalizer(2)
    x = torch.tensor([[1.0, 2.0], [3.0, 6.0]], dtype=torch.float32)
    y = norm(x, accumulate=True)
    assert y.dtype == torch.float32
    np.testing.assert_allclose(y.numpy(), [[-1, -1], [1, 1]], atol=1e-6)
    norm(x)  # no accumulation by default
    assert norm.num_accumulations.item() == 1


def test_empty_normalizer_is_identity_and_empty_batches_are_ignored():
    norm = Normalizer(4)
    norm.accumulate(torch.zeros(0, 4))
    assert norm.acc_count.item() == 0
    x = torch.randn(3, 4, dtype=torch.float64)
    assert torch.equal(norm(x), x)
    assert torch.equal(norm.inverse(x), x)


def test_constant_feature_std_is_clipped_to_epsilon():
    norm = Normalizer(2, std_epsilon=1e-6)
    norm.accumulate(torch.tensor([[1.0, 0.0], [1.0, 2.0]], dtype=torch.float64))
    std = norm.std()
    assert std[0].item() == pytest.approx(1e-6) and std[1].item() == pytest.approx(1.0)
    assert torch.isfinite(norm(torch.tensor([[5.0, 1.0]], dtype=torch.float64))).all()


def test_accumulation_stops_at_max_count():
    norm = Normalizer(1, max_accumulations=2)
    for v in (1.0, 3.0, 100.0):
        norm.accumulate(torch.full((4, 1), v, dtype=torch.float64))
    assert norm.num_accumulations.item() == 2
    assert norm.mean().item() == pytest.approx(2.0)


def test_state_dict_round_trip():
    a = Normalizer(3)
    a.accumulate(torch.randn(10, 3))
    b = Normalizer(3)
    b.load_state_dict(a.state_dict())
    x = torch.randn(4, 3)
    assert torch.equal(a(x), b(x))
