"""Deforming non-penetration filter: conservativeness against ipctk's CCD and exact arithmetic."""

import numpy as np
import pytest
import torch

from colgnn_core.collision import exact
from colgnn_core.collision.filter import (bernstein_coefficients, filter_edge_edge, filter_edge_edge_torch,
                                          filter_vertex_face, filter_vertex_face_torch)
from colgnn_core.errors import InputError
from tests.helpers import collision_cases as cc

GENERATORS = (cc.random_pairs, cc.colliding_vf, cc.colliding_ee, cc.near_coplanar, cc.parallel_edges,
              cc.zero_motion, cc.degenerate_triangles)


def cols(q):
    return [q[:, i] for i in range(8)]


def keep_of(kind, q):
    return (filter_vertex_face if kind == "vf" else filter_edge_edge)(*cols(q))


def batch(rng, n_per_generator: int) -> np.ndarray:
    """Random and adversarial pairs; half of each generator's output is rescaled/translated."""
    parts = []
    for gen in GENERATORS:
        q = gen(rng, n_per_generator)
        half = n_per_generator // 2
        q[:half] = cc.rescale(rng, q[:half])
        parts.append(q)
    return np.concatenate(parts)


def certified_free(kind, q) -> np.ndarray:
    """True where exact rational arithmetic proves the coplanarity cubic never vanishes on [0,1]."""
    s = cc.exact_bernstein_signs(q if kind == "vf" else cc.ee_as_vf(q))
    return np.all(s == s[:, :1], axis=1) & (s[:, 0] != 0)


def check_no_false_negative(kind, q, exact_all: int = 0):
    """Run the property check; returns (pairs, culled, ipctk hits among culled).

    Every culled pair that ipctk's Tight-Inclusion CCD reports as colliding must be proved
    contact-free in exact arithmetic (Tight-Inclusion is conservative: it reports pairs
    closer than its tolerance). ``exact_all`` culled pairs are also certified exactly.
    """
    keep = keep_of(kind, q)
    culled = q[~keep]
    ccd = exact.ccd_vertex_face if kind == "vf" else exact.ccd_edge_edge
    # max_iterations caps Tight-Inclusion's cost on coplanar pairs; a capped query returns
    # "collision" (conservative), which then needs the exact certificate below.
    hit, _ = ccd(*cols(culled), max_iterations=1000)
    suspicious = culled[hit]
    ok = certified_free(kind, suspicious)
    assert ok.all(), f"{kind}: {int((~ok).sum())} culled pairs collide: {suspicious[~ok][:3]}"
    if exact_all:
        sample = culled[: exact_all]
        assert certified_free(kind, sample).all()
    return len(q), len(culled), int(hit.sum())


def test_vertex_through_face_is_kept_and_separated_pair_is_culled():
    a, b, c = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    p0, p1 = np.array([[0.2, 0.2, 1.0]]), np.array([[0.2, 0.2, -1.0]])
    assert filter_vertex_face(p0, a, b, c, p1, a, b, c).tolist() == [True]
    # Moving parallel to the plane, 1 m above: the coplanarity cubic is constant = 1 * |n|.
    assert filter_vertex_face(p0, a, b, c, p0 + [[5.0, 0, 0]], a, b, c).tolist() == [False]
    coef, bound = bernstein_coefficients(p0, a, b, c, p0 + [[5.0, 0, 0]], a, b, c)
    np.testing.assert_allclose(coef, [[1.0, 1.0, 1.0, 1.0]])
    assert np.all(bound < 1e-13)


def test_edge_edge_crossing_kept_and_apart_culled():
    ea0, ea1 = np.array([[-1.0, 0, 1]]), np.array([[1.0, 0, 1]])
    eb0, eb1 = np.array([[0.0, -1, 0]]), np.array([[0.0, 1, 0]])
    down = np.array([[0.0, 0, -2]])
    assert filter_edge_edge(ea0, ea1, eb0, eb1, ea0 + down, ea1 + down, eb0, eb1).tolist() == [True]
    assert filter_edge_edge(ea0, ea1, eb0, eb1, ea0 + down / 4, ea1 + down / 4, eb0, eb1).tolist() == [False]


