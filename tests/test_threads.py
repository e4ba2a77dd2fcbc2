"""Thread counts for stepping: auto_threads, and the guard that puts the collision kernels on one thread while other
processes hold the cores (the real machine's stall counter included)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numba
import numpy as np
import pytest

from colgnn_core.runtime.threads import (MAX_INTERVAL_S, QUIET_SAMPLES, STALL_FRACTION, ContentionGuard,
                                         auto_threads, cpu_stall_us, fastest_thread_count, other_runnable_tasks)
from tests.helpers import train_data as fx
from tests.helpers.correction_cases import make_model


class FakeMachine:
    """A stall counter and a clock: each call to ``tick`` advances 40 ms (a 25 Hz step) with ``busy`` of it stalled."""

    def __init__(self, own: bool = False):
        self.t, self.stalled_us, self.busy, self.own = 0.0, 0, 0.0, own
        self.others_now = 0

    def tick(self, busy: float) -> None:
        """``busy``: the stalled fraction; caused by another process's runnable task unless the machine is ``own``
        (this process's own threads, as in one process benching scene after scene)."""
        self.t += 0.04
        self.stalled_us += int(busy * 0.04e6)
        self.others_now = 1 if busy > 0 and not self.own else 0

    def guard(self, requested: int = 2, **kw) -> ContentionGuard:
        return ContentionGuard(requested, stall=lambda: self.stalled_us, clock=lambda: self.t,
                               others=lambda: self.others_now, **kw)


def _run(machine: FakeMachine, guard: ContentionGuard, busy: list[float]) -> list[int]:
    out = []
    for b in busy:
        machine.tick(b)
        out.append(guard.threads())
    return out


@pytest.mark.parametrize("cores, threads", [(1, 1), (2, 1), (4, 1), (6, 3), (8, 4), (64, 4)])
def test_auto_threads_keeps_one_thread_on_small_machines(cores, threads):
    assert auto_threads(cores) == threads


def test_guard_keeps_the_threads_on_a_free_machine_despite_single_busy_intervals():
    m = FakeMachine()
    g = m.guard(2)
    # The free 2-core machine's measured pattern: mostly 0, single intervals up to 0.19 stalled.
    busy = [0.0] * 30 + [0.19] + [0.0] * 10 + [0.13, 0.0, 0.0, 0.19] + [0.0] * 20
    assert _run(m, g, busy) == [2] * len(busy)
    assert g.reduced_steps == 0


def test_guard_drops_to_one_thread_beside_a_busy_process_and_gives_the_threads_back_after_quiet_steps():
    m = FakeMachine()
    g = m.guard(2)
    assert _run(m, g, [0.0] * 5) == [2] * 5
    beside = _run(m, g, [0.5] * 20)  # one busy process on 2 cores: half the time some task waits
    assert beside[:1] == [2] and beside[2:] == [1] * 18  # smoothed: it trips on the second busy interval
    after = _run(m, g, [0.0] * (QUIET_SAMPLES + 20))
    first_back = after.index(2)
    # The smoothed level decays below STALL_FRACTION within a few steps, then QUIET_SAMPLES calm calls follow.
    assert QUIET_SAMPLES <= first_back <= QUIET_SAMPLES + 8 and set(after[first_back:]) == {2}
    assert g.reduced_steps == beside.count(1) + first_back



def test_a_long_pause_between_steps_does_not_count_as_contention():
    # colgnn bench: the IPC solver's threads keep the cores busy for seconds between the Predictor's steps.
    m = FakeMachine()
    g = m.guard(2)
    assert _run(m, g, [0.0, 0.0]) == [2, 2]
    m.t += 2 * MAX_INTERVAL_S
    m.stalled_us += int(0.9 * 2 * MAX_INTERVAL_S * 1e6)
    assert g.threads() == 2 and g.level == 0.0
    assert _run(m, g, [0.0] * 3) == [2] * 3 and g.reduced_steps == 0

def test_guard_trusts_the_request_without_a_stall_counter_and_never_reads_it_for_one_thread():
    g = ContentionGuard(4, stall=lambda: None)
    assert [g.threads() for _ in range(5)] == [4] * 5

    def unreadable():
        raise AssertionError("read although one thread was requested")

    assert ContentionGuard(1, stall=unreadable).threads() == 1
    with pytest.raises(ValueError, match="requested threads"):
        ContentionGuard(0)
    assert 0 < STALL_FRACTION < 0.5  # below a single busy neighbour's 0.5 on 2 cores


def test_cpu_stall_us_reads_the_machine_or_says_it_cannot(tmp_path):
    a = cpu_stall_us()
    if a is not None:
        time.sleep(0.01)
        assert isinstance(a, int) and 0 <= a <= cpu_stall_us()
    bad = tmp_path / "cpu"
    bad.write_text("garbage\n")
    assert cpu_stall_us(str(bad)) is None and cpu_stall_us(str(tmp_path / "missing")) is None
    good = tmp_path / "psi"
    good.write_text("some avg10=0.00 avg60=0.00 avg300=0.00 total=12345\nfull avg10=0.00 avg60=0.00 avg300=0.00 "
                    "total=0\n")
    assert cpu_stall_us(str(good)) == 12345


def test_guard_keeps_the_threads_when_only_this_process_stalls_the_cores():
    """One process benching scene after scene: its own threads make tasks wait (stall 0.5), and no other process has
    a runnable task. Not contention: the kernels keep their threads (they lost them in 10-18 of 19 steps before)."""
    m = FakeMachine(own=True)
    g = m.guard(2)
    assert _run(m, g, [0.5] * 30) == [2] * 30 and g.reduced_steps == 0
    m.own = False  # then a real neighbour starts
    beside = _run(m, g, [0.5] * 5)
    assert beside[0] == 2 and beside[1:] == [1] * 4


def test_other_runnable_tasks_reads_the_machine_or_says_it_cannot(tmp_path):
    n = other_runnable_tasks()
    assert n is None or n >= 0
    (tmp_path / "loadavg").write_text("0.50 0.40 0.30 3/250 12345\n")
    task = tmp_path / "task"
    for tid, state in ((11, "R"), (12, "S"), (13, "R")):
        (task / str(tid)).mkdir(parents=True)
        (task / str(tid) / "stat").write_text(f"{tid} (py (thread)) {state} 1 2 3\n")
    assert other_runnable_tasks(str(tmp_path / "loadavg"), str(task)) == 1  # 3 running, 2 of them ours
    assert other_runnable_tasks(str(tmp_path / "missing"), str(task)) is None
    (tmp_path / "bad").write_text("garbage\n")
    assert other_runnable_tasks(str(tmp_path / "bad"), str(task)) is None


def _cpu_ticks(pid: int) -> int:
    """User + system clock ticks a process has run (``/proc/PID/stat`` fields 14 and 15)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


@pytest.mark.skipif(cpu_stall_us() is None, reason="this kernel has no CPU pressure stall information")
def test_guard_sees_real_busy_processes_on_every_core():
    # Twice as many busy processes as cores: whatever else runs, some task waits for a CPU nearly all the time.
    # Bare interpreters, not multiprocessing's spawn: a spawned child imports this module (and torch with it), which
    # on a loaded CI machine outlasted the sampling below, so the guard sampled a calm machine.
    spin = "import time\nend = time.monotonic() + 20\nwhile time.monotonic() < end: pass\n"
    procs = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(2 * (os.cpu_count() or 1))]
    try:
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not all(_cpu_ticks(p.pid) > 10 for p in procs):
            time.sleep(0.05)  # each has spun for a tenth of a second: all of them are past start-up
        g = ContentionGuard(2)
        answers = []
        for _ in range(10):
            time.sleep(0.04)
            answers.append(g.threads())
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert answers[-5:] == [1] * 5 and g.level > STALL_FRACTION


def test_predictor_steps_its_kernels_on_the_guards_count():
    scene = fx.scene()
    m = FakeMachine()
    from colgnn_core.runtime.predictor import Predictor

    p = Predictor(make_model(scene, "noisy"), scene, threads=1)
    p.kernel_guard = m.guard(2)  # as a Predictor asked for 2 threads has it, on a fake busy machine
    pose = np.asarray(scene.tool_rest_pose, dtype=np.float64)
    counts = []
    for busy in (0.0, 0.0, 0.9, 0.9, 0.9):
        m.tick(busy)
        counts.append(p.step(pose).kernel_threads)
        assert numba.get_num_threads() == counts[-1]
    assert counts == [2, 2, 2, 1, 1]  # 0.9 of an interval stalled trips the smoothed level at once, and the second
    # sample of another process's runnable task confirms it a step later


@pytest.mark.parametrize("ms_one, ms_two, drift, expected", [
    (7.5, 9.9, 0.0, 1),    # session 27's sphere_mat network: 1 thread clearly faster
    (9.0, 9.2, 0.0, 2),    # within the margin: keep the request
    (10.0, 6.0, 0.0, 2),   # the parallel pool pays off
    (7.5, 9.9, 0.4, 1),    # the machine slows by 40% a call: alternating rounds still see 1 thread faster
])
def test_fastest_thread_count_times_both_counts_alternately(ms_one, ms_two, drift, expected):
    """A fake clock whose call time depends on the thread count set (and on a drift of the machine's speed)."""
    state = {"threads": 2, "t": 0.0, "calls": 0, "sets": []}

    def set_threads(n):
        state["threads"] = n
        state["sets"].append(n)

    def run():
        state["calls"] += 1
        state["t"] += 1e-3 * (ms_one if state["threads"] == 1 else ms_two) * (1 + drift * state["calls"] / 30)

    got = fastest_thread_count(run, 2, set_threads, clock=lambda: state["t"], rounds=3, calls=5)
    assert got == expected
    assert state["calls"] == 30 and state["sets"] == [2, 1, 2, 1, 2, 1, 2]  # alternating, the request restored
    assert fastest_thread_count(run, 1, set_threads) == 1 and state["calls"] == 30  # nothing to choose: no timing


def test_compiled_predictor_times_its_network_threads_and_gives_the_same_steps():
    """A compiled Predictor asked for 2 threads runs its network on 1 or 2 (timed at warm-up), leaves the process
    at 2 after every step, steps as it does with the network on the other count (float32 rounding), and compiles
    nothing while stepping at either count (torch's thread count is part of a compiled variant's guards: a count
    met first mid-run compiled then, a 330-415 ms step in session 27's first try)."""
    import torch
    from torch._dynamo.utils import counters

    from colgnn_core.evaluation.measure import family_poses
    from colgnn_core.runtime.predictor import Predictor

    scene = fx.scene()
    p = Predictor.from_checkpoint(str(fx.trained_checkpoint("full")), threads=2, compile=True)
    assert p.compiled and p.net.network_threads in (1, 2)
    poses = family_poses(scene, 6)
    p.reset(tool_pose=poses[0])
    compiled_frames = counters["frames"]["ok"]
    picked = []
    for pose in poses[1:]:
        picked.append(p.step(pose).positions)
        assert torch.get_num_threads() == 2
    p.reset(tool_pose=poses[0])
    p.net.network_threads = 1 if p.net.network_threads == 2 else 2  # the other count
    scale = scene.bbox_diagonal()
    for pose, a in zip(poses[1:], picked):
        assert np.abs(p.step(pose).positions - a).max() < 1e-5 * scale
        assert torch.get_num_threads() == 2
    assert counters["frames"]["ok"] == compiled_frames


def test_torch_threads_sets_the_count_for_a_block_and_restores_it_even_on_error():
    import torch

    from colgnn_core.runtime.threads import torch_threads

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with torch_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError, match="inside"):
            with torch_threads(1):
                raise RuntimeError("inside")
        assert torch.get_num_threads() == 2
        with torch_threads(None):  # None: the count as it is
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_predictor_on_2_threads_builds_its_graph_on_1_and_steps_as_on_2():
    """The step's small tensor operations run on STEP_THREADS (1): on a shared 2-core machine each 2-thread OpenMP
    region of graph building waits milliseconds for a parked worker (docs/SPEED.md, session 43). The network keeps
    its own count, the process is left at 2, and the steps are the same as with everything on 2 threads."""
    import torch

    from colgnn_core.evaluation.measure import family_poses
    from colgnn_core.runtime.predictor import Predictor
    from colgnn_core.runtime.stepper import STEP_THREADS

    assert STEP_THREADS == 1
    scene = fx.scene()
    before = torch.get_num_threads()
    try:
        p = Predictor.from_checkpoint(str(fx.trained_checkpoint("full")), threads=2)
        seen = {"graph": [], "network": []}
        build, network = p.model.build_graph, p.model.network
        p.model.build_graph = lambda frame: (seen["graph"].append(torch.get_num_threads()), build(frame))[1]
        p.model.network = lambda *a, **k: (seen["network"].append(torch.get_num_threads()), network(*a, **k))[1]
        poses = family_poses(scene, 5)
        steps = {}
        for threads in (STEP_THREADS, None):
            p.net.step_threads = threads
            p.reset(tool_pose=poses[0])
            steps[threads] = [p.step(pose).positions for pose in poses[1:]]
            assert torch.get_num_threads() == 2
        n = len(poses) - 1
        assert seen["graph"][:n] == [1] * n and seen["graph"][n:] == [2] * n
        assert seen["network"] == [2] * (2 * n)  # not timed (no warm-up): the Predictor's count
        for a, b in zip(steps[STEP_THREADS], steps[None]):
            assert np.abs(a - b).max() < 1e-6 * scene.bbox_diagonal()
    finally:
        torch.set_num_threads(before)


def test_blas_threads_sets_numpys_blas_for_a_block_and_restores_it_even_on_error():
    from threadpoolctl import threadpool_info

    from colgnn_core.runtime.threads import blas_threads

    def counts() -> set[int]:
        return {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"}

    before = counts()
    assert before  # numpy's OpenBLAS is loaded
    with blas_threads(1):
        assert counts() == {1}
    assert counts() == before
    with pytest.raises(RuntimeError, match="inside"):
        with blas_threads(1):
            raise RuntimeError("inside")
    assert counts() == before
    with blas_threads(None):
        assert counts() == before


def test_the_stepper_runs_its_physics_prior_on_one_blas_thread(tmp_path, monkeypatch):
    """The modal contact prior's small products on several OpenBLAS threads stalled the network's pool (bench p95
    132 ms against 27 on the full banana, docs/FIDELITY.md session 44): the stepper limits them to
    PRIOR_BLAS_THREADS."""
    from threadpoolctl import threadpool_info

    from colgnn_core.learn.graph import template_from_scene
    from colgnn_core.learn.model import ModelConfig
    from colgnn_core.runtime.models import PriorModel
    from colgnn_core.runtime.stepper import PRIOR_BLAS_THREADS, RawStepper
    from colgnn_core.scenes import load_scene
    from colgnn_core.scenes.hard_cases import press_pose
    from colgnn_core.sim.contact_prior import ContactPrior

    assert PRIOR_BLAS_THREADS == 1
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    scene = load_scene("sphere_mat", "ci")
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    template = template_from_scene(scene, surface_only=True)
    config = ModelConfig(latent=8, message_passing_steps=1, mlp_layers=1, order=0, quasi_static=True,
                         contact_prior=True, prior_compliance="modal")
    stepper = RawStepper(PriorModel(template, rest[template.object_nodes], config), scene, rest_mesh=rest)
    seen = []
    step = ContactPrior.step

    def recording(self, *args):
        seen.append({pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"})
        return step(self, *args)

    monkeypatch.setattr(ContactPrior, "step", recording)
    stepper.reset(rest[template.object_nodes], press_pose(scene, 0.0))
    stepper.step(press_pose(scene, 0.3))
    assert seen == [{1}]
