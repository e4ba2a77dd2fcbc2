"""``colgnn rollout``: drive a trained model with a tool trajectory and record the predicted sequence.

The loop is written against a small *stepper* interface (``reset(x0)``,
``step(pose_next) -> object graph-node positions``) so the real-time
``Predictor`` (GNN step + collision-aware correction) replaces
:class:`RawStepper` without touching the loop: ``correction=True`` rolls out
through :class:`colgnn_core.predictor.Predictor` (which uses RawStepper's
``propose``/``commit`` for the network step, so there is one implementation of it).

The raw network is integrated as trained (second order, from rest: x_{-1} = x_0).
Nothing is clamped unless asked (``limits='data'`` or explicit ``max_displacement`` /
``max_deviation``): then a node moving more than the cap in one step is pulled back
along its step, a node farther than the cap from its rest position is pulled back
towards it, and the number of capped nodes per frame is recorded in
``extra['clamped_nodes']``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.io import Sequence
from colgnn_core.learn.checkpoint import LoadedCheckpoint, load_checkpoint
from colgnn_core.learn.graph import lift_to_mesh
from colgnn_core.learn.model import Frame

MODEL_DIR = Path(__file__).resolve().parent / "assets" / "models"
DATA_STEP_FACTOR = 2.0       # limits='data': per-step cap = 2 x the largest per-frame displacement in training
DATA_DEVIATION_FACTOR = 1.5  # ... and distance-from-rest cap = 1.5 x the largest one in training


class Stepper(Protocol):
    """What the rollout loop needs from a predictor."""

    template: object

    def reset(self, x0_graph: np.ndarray, pose0: np.ndarray) -> None: ...

    def step(self, pose_next: np.ndarray) -> np.ndarray: ...

    def mesh(self, x_graph: np.ndarray) -> np.ndarray: ...


def shipped_checkpoint(scene_name: str) -> Path:
    """Path of the shipped model for a scene (InputError if there is none)."""
    from colgnn_core.scenes import scene_names

    if scene_name not in scene_names():
        raise InputError(f"unknown scene {scene_name!r}; valid scenes: {', '.join(scene_names())}")
    path = MODEL_DIR / f"{scene_name}.pt"
    if not path.is_file():
        raise InputError(f"no shipped model for scene {scene_name!r} ({path}); pass a checkpoint")
    return path


def output_limits(loaded: LoadedCheckpoint, limits: str, max_displacement: float | None = None,
                  max_deviation: float | None = None) -> tuple[float | None, float | None]:
    """(max displacement per step, max distance from rest) caps in m for the network's output.

    ``limits``: 'none' (only the explicit values) or 'data': ``DATA_STEP_FACTOR`` x the largest per-frame node
    displacement and ``DATA_DEVIATION_FACTOR`` x the largest node distance from rest in the checkpoint's training
    data, where no explicit value is given.
    """
    if limits not in ("none", "data"):
        raise InputError(f"limits must be 'none' or 'data', got {limits!r}")
    if limits == "data":
        stats = (loaded.extra or {}).get("data_stats")
        if not stats:
            raise InputError("this checkpoint records no training-data statistics; pass explicit limits")
        if max_displacement is None:
            max_displacement = DATA_STEP_FACTOR * float(stats["max"])
        if max_deviation is None:
            max_deviation = DATA_DEVIATION_FACTOR * float(stats["max_deviation"])
    return max_displacement, max_deviation


def load_model(checkpoint_or_scene, scene=None) -> LoadedCheckpoint:
    """A loaded checkpoint from a LoadedCheckpoint, a checkpoint path, or a scene name (its shipped model)."""
    if isinstance(checkpoint_or_scene, LoadedCheckpoint):
        return checkpoint_or_scene
    if isinstance(checkpoint_or_scene, (str, os.PathLike)):
        text = str(checkpoint_or_scene)
        from colgnn_core.scenes import scene_names

        if text in scene_names() and not Path(text).exists():
            return load_checkpoint(shipped_checkpoint(text), scene)
        return load_checkpoint(text, scene)
    raise InputError(f"expected a checkpoint path or a scene name, got {type(checkpoint_or_scene).__name__}")


class RawStepper:
    """The network alone: x_{t+1} = model(x_t, x_{t-1}, tool at t and t+1), optionally displacement-capped."""

    def __init__(self, model, scene, max_displacement: float | None = None, max_deviation: float | None = None):
        for name, v in (("max_displacement", max_displacement), ("max_deviation", max_deviation)):
            if v is not None and not v > 0:
                raise InputError(f"{name} must be > 0 (m), got {v}")
        self.model = model
        self.scene = scene
        self.template = model.template
        self.max_displacement = max_displacement
        self.max_deviation = max_deviation
        self.rest = self.template.rest.clone()
        self.clamped = 0  # nodes capped in the last step

    def reset(self, x0_graph: np.ndarray, pose0: np.ndarray) -> None:
        self.x_t = torch.from_numpy(np.array(x0_graph, dtype=np.float64))
        self.x_prev = self.x_t.clone()
        self.pose = np.asarray(pose0, dtype=np.float64)
        self.tool_t = torch.from_numpy(self.scene.tool.world_vertices(self.pose))

    @torch.no_grad()
    def propose(self, pose_next: np.ndarray, tool_next: torch.Tensor) -> torch.Tensor:
        """x_{t+1} [N,3] from the network (capped if asked) without advancing the state.

        Sets ``self.clamped``, ``self.last_ms`` ({'graph', 'gnn'} wall times of this call) and
        ``self.world_edges`` (world edges of the graph; None for models without one).
        """
        t0 = time.perf_counter()
        frame = Frame(self.x_prev, self.x_t, self.tool_t, tool_next, pose_next)
        if hasattr(self.model, "build_graph") and hasattr(self.model, "network"):
            graph = self.model.build_graph(frame)
            self.world_edges = int(graph.world.senders.shape[0])
            t1 = time.perf_counter()
            pred_norm, _ = self.model.network(graph)
            x_next = self.model.integrate(pred_norm, frame.x_t, frame.x_prev)
        else:  # models without the graph pieces (the subspace baseline)
            self.world_edges = None
            t1 = t0
            x_next = self.model.predict(frame)
        t2 = time.perf_counter()
        self.last_ms = {"graph": 1e3 * (t1 - t0), "gnn": 1e3 * (t2 - t1)}
        self.clamped = 0
        if self.max_displacement is not None:
            d = x_next - self.x_t
            n = torch.linalg.vector_norm(d, dim=1, keepdim=True)
            over = n > self.max_displacement
            self.clamped = int(over.sum())
            if self.clamped:
                x_next = torch.where(over, self.x_t + d * (self.max_displacement / n), x_next)
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
        self.x_prev, self.x_t, self.tool_t, self.pose = self.x_t, x_next, tool_next, pose_next

    @torch.no_grad()
    def step(self, pose_next: np.ndarray) -> np.ndarray:
        pose_next = np.asarray(pose_next, dtype=np.float64)
        tool_next = torch.from_numpy(self.scene.tool.world_vertices(pose_next))
        x_next = self.propose(pose_next, tool_next)
        self.commit(x_next, tool_next, pose_next)
        return x_next.numpy()

    def mesh(self, x_graph: np.ndarray) -> np.ndarray:
        """Every mesh vertex [N_mesh,3] from the graph nodes [N,3] (:func:`lift_to_mesh`)."""
        return lift_to_mesh(self.template, x_graph)


def rollout(checkpoint_or_scene, poses: np.ndarray, correction: bool = False, *, scene=None,
            initial_positions: np.ndarray | None = None, limits: str = "none", max_displacement: float | None = None,
            max_deviation: float | None = None, progress: bool = False,
            predictor_options: dict | None = None) -> Sequence:
    """Roll a model out over a tool trajectory.

    Args:
        checkpoint_or_scene: checkpoint path, :class:`LoadedCheckpoint`, or scene name (its shipped model).
        poses: [T,7] tool poses, one per model step, frame 0 = the initial state (checked against the
            scene workspace: InputError naming the row).
        correction: collision-aware correction: the rollout goes through :class:`colgnn_core.predictor.Predictor`
            (large pose jumps subdivided; per-frame counts and stage timings added to ``extra``).
        scene: the Scene (default: the one the checkpoint names, at its resolution).
        initial_positions: [N_mesh,3] object vertices at frame 0 (default: the scene's rest mesh).
        limits: 'none' (the raw network, nothing capped) or 'data': caps derived from the training data the
            checkpoint records: ``DATA_STEP_FACTOR`` x the largest per-frame node displacement and
            ``DATA_DEVIATION_FACTOR`` x the largest node distance from rest.
        max_displacement: explicit cap (m) on any node's displacement per step (overrides ``limits``).
        max_deviation: explicit cap (m) on any node's distance from its rest position (overrides ``limits``).
            Capped node counts per frame go to ``extra['clamped_nodes']``.
        progress: tqdm bar.
        predictor_options: keyword arguments for the Predictor (correction=True only), e.g. max_substeps.

    Returns:
        A contract :class:`Sequence` with every mesh vertex (interior ones interpolated when the model is
        surface-only), the tool's surface vertices per frame, ``extra['step_ms']`` [T] (model step wall
        time in ms, 0 for frame 0) and ``extra['clamped_nodes']`` [T].
    """
    loaded = load_model(checkpoint_or_scene, scene)
    if scene is None:
        from colgnn_core.scenes import load_scene

        scene = load_scene(loaded.meta.scene, loaded.meta.resolution)
    poses = scene.check_poses(np.asarray(poses, dtype=np.float64))
    if poses is None or len(poses) < 1:
        raise InputError("poses must have at least one row (frame 0)")
    max_displacement, max_deviation = output_limits(loaded, limits, max_displacement, max_deviation)
    if correction:
        from colgnn_core.predictor import Predictor

        stepper = Predictor(loaded, scene, correction=True, threads=None, max_displacement=max_displacement,
                            max_deviation=max_deviation, **(predictor_options or {})).stepper()
        seq = run_stepper(stepper, scene, poses, initial_positions, progress)
        seq.extra.update(stepper.extra())
        return seq
    stepper = RawStepper(loaded.simulator, scene, max_displacement, max_deviation)
    return run_stepper(stepper, scene, poses, initial_positions, progress)


def run_stepper(stepper: Stepper, scene, poses: np.ndarray, initial_positions: np.ndarray | None = None,
                progress: bool = False) -> Sequence:
    """The rollout loop for any stepper (raw network now, the Predictor later)."""
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
        from tqdm import tqdm

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
