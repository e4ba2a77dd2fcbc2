"""Interior vertices of a surface-only model: the elastic extension against the IPC ground truth's own interior."""

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.io import load_sequence
from colgnn_core.learn.graph import template_from_scene
from colgnn_core.runtime.interior import ElasticInterior, interior_lift
from tests.helpers import train_data as fx


@pytest.fixture(scope="module")
def truth():
    """(scene, surface-only template, ground-truth positions [T,N_mesh,3]) of a simulated cone_bunny press."""
    scene = fx.scene()
    template = template_from_scene(scene, surface_only=True, world_radius=0.01)
    seq = load_sequence(sorted(fx.dataset_dir().glob("train_*.npz"))[0])
    return scene, template, seq.object_positions


def _interior_error(lift, template, positions: np.ndarray) -> float:
    """Relative displacement error of the interior vertices over all frames, given the exact surface."""
    rest, ids = positions[0], template.interior_ids
    num = den = 0.0
    for x in positions[1:]:
        num += float(((lift(x[template.object_nodes])[ids] - x[ids]) ** 2).sum())
        den += float(((x[ids] - rest[ids]) ** 2).sum())
    return (num / den) ** 0.5


def test_the_elastic_interior_follows_the_simulated_one_far_better_than_interpolation(truth):
    scene, template, positions = truth
    rest = positions[0]
    assert len(template.interior_ids) > 20 and np.abs(positions[-1] - rest).max() > 1e-3  # a real dent inside
    elastic = _interior_error(interior_lift("elastic", scene, template, rest), template, positions)
    interpolated = _interior_error(interior_lift("interpolated", scene, template, rest), template, positions)
    assert elastic < 0.25 * interpolated, (elastic, interpolated)  # measured: 0.020 against 0.26


def test_the_elastic_interior_is_linear_keeps_the_surface_and_holds_the_pinned_vertices(truth):
    scene, template, positions = truth
    rest = positions[0]
    lift = ElasticInterior(scene, template, rest)
    nodes = rest[template.object_nodes]
    assert np.array_equal(lift(nodes), rest)  # no displacement, no motion
    rng = np.random.default_rng(0)
    u, v = rng.normal(scale=1e-3, size=(2, *nodes.shape))
    a, b, ab = lift(nodes + u), lift(nodes + v), lift(nodes + u + v)
    assert np.abs((ab - rest) - (a - rest) - (b - rest)).max() < 1e-12
    assert np.array_equal(a[template.object_nodes], nodes + u)  # graph nodes are given, not solved
    # the solved vertices are the interior ones that are not glued (here every glued vertex is on the surface)
    assert np.array_equal(lift.free, np.setdiff1d(template.interior_ids, scene.pinned))


def test_an_unknown_interior_kind_is_refused(truth):
    scene, template, positions = truth
    with pytest.raises(InputError, match="interior must be one of elastic, interpolated"):
        interior_lift("harmonic", scene, template, positions[0])
