"""Self-contact stage: constructed cases that pass through themselves come out clean by ipctk, the tool too.

The oracle is ipctk: ``has_intersections`` on the object alone (``self_intersects``) and on object + tool with object
self-contact filtered out (``tool_intersects``), ``is_step_collision_free`` on the object-tool step
(``tool_step_free``). Surface validity (flipped, collapsed, torn triangles) is checked against the rest shape.
"""

from __future__ import annotations

import numpy as np
import pytest

from colgnn_core.collision.correction import CollisionCorrector
from colgnn_core.collision.exact import self_intersects, tool_intersects, tool_step_free
from colgnn_core.collision.self_contact import GROW_DOUBLING, SELF_CLEARANCE, SelfContact
from colgnn_core.collision.surface_validity import MAX_STRETCH, SurfaceValidity, rigid_fit
from colgnn_core.errors import InputError
from colgnn_core.geometry.tools import make_tool

SIZE, CELLS = 0.04, 8  # m, grid cells per side of a patch


def patch(z: float, offset: int = 0, cells: int = CELLS) -> tuple[np.ndarray, np.ndarray]:
    """A flat square grid patch at height z (m): vertices [(cells+1)^2,3], faces [2 cells^2,3] (normal +z)."""
    g = np.linspace(-SIZE / 2, SIZE / 2, cells + 1)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    V = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], axis=1)
    idx = np.arange(V.shape[0]).reshape(cells + 1, cells + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]) + offset
    return V, F


def two_patches(gap: float = 0.006, cells: int = CELLS) -> tuple[np.ndarray, np.ndarray]:
    Va, Fa = patch(0.0, cells=cells)
    Vb, Fb = patch(gap, offset=len(Va), cells=cells)
    return np.vstack([Va, Vb]), np.vstack([Fa, Fb])


@pytest.fixture(scope="module")
def tool():
    return make_tool("sphere", {"radius": 0.008}, "ci")


def corrected(rest, faces, x1, tool, pose0, pose1):
    """Tool pass then the self stage for the step rest -> x1, as the Predictor runs them."""
    corr = CollisionCorrector(faces, len(rest), tool, dhat=5e-4)
    stage = SelfContact(faces, len(rest), rest)
    T0, T1 = tool.world_vertices(pose0), tool.world_vertices(pose1)
    c = corr.correct(rest, x1, pose0, pose1, T0, T1)
    return stage, stage.correct(corr, rest, c.positions, pose0, pose1, T0, T1), T0, T1


def assert_clean(stage, faces, x0, out, tool, T0, T1):
    x1 = out.positions
    assert not self_intersects(x1, faces)
    assert not tool_intersects(x1, faces, T1, tool.faces)
    assert tool_step_free(x0, x1, faces, T0, T1, tool.faces)
    assert stage.check(x0, x1).pairs == 0
    assert stage.validity.counts(x1).invalid == out.invalid_after == 0
    assert out.pairs_after == 0


def bulge(rest: np.ndarray, height: float = 0.012) -> np.ndarray:
    """The lower of two patches pushed up in its middle (a bump of ``height`` m at the centre, 0 at the rim): it
    passes 6 mm through the upper one."""
    x1 = rest.copy()
    n = len(rest) // 2
    r = np.linalg.norm(rest[:n, :2], axis=1) / (SIZE / 2)
    x1[:n, 2] += height * np.clip(1.0 - r, 0.0, 1.0)
    return x1


def pose(x, y, z):
    return np.array([x, y, z, 0.0, 0.0, 0.0, 1.0])


def turned(x, y, z):
    """A pose turned by a hair (1e-6 rad about z): a step to it is no pure translation, so the tool fallback's
    sliding tier and certificate stay out and its rigid region is what these cases exercise."""
    return np.array([x, y, z, 0.0, 0.0, np.sin(5e-7), np.cos(5e-7)])


def test_two_patches_pushed_through_each_other_come_out_clean(tool):
    rest, F = two_patches()
    x1 = bulge(rest)
    n = len(rest) // 2
    assert self_intersects(x1, F)
    stage, out, T0, T1 = corrected(rest, F, x1, tool, pose(0, 0, 0.02), pose(0, 0, 0.0165))
    assert out.pairs_before > 0
    assert_clean(stage, F, rest, out, tool, T0, T1)
    # The tool pressed into the upper patch: it is still clear of it.
    assert np.all(tool.sdf(out.positions[n:], pose(0, 0, 0.0165)) > 0)


