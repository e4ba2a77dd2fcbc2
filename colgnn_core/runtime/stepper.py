"""One network step and the rollout loop.

The loop (:func:`run_stepper`) is written against a small *stepper* interface (``reset(x0, pose0)``,
``step(pose_next) -> object graph-node positions``, ``mesh(x_graph)``), so the real-time
:class:`~colgnn_core.runtime.predictor.Predictor` (network step + collision-aware correction) replaces
:class:`RawStepper` without touching the loop. The Predictor uses RawStepper's ``propose`` / ``commit`` for the
network step, so there is one implementation of it.

The raw network is integrated as trained (second order, from rest: x_{-1} = x_0). Nothing is clamped unless asked
(``max_displacement`` / ``max_deviation``): then a node moving more than the cap in one step is pulled back along
its step, a node farther than the cap from its rest position is pulled back towards it, and the number of capped
nodes is kept in ``clamped``.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.io import Sequence
from colgnn_core.learn.model import Frame
from colgnn_core.runtime.interior import check_interior_kind, interior_lift
from colgnn_core.runtime.prior_worker import PriorWorker, PriorWorkerError
from colgnn_core.runtime.threads import blas_threads, torch_threads
from colgnn_core.sim.prior import physics_prior
from colgnn_core.sim.tip_prior import TipContact


# Torch threads for the step's small tensor operations (graph features, integration, caps): arrays of a few thousand
# rows, which one thread handles in microseconds. On 2 threads every operation opens an OpenMP region that waits for
# its second worker, and on a shared 2-core machine a parked worker costs milliseconds (one concatenation of the
# banana's node features: 0.02 ms alone, 5-12 ms beside a busy process). The banana's step median at 2 threads, in
# one process alternating the two settings (docs/FIDELITY.md, session 43): quiet 16.7 ms against 16.1 with these
# operations on 2 threads; beside one busy process 14.7 against 19.3; beside a 2-process fit 20.2 against 55.2.
STEP_THREADS = 1
# The physics prior's numpy/scipy BLAS threads (runtime.threads.blas_threads): its products are small, and OpenBLAS's
# spinning workers stall the network's pool (the full banana's modal prior: bench p95 132 -> 27 ms on 1 thread).
PRIOR_BLAS_THREADS = 1


class Stepper(Protocol):
    """What the rollout loop needs from a predictor."""

    template: object

    def reset(self, x0_graph: np.ndarray, pose0: np.ndarray) -> None: ...

    def step(self, pose_next: np.ndarray) -> np.ndarray: ...

    def mesh(self, x_graph: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class StepperState:
    """The network's state at time t, replaced (never changed in place) by each step, so that a copy of the
    reference is a snapshot."""

    x_prev: torch.Tensor  # [N,3] object graph nodes at t-1
    x_t: torch.Tensor     # [N,3] object graph nodes at t
    tool_t: torch.Tensor  # [M,3] tool vertices (world) at t
    pose: np.ndarray      # [7] tool pose at t
    contact: TipContact | None = None  # the physics prior's state at t (tip_prior: the point the tip carries)

    @classmethod
    def at_rest(cls, x0_graph: np.ndarray, pose0: np.ndarray, tool) -> "StepperState":
        """The state at rest velocity (x_{-1} = x_0) with the tool at ``pose0``."""
        x_t = torch.from_numpy(np.array(x0_graph, dtype=np.float64))
        pose = np.asarray(pose0, dtype=np.float64)
        return cls(x_t.clone(), x_t, torch.from_numpy(tool.world_vertices(pose)), pose)

    def advanced(self, x_next: torch.Tensor, tool_next: torch.Tensor, pose_next: np.ndarray,
                 contact: TipContact | None) -> "StepperState":
        """The state at t+1 with object graph nodes ``x_next`` (raw or corrected) and the tip's ``contact``."""
        return StepperState(self.x_t, x_next, tool_next, pose_next, contact)


