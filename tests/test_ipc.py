"""IPC stepper: rest states, a pressing tool, exact targets, verification, bad input, real scenes."""

import numpy as np
import pytest

from colgnn_core.errors import InputError, SimulationError
from colgnn_core.io import Sequence
from colgnn_core.sim.dataset import simulate_sequence
from colgnn_core.sim.ipc import IPCSimulator
from tests.helpers.sim_scenes import assert_sequence_crossing_free, box_scene


def test_body_without_forces_stays_exactly_at_rest():
    scene = box_scene(ground=False, gravity=False)
    sim = IPCSimulator(scene, newton_tol=1e-8)
    x0 = sim.positions
    for _ in range(3):
        st = sim.step(scene.tool_rest_pose)
        assert st.converged and st.newton_iterations == 1
    assert np.array_equal(sim.positions, x0)
    assert np.array_equal(sim.tool_positions, scene.tool.world_vertices(scene.tool_rest_pose))


@pytest.mark.parametrize("friction", [0.0, 0.3])
def test_body_settled_on_ground_stays_at_rest(friction):
    """With gravity and a ground, frame 0 is the settled state; it then stays put to solver tolerance."""
    scene = box_scene(friction=friction)
    sim = IPCSimulator(scene)
    x0 = sim.positions
    gap = x0[:, 2].min() - scene.ground_height
    assert 0 < gap < sim.dhat  # resting on the ground barrier, not floating at its initial 0.5 mm
    tol = sim.newton_tol * sim.bbox_diagonal * sim.dt
    for _ in range(5):
        st = sim.step(scene.tool_rest_pose)
        assert st.newton_iterations <= 2
    assert np.abs(sim.positions - x0).max() <= tol
    assert np.abs(sim.positions - scene.object.vertices).max() < 0.001  # only the 0.5 mm fall, no drift


@pytest.fixture(scope="module")
def pressed():
    """A sphere pressing 8 mm into the slab (2 mm per frame), simulated once."""
    scene = box_scene(tool_z=0.0425)
    sim = IPCSimulator(scene)
    frames = [(sim.positions, sim.tool_positions)]
    poses = [scene.tool_rest_pose.copy()]
    stats = []
    for k in range(1, 6):
        pose = scene.tool_rest_pose.copy()
        pose[0] += 0.0005 * k  # a little lateral drift too
        pose[2] -= 0.002 * k
        stats.append(sim.step(pose))
        frames.append((sim.positions, sim.tool_positions))
        poses.append(pose)
    seq = Sequence(
        object_positions=np.stack([f[0] for f in frames]),
        object_faces=np.asarray(scene.object.faces),
        tool_positions=np.stack([f[1] for f in frames]),
        tool_faces=np.asarray(scene.tool.faces),
        tool_poses=np.stack(poses),
        dt=scene.dt,
    )
    return scene, sim, seq, stats


def test_pressing_tool_reaches_its_exact_target(pressed):
    scene, sim, seq, stats = pressed
    for t in range(seq.frames):
        assert np.array_equal(seq.tool_positions[t], scene.tool.world_vertices(seq.tool_poses[t]))
    assert all(s.converged for s in stats)


def test_pressing_deforms_the_slab_and_keeps_the_gap(pressed):
    scene, sim, seq, stats = pressed
    # The slab top under the sphere is pushed down by several mm; the gap to the tool stays >= dmin.
    top = seq.object_positions[0][:, 2] > 0.0199
    centre = top & (np.linalg.norm(seq.object_positions[0][:, :2], axis=1) < 0.012)
    dz = seq.object_positions[-1][centre, 2] - seq.object_positions[0][centre, 2]
    assert dz.min() < -0.004
    d_tool = scene.tool.sdf(seq.object_positions[-1], seq.tool_poses[-1])
    assert d_tool.min() > 0.9 * sim.dmin
    assert stats[-1].min_distance > 0
    assert np.all(sim.elastic.jacobians(seq.object_positions[-1]) > 0)


def test_pressed_sequence_is_crossing_free_by_exact_ccd(pressed):
    scene, sim, seq, stats = pressed
    assert_sequence_crossing_free(seq, scene.ground_height)


def test_step_rejects_a_malformed_pose():
    sim = IPCSimulator(box_scene(gravity=False, ground=False))
    with pytest.raises(InputError):
        sim.step(np.array([0, 0, 0.05, 0, 0, 0, np.nan]))
    with pytest.raises(InputError):
        sim.step(np.array([0, 0, 0.05, 0, 0, 0, 2.0]))  # quaternion not unit length


