"""Thread counts for stepping: the machine's default (:func:`auto_threads`) and a guard that runs the collision
kernels on one thread while other processes hold the cores (:class:`ContentionGuard`).

Both come from measurements on a 2-core machine. A parallel region (torch's OpenMP pool, numba's parallel
kernels) waits at its end for every worker; when another process holds a core, a parked worker runs a scheduler
time slice later (milliseconds). One region costs microseconds on a free machine, up to ~10 ms beside one busy
process, and a tool pass runs hundreds of them: random bunny steps beside three busy processes took up to 15 s
with the kernels on 2 threads, and under 0.3 s with them on 1 (docs/COLLISION_GUARANTEE.md, session 19).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache
from statistics import median

import torch
from threadpoolctl import ThreadpoolController

__all__ = ["MAX_INTERVAL_S", "QUIET_SAMPLES", "STALL_FRACTION", "ContentionGuard", "auto_threads", "cpu_stall_us",
           "blas_threads", "fastest_thread_count", "other_runnable_tasks", "torch_threads"]

QUIET_SAMPLES = 10     # uncontended calls in a row before the kernels get their threads back (0.4 s at 25 Hz)
STALL_FRACTION = 0.15  # contended: some task waited for a CPU this fraction of the time (smoothed, STALL_SMOOTHING)
STALL_SMOOTHING = 0.25  # weight of the latest interval in the smoothed fraction (a busy neighbour trips it in 2 calls)
MAX_INTERVAL_S = 1.0   # a longer interval between calls says little about now (an idle node, a solver run between)
OTHERS_WINDOW = 3      # contended also needs another process's task runnable in 2 of the last 3 samples of ...
OTHERS_NEEDED = 2      # ... other_runnable_tasks, taken only while the smoothed stall is above half STALL_FRACTION


def auto_threads(cpu_count: int | None = None) -> int:
    """The torch thread count for a real-time Predictor on a machine with ``cpu_count`` cores (default: this one).

    Measured on a 2-core machine (docs/SPEED.md): torch's OpenMP pool at 2 threads collapses (0.1-1.3 s per step)
    as soon as another process holds one of the cores, as the pose publisher and the recorder do next to the
    node, while 1 thread stays within ~30% of the quiet 2-thread step. So 1 thread up to 4 cores; above that, half
    the cores, at most 4 (not measured here: a larger machine has headroom for the pool).
    """
    n = int(cpu_count if cpu_count is not None else (os.cpu_count() or 1))
    return 1 if n <= 4 else min(4, n // 2)


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block on ``n`` torch threads (None: the process's count), restoring the count after."""
    before = torch.get_num_threads()
    if n is None or n == before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@lru_cache(maxsize=1)
def _blas() -> ThreadpoolController:
    """The process's BLAS pools (numpy's and scipy's OpenBLAS), found once at the first use (they are loaded by then:
    the physics priors import scipy.linalg when they are built)."""
    return ThreadpoolController()


@contextmanager
def blas_threads(n: int | None) -> Iterator[None]:
    """Run the block with numpy's and scipy's BLAS on ``n`` threads (None: as they are), restoring them after
    (about 9 us).

    Why: OpenBLAS's workers spin after a call, and torch's OpenMP pool then waits for a core. The full banana's
    modal contact prior (small dense products and Cholesky factorisations) on 2 BLAS threads beside a 2-thread
    network made single steps of the network take 90 ms (``colgnn bench`` p95 132 ms, against 27 with BLAS on one
    thread; docs/FIDELITY.md, session 44)."""
    if n is None:
        yield
        return
    with _blas().limit(limits=n, user_api="blas"):
        yield


def fastest_thread_count(run: Callable[[], object], requested: int, set_threads: Callable[[int], object],
                         clock: Callable[[], float] = time.perf_counter, rounds: int = 3, calls: int = 5,
                         margin: float = 0.05) -> int:
    """1 or ``requested``: the thread count at which ``run`` is faster here and now, timed alternately.

    ``set_threads(n)`` sets the count ``run`` uses; it is left at ``requested``. ``rounds`` x ``calls`` timed calls
    per count, the counts alternating round by round so that a drift of the machine's speed hits both; 1 wins only
    when its median is more than ``margin`` below that of ``requested`` (ties keep the request).

    Why: a small network's parallel regions can cost more than they save. On the 2-core AMD machine of session 27 the
    compiled network of every shipped model was as fast or faster on 1 torch thread as on 2 (``sphere_mat`` 7.5
    against 9.9 ms), while the collision kernels gain from 2 (docs/FIDELITY.md, session 27).
    """
    if requested <= 1:
        return 1
    times: dict[int, list[float]] = {requested: [], 1: []}
    try:
        for _ in range(rounds):
            for n, samples in times.items():
                set_threads(n)
                for _ in range(calls):
                    t = clock()
                    run()
                    samples.append(clock() - t)
    finally:
        set_threads(requested)
    return 1 if median(times[1]) < (1.0 - margin) * median(times[requested]) else requested


def cpu_stall_us(path: str = "/proc/pressure/cpu") -> int | None:
    """Microseconds, since boot, in which some runnable task on the machine waited for a CPU: the ``total`` of the
    ``some`` line of Linux's pressure stall information (PSI; kernel 4.20 on, ~8 us to read). None where it
    cannot be read (not Linux, or a kernel without PSI)."""
    try:
        with open(path, "rb") as f:
            return int(f.readline().split()[4].split(b"=")[1])
    except (OSError, IndexError, ValueError):
        return None