class RawStepper:
    """The network alone: x_{t+1} = model(x_t, x_{t-1}, tool at t and t+1), optionally displacement-capped.

    prior_beside: a model that adds a physics prior without seeing it (``prior_input`` false) solves it in a
    process of its own while the network runs (runtime.prior_worker); False solves it here, before the network
    (the same output; for machines with one core)."""

    def __init__(self, model, scene, max_displacement: float | None = None, max_deviation: float | None = None,
                 rest_mesh: np.ndarray | None = None, interior: str = "elastic", prior_beside: bool = True):
        for name, v in (("max_displacement", max_displacement), ("max_deviation", max_deviation)):
            if v is not None and not v > 0:
                raise InputError(f"{name} must be > 0 (m), got {v}")
        self.model = model
        self.scene = scene
        self.template = model.template
        self.max_displacement = max_displacement
        self.max_deviation = max_deviation
        # The rest shape [N_mesh,3] that the deviation cap, the lifting of interior vertices and the Predictor's rest
        # relaxation refer to: default the mesh file's; the runtime passes the settled rest the ground truth starts
        # from. ``rest`` [N,3] is its graph nodes.
        self.rest_mesh = np.asarray(self.template.mesh_rest_vertices if rest_mesh is None else rest_mesh,
                                    dtype=np.float64).copy()
        self.rest = torch.from_numpy(self.rest_mesh[self.template.object_nodes])
        # How the mesh's interior vertices follow the graph nodes (runtime.interior).
        self.interior = check_interior_kind(interior)
        self._lift = None          # built on first use (the elastic one factorises a matrix: seconds at full)
        # A model's physics prior: built here, not on the first step (it factorises the stiffness: 1.3 s at full
        # cone_bunny, which would otherwise stall the first published step).
        # A network whose nodes do not see its prior (prior_input false) gets it from a process of its own, solved
        # while the network runs (runtime.prior_worker), unless ``prior_beside`` is false.
        config = getattr(model, "config", None)
        kind = getattr(config, "prior_kind", None)
        self._prior_args = (kind, scene, self.rest_mesh, self.template.object_nodes,
                            getattr(config, "prior_mesh", ""), getattr(config, "prior_compliance", ""),
                            getattr(config, "prior_options", {}))
        beside = (kind is not None and prior_beside and not getattr(config, "prior_input", True)
                  and hasattr(model, "build_graph") and hasattr(model, "network"))
        self._prior_worker = PriorWorker(*self._prior_args) if beside else None
        self._physics = self._local_prior() if kind and not beside else None
        self.prior_failure: str | None = None  # why the prior's process was given up (then it runs here)
        self._contact_next: TipContact | None = None  # the prior's state after the last proposal, kept by commit
        self.clamped = 0  # nodes capped in the last step
        # torch threads while the network runs (None: the process's count); the Predictor times it at warm-up
        self.network_threads: int | None = None
        self.step_threads: int | None = STEP_THREADS  # ... and around it (None: the process's count)
        self.state: StepperState | None = None

    def reset(self, x0_graph: np.ndarray, pose0: np.ndarray) -> None:
        self.state = StepperState.at_rest(x0_graph, pose0, self.scene.tool)
        self._contact_next = None

    @torch.no_grad()
    def propose(self, pose_next: np.ndarray, tool_next: torch.Tensor) -> torch.Tensor:
        """x_{t+1} [N,3] from the network (capped if asked) without advancing the state.

        Sets ``self.clamped``, ``self.last_ms`` ({'graph', 'gnn'} wall times of this call; with the prior beside the
        network, 'gnn' includes the wait for it) and
        ``self.world_edges`` (world edges of the graph; None for models without one).
        """
        t0 = time.perf_counter()
        s = self.state
        outer = torch.get_num_threads()
        with torch_threads(self.step_threads):
            beside = self._submit_prior(pose_next)
            frame = Frame(s.x_prev, s.x_t, s.tool_t, tool_next, pose_next, None if beside else self._prior(pose_next))
            if hasattr(self.model, "build_graph") and hasattr(self.model, "network"):
                try:
                    graph = self.model.build_graph(frame)
                    self.world_edges = int(graph.world.senders.shape[0])
                    t1 = time.perf_counter()
                    pred_norm, _ = self.network(graph, outer)
                finally:
                    prior = self._prior_result(pose_next) if beside else frame.prior  # never left in flight
                x_next = self.model.integrate(pred_norm, frame.x_t, frame.x_prev, prior)
            else:  # models without the graph pieces (the subspace baseline)
                self.world_edges = None
                t1 = t0
                x_next = self.model.predict(frame)
            t2 = time.perf_counter()
            self.last_ms = {"graph": 1e3 * (t1 - t0), "gnn": 1e3 * (t2 - t1)}
            return self._capped(x_next)

    def network(self, graph, threads: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's network on ``graph`` (``Simulator.network``), on ``network_threads`` torch threads where
        that is set, else on ``threads`` (None: the current count); the count is restored after."""
        with torch_threads(self.network_threads or threads):
            return self.model.network(graph)

    def _submit_prior(self, pose_next: np.ndarray) -> bool:
        """Start the prior at ``pose_next`` in its process; False when there is none (or it just failed)."""
        if self._prior_worker is None:
            return False
        try:
            self._prior_worker.submit(self.state.contact, self.state.pose, pose_next)
        except PriorWorkerError as exc:
            self._give_up_worker(exc)
            return False
        return True

    def _prior_result(self, pose_next: np.ndarray) -> torch.Tensor:
        """The submitted prior's displacement [N,3]; solved here if its process failed meanwhile."""
        try:
            self._contact_next, u = self._prior_worker.result()
        except PriorWorkerError as exc:
            self._give_up_worker(exc)
            return self._prior(pose_next)
        return torch.from_numpy(u)

    def _give_up_worker(self, exc: PriorWorkerError) -> None:
        """Solve the prior in this process from now on (the model's output stays the same, only slower)."""
        self.prior_failure = str(exc)
        warnings.warn(f"{exc}; solving the physics prior in this process from now on", RuntimeWarning, stacklevel=3)
        self._prior_worker.close()
        self._prior_worker = None
        self._physics = self._local_prior()

    def _local_prior(self):
        """The model's physics prior in this process (factorises the stiffness: seconds at full resolution)."""
        kind, scene, rest_mesh, nodes, mesh, compliance, options = self._prior_args
        return physics_prior(kind, scene, rest_mesh, nodes, mesh=mesh, compliance=compliance, options=options)

    @property
    def prior_worker(self) -> PriorWorker | None:
        """The process that solves the physics prior beside the network (None: none, or it was given up)."""
        return self._prior_worker

    @property
    def prior_beside(self) -> bool:
        """True while the physics prior runs in a process of its own, beside the network (it then holds a core)."""
        return self._prior_worker is not None

    def close(self) -> None:
        """Stop the prior's process, if any (it also stops with this process)."""
        if self._prior_worker is not None:
            self._prior_worker.close()

    def _prior(self, pose_next: np.ndarray) -> torch.Tensor | None:
        """The physics prior's displacement [N,3] at ``pose_next`` for a model with one (else None); the prior's
        state is kept for :meth:`commit`."""
        if self._physics is None:
            return None
        with blas_threads(PRIOR_BLAS_THREADS):
            self._contact_next, u = self._physics.step(self.state.contact, self.state.pose, pose_next)
        return torch.from_numpy(u)

    def _capped(self, x_next: torch.Tensor) -> torch.Tensor:
        """``x_next`` with the displacement and deviation caps applied; sets ``self.clamped``."""
        x_t = self.state.x_t
        self.clamped = 0
        if self.max_displacement is not None:
            d = x_next - x_t
            n = torch.linalg.vector_norm(d, dim=1, keepdim=True)
            over = n > self.max_displacement
            self.clamped = int(over.sum())
            if self.clamped:
                x_next = torch.where(over, x_t + d * (self.max_displacement / n), x_next)
        if self.max_deviation is not None:
            d = x_next - self.rest
            n = torch.linalg.vector_norm(d, dim=1, keepdim=True)
            over = n > self.max_deviation
            if bool(over.any()):
                self.clamped += int(over.sum())
                x_next = torch.where(over, self.rest + d * (self.max_deviation / n), x_next)
        return x_next

    def commit(self, x_next: torch.Tensor, tool_next: torch.Tensor, pose_next: np.ndarray) -> None:
        """Advance the state to t+1 with positions ``x_next`` (raw or corrected)."""
        self.state = self.state.advanced(x_next, tool_next, pose_next, self._contact_next)

    @torch.no_grad()
    def step(self, pose_next: np.ndarray) -> np.ndarray:
        pose_next = np.asarray(pose_next, dtype=np.float64)
        tool_next = torch.from_numpy(self.scene.tool.world_vertices(pose_next))
        x_next = self.propose(pose_next, tool_next)
        self.commit(x_next, tool_next, pose_next)
        return x_next.numpy()

    def mesh(self, x_graph: np.ndarray) -> np.ndarray:
        """Every mesh vertex [N_mesh,3] from the graph nodes [N,3] (:func:`colgnn_core.runtime.interior.interior_lift`
        of ``self.interior``; interior vertices within ``max_deviation`` of the rest, like the nodes)."""
        if self._lift is None:
            self._lift = interior_lift(self.interior, self.scene, self.template, self.rest_mesh)
        mesh = self._lift(x_graph)
        ids = self.template.interior_ids
        if self.max_deviation is not None and ids is not None and self.interior == "elastic":
            # The nodes are capped already, and so is any interpolation of them; the elastic extension of a wild
            # surface can overshoot the cap inside.
            d = mesh[ids] - self.rest_mesh[ids]
            n = np.linalg.norm(d, axis=1, keepdims=True)
            over = n[:, 0] > self.max_deviation
            if over.any():
                mesh[ids[over]] = self.rest_mesh[ids[over]] + d[over] * (self.max_deviation / n[over])
        return mesh


def run_stepper(stepper: Stepper, scene, poses: np.ndarray, initial_positions: np.ndarray | None = None,
                progress: bool = False) -> Sequence:
    """The rollout loop for any stepper (the raw network or the Predictor): a contract Sequence with
    ``extra['step_ms']`` [T] (model step wall time in ms, 0 for frame 0) and ``extra['clamped_nodes']`` [T]."""
    tpl = stepper.template
    n_mesh = scene.object.vertices.shape[0]
    x0 = np.asarray(scene.object.vertices if initial_positions is None else initial_positions, dtype=np.float64)
    if x0.shape != (n_mesh, 3):
        raise InputError(f"initial_positions must be [{n_mesh},3], got {x0.shape}")
    T = len(poses)
    obj = np.empty((T, n_mesh, 3))
    tool = np.empty((T, scene.tool.vertices.shape[0], 3))
    step_ms = np.zeros(T)
    clamped = np.zeros(T, dtype=np.int64)
    obj[0] = x0
    tool[0] = scene.tool.world_vertices(poses[0])
    stepper.reset(x0[tpl.object_nodes], poses[0])
    frames = range(1, T)
    if progress:
        from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

        frames = tqdm(frames, desc="rollout", unit="step")
    for k in frames:
        t0 = time.perf_counter()
        x_graph = stepper.step(poses[k])
        step_ms[k] = 1e3 * (time.perf_counter() - t0)
        clamped[k] = getattr(stepper, "clamped", 0)
        obj[k] = stepper.mesh(x_graph)
        tool[k] = scene.tool.world_vertices(poses[k])
    return Sequence(object_positions=obj, object_faces=np.asarray(scene.object.faces, dtype=np.int64),
                    tool_positions=tool, tool_faces=np.asarray(scene.tool.faces, dtype=np.int64),
                    tool_poses=poses, dt=float(scene.dt),
                    extra={"step_ms": step_ms, "clamped_nodes": clamped})