def test_tool_starting_inside_the_object_is_a_simulation_error():
    scene = box_scene(gravity=False, ground=False)
    with pytest.raises(SimulationError, match="frame 0"):
        IPCSimulator(scene, initial_tool_pose=np.array([0.0, 0.0, 0.025, 0, 0, 0, 1.0]))


def test_failed_frame_names_the_frame_and_keeps_the_state():
    """A tool jumping straight through the slab in one frame cannot be resolved within 3 Newton iterations."""
    scene = box_scene(tool_z=0.0425, gravity=False, ground=False)
    sim = IPCSimulator(scene, max_newton=3)
    x0 = sim.positions
    with pytest.raises(SimulationError, match="frame 1"):
        sim.step(np.array([0.0, 0.0, 0.005, 0, 0, 0, 1.0]))
    assert np.array_equal(sim.positions, x0) and sim.frame == 0


SCENES = ["cone_bunny", "knife_torus", "sphere_mat", "cylinder_banana"]


@pytest.mark.parametrize("name", SCENES)
def test_ci_scene_short_sequence_is_crossing_free(name):
    """14 frames of each scene at 'ci' (the tool reaches the object): verified again with exact CCD. A family whose
    first stroke travels (the banana's) is taken from where that stroke descends."""
    from colgnn_core.scenes import load_scene
    from colgnn_core.scenes.trajectories import sample_pressing_poses

    scene = load_scene(name, "ci")
    seq = simulate_sequence(scene, sample_pressing_poses(scene, 1, 14))
    assert_sequence_crossing_free(seq, scene.ground_height)
    assert seq.extra["newton_iterations"][1:].min() >= 1
    # The tool really touched the object (the barrier was active at some frame).
    assert seq.extra["min_distance"].min() < 3 * float(seq.extra["dmin"])


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENES)
def test_every_ci_scene_40_frames_is_crossing_free(name):
    from colgnn_core.scenes import load_scene, sample_poses

    scene = load_scene(name, "ci")
    seq = simulate_sequence(scene, sample_poses(scene, 2, 40))
    assert_sequence_crossing_free(seq, scene.ground_height)


@pytest.mark.parametrize("friction", [0.0, 0.3])
def test_ground_friction_stops_a_sliding_body(friction):
    """A slab sliding at 5 cm/s on the ground: frictionless it keeps going, with μ = 0.3 it stops
    within one 40 ms frame (Coulomb: after v²/(2μg) = 0.42 mm)."""
    scene = box_scene(friction=friction)
    sim = IPCSimulator(scene)
    x0 = sim.positions
    sim.v[:] = [0.05, 0.0, 0.0]
    for _ in range(5):
        sim.step(scene.tool_rest_pose)
    dx = float(np.mean(sim.positions[:, 0] - x0[:, 0]))
    if friction == 0:
        assert dx == pytest.approx(0.05 * 5 * sim.dt, rel=0.02)
    else:
        # Implicit Euler: h·v = 2 mm < μ·g·h² = 4.7 mm, so the slab sticks within the first step.
        assert 0.0 <= dx < 2 * 0.05**2 / (2 * friction * 9.81)
        assert np.abs(sim.v[:, 0]).max() < 1e-3


def test_ground_friction_gradient_matches_finite_differences():
    scene = box_scene(friction=0.5)
    sim = IPCSimulator(scene)
    lam = sim._ground_lambda(sim.positions)
    assert lam is not None and lam.max() > 0
    rng = np.random.default_rng(0)
    eps_v = sim.friction_eps_v * sim.dt
    for scale in (0.3 * eps_v, 5 * eps_v):  # the smoothed (static) and the sliding regimes
        xo = sim.positions + np.c_[rng.normal(scale=scale, size=(sim.n_obj, 2)), np.zeros(sim.n_obj)]
        _, (ids, g), hess = sim._ground_friction(xo, lam, 2)
        h = 1e-10
        for n in range(3):
            i, d = ids[n], n % 2
            xp, xm = xo.copy(), xo.copy()
            xp[i, d] += h
            xm[i, d] -= h
            fd = (sim._ground_friction(xp, lam, 0)[0] - sim._ground_friction(xm, lam, 0)[0]) / (2 * h)
            assert fd == pytest.approx(g[n, d], rel=1e-4, abs=1e-12)
        assert np.all(np.linalg.eigvalsh(hess) >= -1e-12)