def other_runnable_tasks(loadavg: str = "/proc/loadavg", tasks: str = "/proc/self/task") -> int | None:
    """Runnable tasks on the machine that are not this process's threads, now: the running count of
    ``/proc/loadavg`` minus this process's threads in state R (the reading thread among them). None where it cannot
    be read. A snapshot: a busy process is in it at every read, this process's own parallel workers never are."""
    try:
        with open(loadavg, "rb") as f:
            running = int(f.read().split()[3].split(b"/")[0])
        own = 0
        for tid in os.listdir(tasks):
            try:
                with open(f"{tasks}/{tid}/stat", "rb") as f:
                    own += f.read().rsplit(b")", 1)[1].split()[0] == b"R"
            except (OSError, IndexError):
                continue  # the thread ended between the listing and the read
    except (OSError, IndexError, ValueError):
        return None
    return max(running - own, 0)


class ContentionGuard:
    """The thread count for the collision kernels of the next step: ``requested``, or 1 while other work keeps the
    machine's cores busy.

    Each call reads the machine's CPU stall time (:func:`cpu_stall_us`) and takes the fraction of the time since
    the last call in which some task waited for a CPU. Measured on the 2-core machine over Predictor steps at 2
    threads: 0.000 median (p90 0.002, single steps up to 0.19) when nothing else runs, 0.50 beside one busy
    process, 0.97 beside a 2-thread solver. So the fraction is smoothed (``STALL_SMOOTHING``), and a smoothed
    fraction above ``STALL_FRACTION`` is contended. An interval longer than ``MAX_INTERVAL_S`` is not counted:
    in ``colgnn bench`` the IPC solver's threads ran in the 2 s before the Predictor's second step.

    The stall counts this process's own threads too: in one ``colgnn bench`` process a later scene ran its kernels
    on 1 thread in 10-18 of 19 steps on a quiet machine (docs/COLLISION_GUARANTEE.md, session 21). So a high stall
    is contention only when another process has a runnable task as well (:func:`other_runnable_tasks`, sampled only
    while the smoothed stall is above half ``STALL_FRACTION``, in ``OTHERS_NEEDED`` of the last ``OTHERS_WINDOW``
    samples). A busy neighbour is in every sample; the process's own parallel workers never are.

    The guard drops to 1 thread at the first contended call, and gives the threads back after ``quiet``
    uncontended calls in a row. One thread costs at most the parallel speed-up (about 10% of a step), while a
    parallel region beside a busy process can cost milliseconds, hundreds of times a step. Results do not depend
    on the count (the kernels write disjoint rows in the serial order).

    Args:
        requested: the thread count asked for (>= 1); with 1 the guard never reads the clock.
        stall: the machine's stall time so far (us), or None if unknown (then the guard trusts the request).
        clock: seconds, monotonic.
        quiet: uncontended calls in a row before ``requested`` threads are used again.
        others: runnable tasks of other processes now, or None if unknown (then the stall alone decides); the
            argument None: the stall alone decides.
    """

    def __init__(self, requested: int, stall: Callable[[], int | None] = cpu_stall_us,
                 clock: Callable[[], float] = time.perf_counter, quiet: int = QUIET_SAMPLES,
                 others: Callable[[], int | None] | None = other_runnable_tasks):
        if requested < 1:
            raise ValueError(f"requested threads must be >= 1, got {requested}")
        self.requested = int(requested)
        self.stall, self.clock, self.quiet, self.others = stall, clock, int(quiet), others
        self._others_seen: list[bool] = []  # per sample while the stall is high: another process's task runnable
        self.calm = self.quiet  # uncontended calls in a row: the request is trusted from the start
        self.reduced_steps = 0  # calls that answered fewer threads than requested
        self.level = 0.0  # the smoothed stall fraction
        self._last: tuple[int, float] | None = None  # (stall us, clock s) at the last call

    def threads(self) -> int:
        """Read the machine's stall time and return the kernels' thread count for the next step."""
        if self.requested == 1:
            return 1
        now = (self.stall(), self.clock())
        last, self._last = self._last, now if now[0] is not None else None
        if last is not None and now[0] is not None and 0 < now[1] - last[1] <= MAX_INTERVAL_S:
            fraction = (now[0] - last[0]) * 1e-6 / (now[1] - last[1])
            self.level += STALL_SMOOTHING * (fraction - self.level)
        others = self._others_busy()  # samples from half the threshold on, so two samples are in at the threshold
        self.calm = 0 if self.level > STALL_FRACTION and others else self.calm + 1
        if self.calm >= self.quiet:
            return self.requested
        self.reduced_steps += 1
        return 1

    def _others_busy(self) -> bool:
        """Another process has had a runnable task in ``OTHERS_NEEDED`` of the last ``OTHERS_WINDOW`` samples (taken
        only while the smoothed stall is above half ``STALL_FRACTION``; forgotten when it falls below)."""
        if self.others is None:
            return True
        if self.level <= 0.5 * STALL_FRACTION:
            self._others_seen.clear()
            return False
        n = self.others()
        self._others_seen.append(n is None or n >= 1)
        del self._others_seen[:-OTHERS_WINDOW]
        return sum(self._others_seen) >= OTHERS_NEEDED