def test_a_fold_comes_out_unfolded_and_unflipped(tool):
    rest, F = patch(0.0)
    x1 = rest.copy()
    right = rest[:, 0] > 0.005
    # Fold the right part over the left about the line x = 0.005, 1 mm above it: it lands on the left part upside
    # down (flipped) and, tilted, passes through it.
    x1[right, 0] = 0.01 - rest[right, 0]
    x1[right, 2] = 0.001 - 0.2 * (rest[right, 0] - 0.005)
    assert stage_counts(rest, F, x1).flipped > 0
    stage, out, T0, T1 = corrected(rest, F, x1, tool, pose(0, 0, 0.05), pose(0, 0, 0.049))
    assert out.invalid_before > 0
    assert_clean(stage, F, rest, out, tool, T0, T1)


def test_a_collapsed_triangle_is_repaired(tool):
    rest, F = patch(0.0)
    x1 = rest + np.array([0.0, 0.0, 0.001])  # a small lift everywhere ...
    f = F[len(F) // 2]
    x1[f[2]] = 0.5 * (x1[f[0]] + x1[f[1]])  # ... and one triangle flattened onto its edge
    counts = stage_counts(rest, F, x1)
    assert counts.collapsed >= 1
    stage, out, T0, T1 = corrected(rest, F, x1, tool, pose(0, 0, 0.05), pose(0, 0, 0.05))
    assert out.invalid_before >= 1
    assert_clean(stage, F, rest, out, tool, T0, T1)
    # Local: vertices far from the collapsed triangle keep the lift.
    far = np.linalg.norm(rest - rest[f[2]], axis=1) > 0.02
    np.testing.assert_allclose(out.positions[far], x1[far])


def test_a_triangle_already_flipped_in_the_last_state_is_repaired_from_the_rest(tool):
    # The fallback can leave a flipped triangle (its one unrepaired case); the next step starts from it. Returning to
    # x0 would keep it, so the patch takes its neighbours' displacement from the rest.
    rest, F = patch(0.0)
    h = SIZE / CELLS
    centre = len(rest) // 2
    x0 = rest + np.array([0.0, 0.0, 0.002])
    x0[centre] += [1.6 * h, 0.4 * h, 0.003]  # pulled over its neighbours, above them: flipped, not touching
    stage = SelfContact(F, len(rest), rest)
    assert stage.validity.counts(x0).flipped > 0
    assert stage.check(x0, x0).pairs == 0 and not self_intersects(x0, F)
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    p = pose(0, 0, 0.05)
    T = tool.world_vertices(p)
    out = stage.correct(corr, x0, x0 + [0.0, 0.0, 1e-4], p, p, T, T)
    assert out.invalid_before > 0 and not out.fallback
    assert_clean(stage, F, x0, out, tool, T, T)
    # The repaired vertex follows its neighbours' lift from the rest; far vertices keep theirs.
    np.testing.assert_allclose(out.positions[centre], rest[centre] + [0.0, 0.0, 0.0021], atol=2e-6)  # 30 sweeps
    far = np.linalg.norm(rest - rest[centre], axis=1) > 3 * h
    np.testing.assert_allclose(out.positions[far], x0[far] + [0.0, 0.0, 1e-4])


def test_the_fallback_repairs_a_triangle_that_the_last_state_left_flipped(tool):
    rest, F = patch(0.0)
    h = SIZE / CELLS
    centre = len(rest) // 2
    x0 = rest + np.array([0.0, 0.0, 0.002])
    x0[centre] += [1.6 * h, 0.4 * h, 0.003]
    stage = SelfContact(F, len(rest), rest, max_rounds=0)  # no repair rounds: straight to the fallback
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    p = pose(0, 0, 0.05)
    T = tool.world_vertices(p)
    out = stage.correct(corr, x0, x0 + [0.0, 0.0, 1e-4], p, p, T, T)
    assert out.fallback and out.invalid_before > 0
    assert_clean(stage, F, x0, out, tool, T, T)  # it used to keep x0's flipped triangles, step after step
    far = np.linalg.norm(rest - rest[centre], axis=1) > 3 * h
    # The fallback's local tier sends only a zone around the defect back to x0: elsewhere the proposal stands.
    assert out.local
    np.testing.assert_array_equal(out.positions[far], x0[far] + [0.0, 0.0, 1e-4])


def test_the_fallback_repairs_a_flipped_triangle_that_its_rigid_region_carries_with_the_tool(tool):
    rest, F = patch(0.0)
    h = SIZE / CELLS
    centre = len(rest) // 2
    x0 = rest + np.array([0.0, 0.0, 0.002])
    x0[centre] += [1.6 * h, 0.4 * h, 0.003]  # flips its triangles; 5 mm high, under the tool
    stage = SelfContact(F, len(rest), rest, max_rounds=0)  # no repair rounds: straight to the fallback
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    top = x0[centre, 2] + 0.0005 + 0.008  # the sphere 0.5 mm above the raised vertex, then 0.3 mm lower
    p0, p1 = pose(*x0[centre, :2], top), turned(*x0[centre, :2], top - 3e-4)
    T0, T1 = tool.world_vertices(p0), tool.world_vertices(p1)
    carried = corr.rigid_fallback(x0, x0.copy(), p0, p1, T0, T1, corr.clearance.clearance)
    assert carried[F[stage.validity.invalid(x0)]].all()  # the rigid region holds the flipped triangles
    out = stage.correct(corr, x0, x0.copy(), p0, p1, T0, T1)
    assert out.fallback and out.invalid_before > 0
    assert_clean(stage, F, x0, out, tool, T0, T1)  # they used to move rigidly with the tool, flipped


def collapsed_corner_while_dragging(tool):
    """A 3 mm drag over a patch whose corner triangle, far from the tool, collapses in the proposal (a pair-free
    state with an invalid triangle). Returns (stage, corrector, rest, faces, x0, tool-corrected x1, its check,
    poses, tool vertices)."""
    rest, F = patch(0.0)
    x0 = rest + np.array([0.0, 0.0, 0.002])
    stage = SelfContact(F, len(rest), rest, max_rounds=0)  # no repair rounds: the input is the only checked state
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    p0, p1 = pose(0, 0, 0.002 + 0.008 + 3e-4), turned(3e-3, 0, 0.002 + 0.008 + 3e-4)  # a 3 mm drag over the surface
    T0, T1 = tool.world_vertices(p0), tool.world_vertices(p1)
    x1 = x0.copy()
    b, c = (v for v in F[np.flatnonzero((F == 0).any(axis=1))[0]] if v != 0)
    x1[0] += 0.95 * (0.5 * (x0[b] + x0[c]) - x0[0])  # the corner triangle, far from the tool, collapsed
    x1 = corr.correct(x0, x1, p0, p1, T0, T1).positions
    chk = stage.check(x0, x1)
    return stage, corr, rest, F, x0, x1, chk, (p0, p1), (T0, T1)


def test_a_fallback_that_would_carry_its_region_with_the_tool_gives_way_to_a_pair_free_state(tool, monkeypatch):
    monkeypatch.setattr(SelfContact, "_local_fallback", lambda self, *args: None)  # the global tiers alone
    stage, corr, rest, F, x0, x1, chk, (p0, p1), (T0, T1) = collapsed_corner_while_dragging(tool)
    assert chk.pairs == 0 and chk.invalid.sum() > 0
    fallback = x0.copy()
    region = corr.rigid_fallback(x0, fallback, p0, p1, T0, T1, corr.clearance.clearance)
    assert stage.carried(x0, fallback, region) > stage.quiet  # the fallback would drag the region along
    out = stage.correct(corr, x0, x1, p0, p1, T0, T1)
    assert not out.fallback and out.invalid_after == int(chk.invalid.sum()) > 0  # counted, not hidden
    np.testing.assert_array_equal(out.positions, x1)
    assert not self_intersects(out.positions, F)
    assert not tool_intersects(out.positions, F, T1, tool.faces)
    assert tool_step_free(x0, out.positions, F, T0, T1, tool.faces)


def test_the_local_fallback_repairs_a_collapsed_triangle_far_from_a_dragging_tool(tool):
    """The same step with the local tier: only the collapsed corner and a ring around it go back to x0, the rest
    keeps the tool-corrected proposal (the tool pass's own check passes, so nothing is carried), and the result is
    clean, the collapsed triangle included."""
    stage, corr, rest, F, x0, x1, chk, (p0, p1), (T0, T1) = collapsed_corner_while_dragging(tool)
    out = stage.correct(corr, x0, x1, p0, p1, T0, T1)
    assert out.fallback and out.local and out.region == 0
    assert_clean(stage, F, x0, out, tool, T0, T1)
    back = np.all(out.positions == x0, axis=1) & np.any(x1 != x0, axis=1)
    assert back[0] and np.linalg.norm(rest[back, :2] - rest[0, :2], axis=1).max() < 3 * SIZE / CELLS
    np.testing.assert_array_equal(out.positions[~back], x1[~back])


def stage_counts(rest, F, x):
    return SurfaceValidity(F, rest).counts(x)


def test_validity_bounds_flag_stretch_and_ignore_rigid_motion():
    rest, F = patch(0.0)
    v = SurfaceValidity(F, rest)
    # A rigid turn by 150 degrees about x and a shift: the rest frame of the object, nothing invalid.
    c, s = np.cos(np.radians(150)), np.sin(np.radians(150))
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    assert v.counts(rest @ R.T + [0.1, 0, 0]).invalid == 0
    x = rest.copy()
    x[0, 0] -= (MAX_STRETCH + 0.5) * SIZE / CELLS  # one corner pulled out beyond the bound
    got = v.counts(x)
    assert got.torn >= 1 and got.invalid >= 1


def test_untouched_step_is_left_alone(tool):
    rest, F = two_patches()
    x1 = rest + np.array([0.0, 0.0, 1e-4])  # everything moves together: nothing to do
    stage, out, _, _ = corrected(rest, F, x1, tool, pose(0, 0, 0.05), pose(0, 0, 0.05))
    assert out.pairs_before == out.invalid_before == out.moved == 0 and not out.fallback
    np.testing.assert_array_equal(out.positions, x1)


def test_fallback_is_clean_for_self_and_tool(tool):
    rest, F = two_patches()
    x1 = bulge(rest)
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    stage = SelfContact(F, len(rest), rest, max_rounds=0)  # no repair: straight to the fallback
    p0, p1 = pose(0, 0, 0.0165), turned(0.002, 0, 0.015)  # the tool presses on the upper patch and drags
    T0, T1 = tool.world_vertices(p0), tool.world_vertices(p1)
    c = corr.correct(rest, x1, p0, p1, T0, T1)
    out = stage.correct(corr, rest, c.positions, p0, p1, T0, T1)
    assert out.fallback and out.local and out.region == 0  # the tool pass's check passes: nothing carried
    assert_clean(stage, F, rest, out, tool, T0, T1)
    # The local tier: the lower patch's bump goes back to rest where it crossed the upper patch (its top, a zone
    # grown around the crossing), and keeps the proposal where it crossed nothing (its foot).
    assert out.local
    n = len(rest) // 2
    stayed = np.all(out.positions[:n] == rest[:n], axis=1)
    kept = np.all(out.positions[:n] == x1[:n], axis=1)
    assert np.all(stayed | kept) and stayed[n // 2] and (kept & (x1[:n, 2] > 0)).any()


def test_the_global_fallback_is_clean_for_self_and_tool(tool, monkeypatch):
    """The same step when the local tier finds nothing clean (monkeypatched off): the global tier keeps the previous
    state but where the tool requires."""
    monkeypatch.setattr(SelfContact, "_local_fallback", lambda self, *args: None)
    rest, F = two_patches()
    x1 = bulge(rest)
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    stage = SelfContact(F, len(rest), rest, max_rounds=0)
    p0, p1 = pose(0, 0, 0.0165), turned(0.002, 0, 0.015)
    T0, T1 = tool.world_vertices(p0), tool.world_vertices(p1)
    out = stage.correct(corr, rest, corr.correct(rest, x1, p0, p1, T0, T1).positions, p0, p1, T0, T1)
    assert out.fallback and not out.local and out.region > 0
    assert_clean(stage, F, rest, out, tool, T0, T1)
    # The lower patch, which the fallback does not need, stays where it was (its bump is dropped); on the upper one
    # nothing moves farther than the tool's step (the rigid region moves with it, its soft border less).
    moved = np.linalg.norm(out.positions - rest, axis=1)
    n = len(rest) // 2
    assert np.all(moved[:n] == 0) and moved[n:].max() <= np.linalg.norm(p1[:3] - p0[:3]) + 1e-7  # (turned 1e-6 rad)


def dragging_fallback_case(tool, cells: int = 48):
    """The tool presses into the upper patch and drags 4 mm in one step, while a spike of the lower patch passes
    through the upper one far from the tool (a self pair: no pair-free state to give way to, so the fallback is
    published). Returns (stage, rest, faces, the published result, T0, T1)."""
    rest, F = two_patches(cells=cells)
    x1 = rest.copy()
    x1[40 * (cells + 1) + 40, 2] = 0.009
    corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
    stage = SelfContact(F, len(rest), rest, max_rounds=0)  # no repair rounds: straight to the fallback
    h = 0.006 + 0.008  # the sphere resting on the upper patch
    p0, p1 = pose(0, 0, h + 2e-4), pose(0.004, 0, h - 5e-4)
    T0, T1 = tool.world_vertices(p0), tool.world_vertices(p1)
    out = stage.correct(corr, rest, corr.correct(rest, x1, p0, p1, T0, T1).positions, p0, p1, T0, T1)
    return stage, rest, F, out, T0, T1


def test_a_fallback_keeps_its_rigid_region_small_with_a_soft_border(tool):
    """The rigid region moves 4 mm with the tool; with a hard border every ring around it tore and the region spread
    over the whole upper patch (2,401 vertices). A ramp over BLEND_RINGS rings keeps it near the tool: 97 vertices
    move the whole step, a few hundred less, the rest of the object not at all, and the result is clean."""
    stage, rest, F, out, T0, T1 = dragging_fallback_case(tool)
    n = len(rest) // 2
    moved = np.linalg.norm(out.positions - rest, axis=1)
    assert out.fallback and 0 < out.region < n // 10 and out.fallback_rounds == 0
    assert np.all(moved[:n] == 0) and 0 < np.count_nonzero(moved[n:]) < n // 4
    assert_clean(stage, F, rest, out, tool, T0, T1)


def test_a_fallback_region_that_must_spread_over_the_object_grows_in_logarithmically_many_rounds(tool, monkeypatch):
    """Without the soft border (as when it fails its check), the same case needs the rigid region over the whole
    patch (about 24 rings). One ring a round took a round each (each round is a check: seconds on a torn step); 2, 4,
    8, ... rings a round keep the rounds logarithmic, and the result is clean."""
    monkeypatch.setattr(SelfContact, "_soft_border", lambda self, *args: None)
    cells = 48
    stage, rest, F, out, T0, T1 = dragging_fallback_case(tool, cells)
    assert out.fallback and out.region >= len(rest) // 2  # the whole upper patch turned with the tool
    assert 3 <= out.fallback_rounds <= GROW_DOUBLING + int(np.ceil(np.log2(cells))) + 1 < cells // 2
    assert_clean(stage, F, rest, out, tool, T0, T1)


def test_the_repair_rounds_stop_at_a_fixed_point_with_the_outcome_of_running_them_all(tool, monkeypatch):
    """The sphere presses the upper patch 9 mm down through the lower one while moving 3 mm: from round 5 on the
    rounds return the state they start from. They stop there; the outcome is bit for bit that of all rounds."""
    import colgnn_core.collision.self_contact as self_contact

    rest, F = two_patches()
    h = 0.006 + 0.008 + 3e-4  # the sphere just above the upper patch
    p0, p1 = pose(0, 0, h), pose(0.003, 0, h - 0.009)
    T0, T1 = tool.world_vertices(p0), tool.world_vertices(p1)

    def run():
        corr = CollisionCorrector(F, len(rest), tool, dhat=5e-4)
        stage = SelfContact(F, len(rest), rest)
        return stage, stage.correct(corr, rest, corr.correct(rest, rest, p0, p1, T0, T1).positions, p0, p1, T0, T1)

    stage, out = run()
    monkeypatch.setattr(self_contact, "STATELESS_ROUND", 10**6)  # every round runs
    _, full = run()
    assert out.pairs_before > 0 and out.rounds < full.rounds == stage.max_rounds
    np.testing.assert_array_equal(out.positions, full.positions)
    assert (out.fallback, out.region, out.pairs_after, out.invalid_after, out.tool_fallback) == \
        (full.fallback, full.region, full.pairs_after, full.invalid_after, full.tool_fallback)
    assert_clean(stage, F, rest, out, tool, T0, T1)

def test_rest_touching_itself_is_refused():
    rest, F = two_patches(gap=1e-7)
    with pytest.raises(InputError, match="touches itself"):
        SelfContact(F, len(rest), rest)


def test_self_clearance_threshold_is_kept_over_the_step(tool):
    rest, F = two_patches(gap=0.002)
    x1 = rest.copy()
    n = len(rest) // 2
    x1[:n, 2] += 0.0019  # the lower patch stops 0.1 mm under the upper one: closer than the start allows
    stage, out, T0, T1 = corrected(rest, F, x1, tool, pose(0, 0, 0.05), pose(0, 0, 0.05))
    upper, lower = out.positions[n:, 2].min(), out.positions[:n, 2].max()
    assert upper - lower > SELF_CLEARANCE


def turn_about_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_rigid_fit_recovers_a_rigid_motion():
    rest, _ = two_patches()
    R = turn_about_z(0.7) @ np.array([[1.0, 0, 0], [0, 0.6, -0.8], [0, 0.8, 0.6]])
    p = np.array([0.3, -0.1, 0.05])
    ids = np.arange(len(rest))
    got_R, got_p = rigid_fit(rest @ R.T + p, rest, ids)
    np.testing.assert_allclose(got_R, R, atol=1e-12)
    np.testing.assert_allclose(got_p, p, atol=1e-12)


def test_hot_vertices_are_counted_from_the_object_s_rigid_motion_not_from_rest():
    rest, F = two_patches()
    stage = SelfContact(F, len(rest), rest)
    x0 = rest @ turn_about_z(0.2).T + [0.05, 0.0, 0.01]
    x1 = rest @ turn_about_z(0.3).T + [0.052, 0.0, 0.012]  # turned 0.1 rad and moved 2 mm: nothing deforms
    assert stage.deviation(x0, x1)[0].max() < 1e-12 and stage.check(x0, x1).clean
    # The same motion with the lower patch's middle pushed 12 mm up through the upper one: only the bump is hot.
    bumped = bulge(rest) @ turn_about_z(0.3).T + [0.052, 0.0, 0.012]
    chk = stage.check(x0, bumped)
    n = len(rest) // 2
    moved = np.linalg.norm(bulge(rest) - rest, axis=1) > stage.quiet
    assert 0 < chk.hot <= int(moved.sum()) < n
    assert chk.pairs > 0  # the pass-through is found


def test_quiet_pairs_under_the_rigid_motion_are_still_checked():
    """Two patches 2 mm apart carried 5 cm away in one step while the lower one rises 1.95 mm: every vertex stays
    within ``quiet`` (2 mm here) of the fitted rigid motion, so only the rest-pair bound with the fit's deviations can
    find the pair that comes within 50 um; the stage keeps it apart."""
    rest, F = two_patches(gap=0.002)
    n = len(rest) // 2
    corr = CollisionCorrector(F, len(rest), make_tool("sphere", {"radius": 0.008}, "ci"), dhat=5e-4)
    stage = SelfContact(F, len(rest), rest, quiet=0.002)
    x1 = rest + [0.05, 0.0, 0.0]
    x1[:n, 2] += 0.00195
    dev, sigma = stage.deviation(rest, x1)
    assert dev.max() < stage.quiet and sigma == pytest.approx(1.0)
    chk = stage.check(rest, x1)
    assert chk.hot == 0 and chk.pairs > 0
    far = pose(0, 0, 0.5)
    T = corr.tool.world_vertices(far)
    out = stage.correct(corr, rest, x1, far, far, T, T)
    assert out.positions[n:, 2].min() - out.positions[:n, 2].max() > SELF_CLEARANCE