def test_pcg_solves_the_newton_system_like_a_factorisation_or_hands_it_over():
    """The Newton system's CG: Jacobi-preconditioned to PCG_RTOL on an SPD system like the simulator's (mass-dominated
    diagonal plus a stiff coupled block); None where CG cannot (a non-positive diagonal, or too few iterations), so
    that the caller factorises instead."""
    import scipy.sparse as sp

    from colgnn_core.sim.linear_solve import pcg_solve

    rng = np.random.default_rng(0)
    n = 300
    a = sp.random(n, n, density=0.02, random_state=1)
    h = (a @ a.T * 50.0 + sp.eye(n) * 2.0).tocsr()  # SPD, far from diagonal
    r = rng.normal(size=n)
    x = pcg_solve(h, r)
    assert x is not None
    np.testing.assert_allclose(x, np.linalg.solve(h.toarray(), r), rtol=0, atol=1e-6 * np.abs(x).max())
    assert np.array_equal(pcg_solve(h, np.zeros(n)), np.zeros(n))
    assert pcg_solve(h - sp.eye(n) * 10.0, r) is None  # a non-positive diagonal entry: not for CG
    assert pcg_solve(h, r, max_iterations=2) is None  # not converged: the factorisation takes over


def _chain(n: int, shift: float):
    """A stiff 1-D chain: the Laplacian of n nodes plus ``shift`` on the diagonal (condition number ~ 4 / shift)."""
    import scipy.sparse as sp

    return (sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]) + shift * sp.eye(n)).tocsr()


def test_the_newton_solver_factorises_a_stiff_system_once_and_reuses_the_factor():
    """A system too stiff for Jacobi CG (a long chain: a stiff object's Hessian has the same trouble) is factorised
    once; the next systems of the same free set, nearby in value, are solved by CG preconditioned with that lagged
    factor, every one to PCG_RTOL. A mass-dominated system never factorises."""
    from colgnn_core.sim.linear_solve import PCG_RTOL, NewtonSystemSolver

    rng = np.random.default_rng(0)
    n = 4000
    solver = NewtonSystemSolver()
    for k in range(4):
        h = _chain(n, 1e-6 * (1.0 + 0.3 * k))  # condition ~ 4e6: CG would need thousands of Jacobi iterations
        r = rng.normal(size=n)
        x = solver.solve(h, r, key=n)
        assert np.linalg.norm(h @ x - r) <= 10 * PCG_RTOL * np.linalg.norm(r)
    assert solver.jacobi_failed and solver.factorisations == 1
    soft = NewtonSystemSolver()
    h = _chain(n, 5.0)  # the mass term dominates
    x = soft.solve(h, np.ones(n), key=n)
    assert np.linalg.norm(h @ x - 1.0) <= 10 * PCG_RTOL * np.sqrt(n)
    assert not soft.jacobi_failed and soft.factorisations == 0


def test_a_system_that_jacobi_cg_solves_slowly_is_factorised_from_then_on():
    """Converging is not enough: more than JACOBI_SLOW_ITERATIONS switches the simulation to the lagged factor (the
    soft banana's deep presses took 200-400 Jacobi iterations a solve, 30-40 solves a frame)."""
    import scipy.sparse as sp

    from colgnn_core.sim.linear_solve import JACOBI_SLOW_ITERATIONS, PCG_RTOL, NewtonSystemSolver, pcg_solve

    n = 2000
    h = _chain(n, 2e-3)  # condition ~ 2e3: Jacobi CG converges, slowly
    stats: dict = {}
    assert pcg_solve(h, np.ones(n), stats=stats) is not None and stats["iterations"] > JACOBI_SLOW_ITERATIONS
    solver = NewtonSystemSolver()
    rng = np.random.default_rng(1)
    for k in range(5):
        hk = (h + 1e-4 * k * sp.eye(n)).tocsr()
        r = rng.normal(size=n)
        x = solver.solve(hk, r, key=n)
        assert np.linalg.norm(hk @ x - r) <= 10 * PCG_RTOL * np.linalg.norm(r)
    assert solver.jacobi_failed and solver.factorisations == 1  # one factor, reused by the four later systems
