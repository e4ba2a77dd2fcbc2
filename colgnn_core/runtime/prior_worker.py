"""A physics prior solved in a process of its own, so that the network step runs beside it rather than after it.

Why a process: a model whose nodes do not see its prior (``ModelConfig.prior_input`` false) only adds the prior to
its output, so the prior and the network need not wait for each other. In one process they still would: the
prior's back-substitution (cholespy) holds the GIL (80 solves take 0.20 s on one thread and on two), and its
active-set rounds are many small numpy calls that hold it too. On the full banana the modal contact prior takes
9-10 ms of a 26 ms step in contact (docs/FIDELITY.md, session 45); beside the network it hides behind the graph and
the network's ~10 ms.

Protocol (one request in flight): :meth:`PriorWorker.submit` sends ``(state, pose_prev, pose)``, and
:meth:`PriorWorker.result` returns the prior's ``(state, displacement [N,3] m)``, exactly what ``prior.step`` returns
in the parent (the same code, the same factorisation, the same float64 arithmetic). The child is started with
``spawn`` (a fork of a process that runs DDS or torch threads is unsafe), limits its BLAS and numba pools to one
thread (it owns one core while the network holds the other), and exits when the parent closes the pipe or dies.

A worker that fails (it died, or raised) raises :class:`PriorWorkerError`; the stepper then solves the prior in
its own process for the rest of its life (runtime.stepper.RawStepper).
"""

from __future__ import annotations

import multiprocessing as mp
import weakref
from multiprocessing.connection import Connection

import numpy as np

__all__ = ["READY_TIMEOUT_S", "PriorWorker", "PriorWorkerError"]

READY_TIMEOUT_S = 300.0  # the child imports, factorises the stiffness and loads (or builds) the modal cache: seconds
                         # with the cache, about a minute on the full banana without it


class PriorWorkerError(RuntimeError):
    """The prior's process failed: it died, it did not start, or the prior raised there (the message says which)."""


class PriorWorker:
    """``sim.prior.physics_prior(kind, scene, rest_mesh, nodes, mesh, compliance, options)`` in a child process.

    rest_mesh: [N_mesh,3] settled rest (m); nodes: [N] graph-node mesh ids. Returns once the child has started;
    the child builds its prior meanwhile (seconds: imports, the stiffness's factorisation), beside whatever the
    caller does next (the Predictor compiles its network), and the first :meth:`submit` waits for it (its errors,
    such as a failed factorisation, are raised there as :class:`PriorWorkerError`)."""

    def __init__(self, kind: str, scene, rest_mesh: np.ndarray, nodes: np.ndarray, mesh: str = "",
                 compliance: str = "", options: dict | None = None):
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=serve, name=f"colgnn-prior-{kind}", daemon=True,
                                    args=(child, kind, scene, np.asarray(rest_mesh), np.asarray(nodes), mesh,
                                          compliance, dict(options or {})))
        self._process.start()
        child.close()
        self._pending = False
        self._ready = False
        self._finalizer = weakref.finalize(self, _shut, self._conn, self._process)

    def wait_ready(self) -> None:
        """Wait until the child has built its prior (at most READY_TIMEOUT_S)."""
        if self._ready:
            return
        if not self._conn.poll(READY_TIMEOUT_S):
            self.close()
            raise PriorWorkerError(f"the prior's process did not start within {READY_TIMEOUT_S:.0f} s")
        self._receive()
        self._ready = True

    @property
    def alive(self) -> bool:
        return self._process.is_alive()

    @property
    def pid(self) -> int | None:
        """The child's process id."""
        return self._process.pid

    def submit(self, state, pose_prev: np.ndarray, pose: np.ndarray) -> None:
        """Start ``prior.step(state, pose_prev, pose)`` in the child (poses [7]: position, quaternion xyzw)."""
        if self._pending:
            raise PriorWorkerError("a prior request is already in flight: take its result first")
        self.wait_ready()
        try:
            self._conn.send((state, np.asarray(pose_prev, dtype=np.float64), np.asarray(pose, dtype=np.float64)))
        except (OSError, EOFError, BrokenPipeError) as exc:
            raise PriorWorkerError(f"the prior's process is gone ({exc})") from exc
        self._pending = True

    def result(self) -> tuple[object, np.ndarray]:
        """The submitted request's ``(state, displacement [N,3] m)``; waits for it."""
        if not self._pending:
            raise PriorWorkerError("no prior request in flight")
        self._pending = False
        return self._receive()

    def _receive(self):
        try:
            status, payload = self._conn.recv()
        except (OSError, EOFError) as exc:
            code = self._process.exitcode
            raise PriorWorkerError("the prior's process died" + (f" (exit code {code})" if code is not None else "")
                                   ) from exc
        if status != "ok":
            raise PriorWorkerError(f"the prior failed in its process: {payload}")
        return payload

    def close(self) -> None:
        """Stop the child (idempotent)."""
        self._finalizer()


def _shut(conn: Connection, process) -> None:
    try:
        conn.send(None)
    except (OSError, EOFError, BrokenPipeError):
        pass
    conn.close()
    process.join(timeout=2.0)
    if process.is_alive():
        process.kill()
        process.join(timeout=2.0)


def serve(conn: Connection, kind: str, scene, rest_mesh: np.ndarray, nodes: np.ndarray, mesh: str,
          compliance: str, options: dict | None = None) -> None:
    """The child's loop: build the prior, answer ``(state, pose_prev, pose)`` with ``("ok", (state, u))`` or
    ``("error", message)``, stop at ``None`` or when the parent's end closes."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)  # one core for the prior: the network holds the other
    try:
        import numba

        numba.set_num_threads(1)
        from colgnn_core.sim.prior import physics_prior

        prior = physics_prior(kind, scene, rest_mesh, nodes, mesh=mesh, compliance=compliance, options=options)
    except Exception as exc:  # noqa: BLE001 (any failure goes back to the parent as a message)
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ok", None))
    while True:
        try:
            request = conn.recv()
        except (OSError, EOFError):
            return
        if request is None:
            return
        state, pose_prev, pose = request
        try:
            conn.send(("ok", prior.step(state, pose_prev, pose)))
        except Exception as exc:  # noqa: BLE001
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