def test_minus_sign_in_n_hat_matters():
    """The published '+' variant culls real collisions; ours keeps every one of them."""
    rng = np.random.default_rng(7)
    q = cc.colliding_vf(rng, 4000)
    assert keep_of("vf", q).all()
    # '+' variant: n_hat = (n0 + n1 + (vb - va) x (vc - va)) / 2
    p0, a0, b0, c0, p1, a1, b1, c1 = cols(q)
    n0 = np.cross(b0 - a0, c0 - a0)
    n1 = np.cross(b1 - a1, c1 - a1)
    w = np.cross((b1 - b0) - (a1 - a0), (c1 - c0) - (a1 - a0))
    nh = (n0 + n1 + w) / 2
    d0, d1 = p0 - a0, p1 - a1
    coef = np.stack([(d0 * n0).sum(1), 2 * (d0 * nh).sum(1) + (d1 * n0).sum(1),
                     2 * (d1 * nh).sum(1) + (d0 * n1).sum(1), (d1 * n1).sum(1)], axis=1)
    wrong_culls = np.all(coef > 0, axis=1) | np.all(coef < 0, axis=1)
    assert wrong_culls.sum() > 10


@pytest.mark.parametrize("kind", ["vf", "ee"])
def test_known_collisions_never_culled(kind):
    rng = np.random.default_rng(11)
    q = (cc.colliding_vf if kind == "vf" else cc.colliding_ee)(rng, 5000)
    q[:2500] = cc.rescale(rng, q[:2500])
    keep = keep_of(kind, q)
    # Rounding when building the inputs can at most make a pair miss by 1e-16; anything culled
    # must then be exactly contact-free.
    assert certified_free(kind, q[~keep]).all()
    assert keep.mean() > 0.999


@pytest.mark.parametrize("kind", ["vf", "ee"])
def test_property_no_false_negatives_100k(kind):
    """>= 100k pairs in total (2 x 56k) against ipctk's Tight-Inclusion CCD."""
    rng = np.random.default_rng(99 if kind == "vf" else 100)
    n, culled, hits = check_no_false_negative(kind, batch(rng, 8000), exact_all=5000)
    assert n == 56000
    print(f"{kind}: {n} pairs, {culled} culled, {hits} culled pairs flagged by Tight-Inclusion, all proved free")


def test_error_bound_is_exact_on_near_coplanar_sets():
    """Every culled pair of the hardest sets is certified in rational arithmetic."""
    rng = np.random.default_rng(5)
    for gen in (cc.near_coplanar, cc.parallel_edges, cc.degenerate_triangles):
        q = gen(rng, 600)
        q[:300] = cc.rescale(rng, q[:300])
        for kind in ("vf", "ee"):
            keep = keep_of(kind, q)
            assert certified_free(kind, q[~keep]).all()


def test_overflow_underflow_nan_are_kept():
    rng = np.random.default_rng(3)
    q = cc.random_pairs(rng, 200)
    for scale in (1e-160, 1e120):
        assert keep_of("vf", q * scale).all()  # products under/overflow: never culled
    bad = q.copy()
    bad[:, 0, 0] = np.nan
    assert keep_of("vf", bad).all()


def test_torch_matches_numpy_and_is_conservative_in_float32():
    rng = np.random.default_rng(8)
    q = batch(rng, 300)
    for kind, fnp, ft in (("vf", filter_vertex_face, filter_vertex_face_torch),
                          ("ee", filter_edge_edge, filter_edge_edge_torch)):
        k64 = ft(*[torch.from_numpy(np.ascontiguousarray(x)) for x in cols(q)]).numpy()
        np.testing.assert_array_equal(k64, fnp(*cols(q)))
        q32 = q.astype(np.float32)
        k32 = ft(*[torch.from_numpy(np.ascontiguousarray(x)) for x in cols(q32)]).numpy()
        culled = q32[~k32].astype(np.float64)  # the float32 values, exactly
        assert certified_free(kind, culled).all()


def test_bad_input_raises():
    x = np.zeros((3, 3))
    with pytest.raises(InputError):
        filter_vertex_face(x, x, x, x, x, x, x, np.zeros((2, 3)))
    with pytest.raises(InputError):
        filter_vertex_face(x, x, x, x, x, x, x, np.zeros((3, 2)))
    with pytest.raises(InputError):
        filter_vertex_face_torch(*([torch.zeros(3, 3)] * 7 + [torch.zeros(3, 3, dtype=torch.int64)]))
