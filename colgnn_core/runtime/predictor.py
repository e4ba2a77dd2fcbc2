"""The real-time predictor: one GNN step + collision-aware correction per tool pose.

``Predictor`` is the one stepping API behind ``colgnn rollout`` (with correction),
``colgnn bench`` and the ROS node::

    pred = Predictor.from_checkpoint("cone_bunny")          # or a checkpoint path
    pred.reset()
    res = pred.step(tool_pose)                               # [px,py,pz,qx,qy,qz,qw]
    res.positions, res.surface_faces, res.collision_counts(), res.timings_ms

Each call validates the pose (NaN/inf, quaternion norm, workspace: InputError with
the state unchanged), splits a jump larger than the training distribution's per-step
tool motion into several model steps (``interpolate_poses``; more than
``max_substeps`` is refused, state unchanged), runs the network on each sub-pose,
corrects its output with :class:`~colgnn_core.collision.correction.CollisionCorrector`
and feeds the *corrected* positions to the next step.

The guarantee is stated for what is published: over the straight motion from the last published state
to the new one (every vertex linear, the tool's vertices too), every object-surface/tool primitive pair
stays farther apart than min(0.18 mm, 0.5 x its distance at the start), so ipctk's
``is_step_collision_free`` (Tight-Inclusion, default line-search clearance) finds no collision in it and
the new frame does not intersect the tool. A single model step is corrected for exactly that motion. A jump
split into model steps is corrected per model step for contact only (nobody sees those motions), and then
once more as a whole: the straight motion from the last published state to the last model step's result
goes through the same correction, clearance included, and its output is the new state.

The correction works on the object graph nodes' surface (surface-only models: all
graph nodes; full-mesh models: the surface subset); interior mesh vertices are
lifted from the corrected nodes (``interior``: the elastic extension by default, the free interpolation in the
node; :mod:`colgnn_core.runtime.interior`), so the published mesh is the corrected one.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
from collections.abc import Sequence
import time
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np
import torch
from scipy.spatial import cKDTree

from colgnn_core.collision.correction import (DEFAULT_MAX_ITERATIONS, MAX_ROTATION, PROJECT_RULES, PUSH_RULES,
                                              CollisionCorrector)
from colgnn_core.collision.kernels import use_kernel_threads
from colgnn_core.collision.self_contact import SelfContact
from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import interpolate_poses, pose_path
from colgnn_core.learn.core_model import EdgeSet
from colgnn_core.learn.model import Frame
from colgnn_core.runtime.models import model_and_scene, output_limits, settled_rest
from colgnn_core.runtime.stepper import RawStepper
from colgnn_core.runtime.threads import ContentionGuard, auto_threads, fastest_thread_count
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.hard_cases import press_pose
from colgnn_core.scenes.scene import at_resolution
from colgnn_core.scenes.trajectories import sample_poses, split_seeds

__all__ = ["Predictor", "PredictorState", "StepResult", "correction_iterations", "correction_table",
           "self_contact_default", "tool_step_limits", "DEFAULT_MAX_SUBSTEPS", "RECOMMENDED_REST_RELAXATION"]

DEFAULT_MAX_SUBSTEPS = 16
WARM_UP_DEPTH = 0.3  # Predictor.warm_up: a fraction of the way from the surface to the deepest valid pose
RECOMMENDED_REST_RELAXATION = 0.05  # the ROS node's default (deviation decays as 0.975^steps once the tool is away)
# After this many consecutive released model steps (see Predictor._released) the relaxation rate ramps linearly from
# ``rest_relaxation`` to 1 over SETTLE_RAMP_STEPS more: a released elastic object is at rest a few seconds later,
# whatever the network's own (distribution-shifted) dynamics would do there.
SETTLE_AFTER_STEPS = 50
SETTLE_RAMP_STEPS = 100
EASE_PEAK = 1.5            # trajectories.py eases every move with a smoothstep: peak speed 1.5x the mean
MIN_ROTATION_STEP = math.radians(2.0)  # floor of the per-step rotation limit (families without tilt)
TRIM_EVERY = 200           # model steps between returns of freed heap memory to the OS (see _release_memory)
# The domain check (Predictor.outside_domain): a model step is outside the training domain when the tool is within the
# network's reach (world edges) yet farther than DOMAIN_RADIUS_FACTOR x r_W from every training tool position, or
# when the object is farther from its settled rest than DOMAIN_DEVIATION_FACTOR x the training data's largest
# deviation. The output is still published (and corrected): the flag tells the user not to trust its shape.
DOMAIN_RADIUS_FACTOR = 2.0
DOMAIN_DEVIATION_FACTOR = 1.25
# How the interior vertices follow the surface where only the surface is used (the node publishes the surface; the
# speed benchmarks time the node's configuration): the free interpolation, not the elastic solve (runtime.interior).
REALTIME_INTERIOR = "interpolated"
COUNT_LABELS = ("vertex_face_before", "edge_edge_before", "vertex_face_after", "edge_edge_after",
                "penetrating_vertices_after", "correction_iterations", "fallback", "substeps",
                "self_pairs_before", "self_pairs_after", "invalid_faces_before", "invalid_faces_after",
                "self_fallback")


@dataclass
class StepResult:
    """One published state.

    positions: [N_mesh,3] every object mesh vertex (m); surface_faces [F,3] (mesh ids) and
    surface_vertex_ids [S] are the scene's constant arrays (shared, do not modify);
    tool_vertices [M,3] world, tool_faces [G,3]; tool_pose [7] the (normalised) pose used.
    Counts are summed over the substeps (``*_before``: crossings in the raw network output;
    ``*_after``: crossings the fast check finds after correction); ``interior_cleared``: interior mesh vertices
    the lifting had put inside the tool, moved out (published state only); ``published_moved``: with substeps,
    surface vertices the correction of the whole published step moved (module docstring).
    Self-contact stage (:mod:`colgnn_core.collision.self_contact`, on the published step): ``self_pairs_before`` /
    ``invalid_faces_before``: object self pairs closer than the self clearance during the step and flipped, collapsed
    or torn triangles after the tool pass; ``*_after``: what is left after the stage (0 but for rotated triangles of
    its fallback); ``self_fallback``: its certified fallback was used; ``self_moved``: vertices it moved.
    timings_ms: graph, gnn, correction (the tool pass), self_contact (the self stage, its repeated tool passes
    included), total (ms, summed over substeps).
    """

    positions: np.ndarray
    surface_faces: np.ndarray
    surface_vertex_ids: np.ndarray
    tool_vertices: np.ndarray
    tool_faces: np.ndarray
    tool_pose: np.ndarray
    vertex_face_before: int = 0
    edge_edge_before: int = 0
    vertex_face_after: int = 0
    edge_edge_after: int = 0
    penetrating_vertices_after: int = 0
    interior_cleared: int = 0
    correction_iterations: int = 0
    fallback: bool = False
    substeps: int = 1
    published_moved: int = 0
    out_of_domain: int = 0     # model steps of this call outside the training domain (Predictor.outside_domain)
    self_pairs_before: int = 0
    self_pairs_after: int = 0
    invalid_faces_before: int = 0
    invalid_faces_after: int = 0
    self_fallback: bool = False
    self_moved: int = 0
    kernel_threads: int = 1    # the collision kernels' threads in this call (fewer than asked while the cores are busy)
    timings_ms: dict = field(default_factory=dict)

    @property
    def surface_vertices(self) -> np.ndarray:
        """[S,3] positions of the surface vertices (a gather; faces index ``positions``)."""
        return self.positions[self.surface_vertex_ids]

    def collision_counts(self) -> dict[str, int]:
        """The ``collision_counts`` topic fields (msg_tools.conversions.COLLISION_COUNT_LABELS order)."""
        return {k: int(getattr(self, k)) for k in COUNT_LABELS}


@dataclass(frozen=True)
class PredictorState:
    """What the Predictor publishes and counts besides the network's state (``Predictor.net.state``). Both are
    replaced, never changed in place, by each model step: a failed ``step`` restores them by reference."""

    mesh: np.ndarray           # [N_mesh,3] the published object positions
    tool_vertices: np.ndarray  # [M,3] the tool at the current pose (world)
    steps: int = 0             # model steps since reset
    fallbacks: int = 0         # steps whose correction used the fallback since reset
    self_fallbacks: int = 0    # published steps whose self-contact stage used its fallback since reset
    relaxed_steps: int = 0     # model steps relaxed towards rest since reset
    free_steps: int = 0        # consecutive released model steps (the settle ramp's clock; see Predictor._released)
    out_of_domain: int = 0     # model steps outside the training domain since reset


@lru_cache(maxsize=None)
def _family_limits(scene_name: str, resolution: str, seeds: int = 3, frames: int = 160) -> tuple[float, float]:
    scene = load_scene(scene_name, resolution)
    fam = scene.family
    trans = EASE_PEAK * float(np.max(fam["speed"])) * float(np.max(fam.get("retract_speed_factor", 1.0)))
    rot = 0.0
    for seed in split_seeds("train", seeds):
        P = sample_poses(scene, seed, frames)
        trans = max(trans, float(np.linalg.norm(np.diff(P[:, :3], axis=0), axis=1).max()))
        dots = np.clip(np.abs((P[1:, 3:] * P[:-1, 3:]).sum(1)), 0.0, 1.0)
        rot = max(rot, float((2.0 * np.arccos(dots)).max()))
    return trans, max(rot, MIN_ROTATION_STEP)


def correction_iterations(scene) -> int:
    """Correction passes before the fallback for ``scene``: its TOML's ``[correction] max_iterations``, else
    DEFAULT_MAX_ITERATIONS (a ``[correction.<resolution>]`` table overrides it at that resolution). InputError when
    the value is not an integer >= 0."""
    value = correction_table(scene).get("max_iterations", DEFAULT_MAX_ITERATIONS)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise InputError(f"{scene.name}: correction.max_iterations must be an integer >= 0, got {value!r}")
    return value


def correction_push_rule(scene) -> str:
    """How the tool pass merges several pushes on one vertex for ``scene``: its TOML's ``[correction] push_rule``
    (or ``[correction.<resolution>]``'s), else ``mean`` (:func:`~colgnn_core.collision.correction.merge_pushes`)."""
    return correction_choice(scene, "push_rule", PUSH_RULES)


def correction_project(scene) -> str:
    """Which vertices the tool pass projects out of the tool for ``scene``: its TOML's ``[correction] project`` (or
    ``[correction.<resolution>]``'s), else ``all`` (:class:`~colgnn_core.collision.correction.CollisionCorrector`)."""
    return correction_choice(scene, "project", PROJECT_RULES)


def correction_choice(scene, key: str, choices: tuple[str, ...]) -> str:
    """The scene's ``[correction] key`` (:func:`correction_table`), else the first of ``choices``. InputError, naming
    the key and the choices, when the value is not one of them."""
    value = correction_table(scene).get(key, choices[0])
    if value not in choices:
        raise InputError(f"{scene.name}: correction.{key} must be one of {', '.join(choices)}, got {value!r}")
    return value


def correction_table(scene) -> dict:
    """The scene TOML's ``[correction]`` table at the scene's resolution: a ``[correction.full]`` or
    ``[correction.ci]`` sub-table overrides the common keys there (:func:`~colgnn_core.scenes.scene.at_resolution`)."""
    return at_resolution(scene.config.get("correction", {}), scene.resolution)


def self_contact_default(scene) -> bool:
    """Whether the Predictor runs the self-contact stage for ``scene`` unless told otherwise: its TOML's
    ``[correction] self_contact`` (or ``[correction.<resolution>]``'s), else False. A scene turns it on where its
    shipped model's steps are valid surfaces, so that the stage stays cheap (it repairs rarely); on a model that
    tears, the stage costs tens of ms a step. InputError when the value is not a boolean."""
    value = correction_table(scene).get("self_contact", False)
    if not isinstance(value, bool):
        raise InputError(f"{scene.name}: correction.self_contact must be true or false, got {value!r}")
    return value


def tool_step_limits(scene, extra: dict | None = None) -> tuple[float, float]:
    """(max translation m, max rotation rad) of the tool in one model step in the training distribution.

    From the checkpoint's ``extra`` when it records ``tool_step_max_translation`` /
    ``tool_step_max_rotation``; else from the scene's trajectory family: the larger of the
    analytic peak speed (1.5 x the top mean speed x the retract factor) and the largest step in
    a few sampled training trajectories (rotation likewise, at least 2 degrees).
    """
    extra = extra or {}
    if "tool_step_max_translation" in extra and "tool_step_max_rotation" in extra:
        return float(extra["tool_step_max_translation"]), float(extra["tool_step_max_rotation"])
    return _family_limits(scene.name, scene.resolution)


@lru_cache(maxsize=1)
def _libc_malloc_trim():
    """glibc's malloc_trim, or None (another C library)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def _release_memory() -> None:
    """Hand freed heap pages back to the OS. The correction's arrays change size every step; glibc then keeps
    fragmented free memory and a long-running process's RSS creeps up (several MB per 1,000 full-resolution
    cone_bunny steps measured); a periodic malloc_trim keeps it flat (~1 ms, every TRIM_EVERY steps)."""
    trim = _libc_malloc_trim()
    if trim is not None:
        trim(0)


def _rotation_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    return float(2.0 * np.arccos(min(1.0, abs(float(np.dot(q0, q1))))))


class Predictor:
    """GNN step + collision-aware correction for one scene (see module docstring).

    Args:
        loaded: a :class:`~colgnn_core.learn.checkpoint.LoadedCheckpoint` (GNN or subspace model).
        scene: the Scene it belongs to.
        correction: run the collision-aware correction (False: the raw network, still validated/subdivided).
        max_substeps: most model steps one ``step`` call may take for a large jump.
        threads: torch intra-op threads (set process-wide), and the collision kernels' numba threads (set per
            stepping thread, :func:`~colgnn_core.collision.kernels.use_kernel_threads`). The kernels drop to one
            thread while other processes hold the cores (:class:`~colgnn_core.runtime.threads.ContentionGuard`;
            ``StepResult.kernel_threads``). A compiled network runs on 1 thread instead where it was faster there
            when the Predictor was built (timed at warm-up; ``net.network_threads``).
        max_iterations: correction passes before the safe fallback; default the scene's
            ``[correction] max_iterations`` (:func:`correction_iterations`).
        step_limits: (max translation m, max rotation rad) per model step; default from the
            checkpoint / scene family (:func:`tool_step_limits`).
        max_displacement, max_deviation: optional caps on the raw network output (see
            :class:`colgnn_core.runtime.stepper.RawStepper`), applied before the correction.
        compile: run the network through ``torch.compile`` (~1.8x faster GNN on a CPU); it is
            compiled here, before the first step (seconds; cached on disk by torch), and falls back to
            eager with a warning where compiling is impossible. GNN models only.
        rest_relaxation: fraction ``a`` of the way back to the rest shape the network's output moves in a step
            in which the tool is out of the network's reach (no world edge, or a static tool out of reach of the
            rest shape): ``x <- x + a (rest - x)``. The
            scenes' objects are elastic, so once released they return to rest; a learned model drifts instead
            (a few % of the bbox diagonal after thousands of steps), and this pulls it back. Once the tool has
            been out of reach for ``SETTLE_AFTER_STEPS`` model steps the rate ramps to 1 over
            ``SETTLE_RAMP_STEPS`` (a distorted network state can hold a deformation against a constant small
            rate: x* - rest = network acceleration / a). 0 (default): off. GNN models only; applied before
            the correction, so the guarantee is unchanged.
        interior: how a surface-only model's interior vertices follow its surface nodes (``positions``):
            'elastic' (default; the linear-elastic extension, a back-substitution per step: ~3.6 ms at full
            resolution) or 'interpolated' (inverse-distance weights, free; the node's choice, as it publishes
            the surface only). See :mod:`colgnn_core.runtime.interior`.
        warm_up: before returning, step into contact at the scene's target and back, then reset
            (:meth:`warm_up`): the first real pose then meets no lazy compilation (numba's kernels on a fresh
            clone, torch's specialisations). The node does this; a fresh clone's first start takes ~25 s longer.
        self_contact: run the self-contact stage after the tool pass (with ``correction``): the published object
            never passes through itself and its surface stays valid (docs/COLLISION_GUARANTEE.md). Default (None):
            the scene's ``[correction] self_contact`` (:func:`self_contact_default`), on where the shipped model's
            steps are valid surfaces and the stage is cheap; on a model that tears it costs tens of ms a step.
    """

    def __init__(self, loaded, scene, *, correction: bool = True, max_substeps: int = DEFAULT_MAX_SUBSTEPS,
                 threads: int | None = 2, max_iterations: int | None = None,
                 step_limits: tuple[float, float] | None = None, max_displacement: float | None = None,
                 max_deviation: float | None = None, compile: bool = False, rest_relaxation: float = 0.0,
                 self_contact: bool | None = None, warm_up: bool = False, interior: str = "elastic"):
        if max_substeps < 1:
            raise InputError(f"max_substeps must be >= 1, got {max_substeps}")
        if not 0.0 <= rest_relaxation < 1.0:
            raise InputError(f"rest_relaxation must be in [0, 1), got {rest_relaxation}")
        if threads is not None:
            if threads < 1:
                raise InputError(f"threads must be >= 1, got {threads}")
            torch.set_num_threads(int(threads))
        self.loaded = loaded
        self.scene = scene
        self.model = loaded.simulator
        self.template = self.model.template
        self.correction = bool(correction)
        self.rest_relaxation = float(rest_relaxation)
        self._rest_tree = None  # k-d tree of the rest graph nodes (built on first need)
        self.max_substeps = int(max_substeps)
        self.threads = torch.get_num_threads()
        self.kernel_guard = ContentionGuard(self.threads)  # the collision kernels use the network's cores if free
        self.max_translation, self.max_rotation = (tool_step_limits(scene, loaded.extra) if step_limits is None
                                                   else (float(step_limits[0]), float(step_limits[1])))
        if not (self.max_translation > 0 and self.max_rotation > 0):
            raise InputError(f"step limits must be > 0, got {self.max_translation} m, {self.max_rotation} rad")
        tpl = self.template
        # One rest state: the settled shape the ground truth starts from (start, relaxation and caps refer to it).
        self.rest_mesh = settled_rest(loaded, scene)
        self.net = RawStepper(self.model, scene, max_displacement, max_deviation,  # the network step and its state
                              rest_mesh=self.rest_mesh, interior=interior)
        extra = loaded.extra or {}
        poses = extra.get("domain_tool_positions")
        self._domain_tree = cKDTree(np.asarray(poses, dtype=np.float64)) if poses is not None else None
        self.domain_radius = DOMAIN_RADIUS_FACTOR * float(tpl.world_radius)
        dev = extra.get("domain_max_deviation")
        self.domain_deviation = DOMAIN_DEVIATION_FACTOR * float(dev) if dev is not None else None
        self.surface_faces = np.asarray(scene.object.faces, dtype=np.int64)
        self.surface_vertex_ids = np.unique(self.surface_faces)
        self.tool_faces = np.asarray(scene.tool.faces, dtype=np.int64)
        if max_iterations is None:
            max_iterations = correction_iterations(scene)
        self.corrector = (CollisionCorrector(tpl.surface_faces, tpl.num_object_nodes, scene.tool, scene.dhat,
                                             max_iterations=max_iterations, push_rule=correction_push_rule(scene),
                                             project=correction_project(scene))
                          if self.correction else None)
        if self_contact is None:
            self_contact = self_contact_default(scene)
        self.self_contact = (SelfContact(tpl.surface_faces, tpl.num_object_nodes, self.net.rest.numpy())
                             if self.corrector is not None and self_contact else None)
        self.state: PredictorState | None = None
        self._since_trim = 0
        self.reset()
        self.compiled = bool(compile) and hasattr(self.model, "compile_network")
        if self.compiled:
            self.model.compile_network()
            self._warm_up_network()
        self.warm_up_s = self.warm_up() if warm_up else 0.0

    @torch.inference_mode()
    def _warm_up_network(self) -> None:
        """Call the network on the rest graph with 0, 1 and 2 world-edge pairs: every shape class the
        compiled network can meet (torch specialises sizes 0 and 1; 2 and up share one kernel), at ``threads`` and at
        1 thread (torch's thread count is part of what a compiled variant assumes: a count met first mid-run would
        compile then, 0.3-4 s). Then time it on 1 thread against ``threads`` and keep the faster count for the
        network (``net.network_threads``; :func:`~colgnn_core.runtime.threads.fastest_thread_count`)."""
        graphs = [self._rest_graph(pairs) for pairs in (0, 1, 2)]
        for n in sorted({1, self.threads}, reverse=True):
            torch.set_num_threads(n)
            for graph in graphs:
                self.model.network(graph)
        torch.set_num_threads(self.threads)
        # A prior solved beside the network holds a core while the network runs: leave it that core.
        requested = min(self.threads, max(1, (os.cpu_count() or 1) - 1)) if self.net.prior_beside else self.threads
        self.net.network_threads = fastest_thread_count(lambda: self.model.network(graphs[-1]), requested,
                                                        torch.set_num_threads)

    def _rest_graph(self, pairs: int):
        """The graph at the current (rest) state with ``pairs`` world-edge pairs between node 0 and tool node 0."""
        s = self.net.state
        g = self.model.build_graph(Frame(s.x_t, s.x_t, s.tool_t, s.tool_t, s.pose, torch.zeros_like(s.x_t)))
        n = g.num_object_nodes
        send = torch.tensor([n] * pairs + [0] * pairs, dtype=torch.int64)
        recv = torch.tensor([0] * pairs + [n] * pairs, dtype=torch.int64)
        feats = torch.zeros((2 * pairs, g.world.features.shape[1]), dtype=g.world.features.dtype)
        # replace(): keep every other part of the graph (a coarse level's edges, for one)
        return replace(g, world=EdgeSet(feats, send, recv))

    def warm_up(self, depth: float = WARM_UP_DEPTH) -> float:
        """Press ``depth`` of the way from the surface to the deepest valid pose at the scene's target in single
        model steps, go back to the rest pose in substepped steps, then :meth:`reset`. Every stage (graph, network,
        correction with contact, clearance, substep check, lifting, self-contact) runs once, so that its lazily
        compiled kernels exist before the first real pose. Returns the seconds it took."""
        started = time.monotonic()
        rest = np.asarray(self.scene.tool_rest_pose, dtype=np.float64)
        try:
            bottom = press_pose(self.scene, depth)
        except InputError:  # a user's object that the tool misses above its target: warm up without contact
            bottom = rest
        for pose in pose_path(rest, bottom, 0.9 * self.max_translation):
            self.step(pose)
        for pose in pose_path(bottom, rest, min(2.0, self.max_substeps) * 0.9 * self.max_translation):
            self.step(pose)
        self.reset()
        return time.monotonic() - started

    @classmethod
    def from_checkpoint(cls, checkpoint_or_scene, *, scene=None, correction: bool = True,
                        max_substeps: int = DEFAULT_MAX_SUBSTEPS, threads: int | None = 2, limits: str = "none",
                        **kwargs) -> "Predictor":
        """A Predictor from a checkpoint path, a LoadedCheckpoint, or a scene name (its shipped model).

        ``limits='data'`` caps the network output by the training data's extremes
        (:func:`colgnn_core.runtime.models.output_limits`) unless ``max_displacement`` / ``max_deviation`` are
        given; other keyword arguments go to :class:`Predictor` (e.g. ``compile=True``).
        """
        loaded, scene = model_and_scene(checkpoint_or_scene, scene)
        kwargs["max_displacement"], kwargs["max_deviation"] = output_limits(
            loaded, limits, kwargs.get("max_displacement"), kwargs.get("max_deviation"))
        return cls(loaded, scene, correction=correction, max_substeps=max_substeps, threads=threads, **kwargs)

    # -- state ----------------------------------------------------------------------------------------------------
    def reset(self, positions: np.ndarray | None = None, tool_pose: np.ndarray | None = None) -> None:
        """Object at its settled rest (or ``positions`` [N_mesh,3]) and at rest velocity; tool at its rest pose (or
        ``tool_pose``)."""
        n_mesh = self.scene.object.vertices.shape[0]
        x0 = np.asarray(self.rest_mesh if positions is None else positions, dtype=np.float64)
        if x0.shape != (n_mesh, 3) or not np.all(np.isfinite(x0)):
            raise InputError(f"positions must be a finite [{n_mesh},3] array, got shape {x0.shape}")
        pose = self.scene.tool_rest_pose if tool_pose is None else tool_pose
        pose = self.scene.check_pose(pose)
        self.net.reset(x0[self.template.object_nodes], pose)
        self.state = PredictorState(mesh=x0.copy(), tool_vertices=self.scene.tool.world_vertices(pose))

    @property
    def steps(self) -> int:
        """Model steps since reset."""
        return self.state.steps

    @property
    def fallbacks(self) -> int:
        """Model steps since reset whose correction used the safe fallback."""
        return self.state.fallbacks

    @property
    def relaxed_steps(self) -> int:
        """Model steps since reset relaxed towards the rest shape."""
        return self.state.relaxed_steps

    @property
    def free_steps(self) -> int:
        """Consecutive released model steps (the settle ramp's clock)."""
        return self.state.free_steps

    @property
    def tool_pose(self) -> np.ndarray:
        """[7] the tool pose of the current state."""
        return self.net.state.pose.copy()

    @property
    def positions(self) -> np.ndarray:
        """[N_mesh,3] the current published object positions."""
        return self.state.mesh.copy()

    @property
    def graph_positions(self) -> np.ndarray:
        """[N,3] the current object graph-node positions."""
        return self.net.state.x_t.numpy().copy()

    # -- stepping -------------------------------------------------------------------------------------------------
    def substeps_for(self, pose: np.ndarray) -> int:
        """Model steps needed to move the tool from the current pose to ``pose`` (validated [7])."""
        cur = self.net.state.pose
        n_t = float(np.linalg.norm(pose[:3] - cur[:3])) / self.max_translation
        n_r = _rotation_angle(cur[3:], pose[3:]) / self.max_rotation
        # 1e-9: a step exactly at the limit stays one step despite rounding.
        return max(1, int(math.ceil(max(n_t, n_r) - 1e-9)))

    def check(self, tool_pose) -> tuple[np.ndarray, int]:
        """(validated pose, substeps) or InputError; does not change the state."""
        pose = self.scene.check_pose(tool_pose)
        n = self.substeps_for(pose)
        turn = _rotation_angle(self.net.state.pose[3:], pose[3:])
        if self.corrector is not None and turn > MAX_ROTATION:
            raise InputError(f"tool pose jump too large: it turns the tool by {math.degrees(turn):.1f} deg in one "
                             f"step; the collision guarantee covers up to {math.degrees(MAX_ROTATION):.0f} deg")
        if n > self.max_substeps:
            cur = self.net.state.pose
            raise InputError(
                f"tool pose jump too large: {np.linalg.norm(pose[:3] - cur[:3]) * 1e3:.1f} mm and "
                f"{math.degrees(_rotation_angle(cur[3:], pose[3:])):.1f} deg in one step would need {n} model steps "
                f"(limit {self.max_substeps} of at most {self.max_translation * 1e3:.2f} mm / "
                f"{math.degrees(self.max_rotation):.2f} deg each)")
        return pose, n

    @torch.inference_mode()
    def step(self, tool_pose) -> StepResult:
        """Advance to ``tool_pose`` [7] and return the published state (InputError: state unchanged)."""
        t_start = time.perf_counter()
        pose, n = self.check(tool_pose)
        # numba's count is per thread (a ROS executor may step from another), so it is set on every step.
        kernel_threads = use_kernel_threads(self.kernel_guard.threads())
        start = self.net.state.pose
        subposes = interpolate_poses(start, pose, np.arange(1, n + 1) / n) if n > 1 else pose[None]
        subposes[-1] = pose
        res = StepResult(positions=self.state.mesh, surface_faces=self.surface_faces,
                         surface_vertex_ids=self.surface_vertex_ids, tool_vertices=None, tool_faces=self.tool_faces,
                         tool_pose=pose, substeps=n, kernel_threads=kernel_threads)
        ms = {"graph": 0.0, "gnn": 0.0, "correction": 0.0, "self_contact": 0.0}
        saved = (self.net.state, self.state)
        try:
            for sp in subposes:
                self._model_step(sp, res, ms, clearance=n == 1)
            if n > 1 and self.corrector is not None:
                self._correct_published(saved[0], pose, res, ms)
            if self.self_contact is not None:
                self._correct_self(saved[0], pose, res, ms)
        except BaseException:
            # A failure inside a model step (e.g. non-finite network output) leaves the state as it was.
            self.net.state, self.state = saved
            raise
        t_lift = time.perf_counter()
        self.state = replace(self.state, mesh=self.lift(self.net.state.x_t.numpy(), res))
        ms["graph"] += 1e3 * (time.perf_counter() - t_lift)  # lifting belongs to the graph bookkeeping
        res.positions = self.state.mesh
        res.tool_vertices = self.state.tool_vertices
        ms["total"] = 1e3 * (time.perf_counter() - t_start)
        res.timings_ms = ms
        return res

    def _correct_published(self, start, pose: np.ndarray, res: StepResult, ms: dict) -> None:
        """After the model steps of one published step: correct the straight motion from the last published state
        (``start``, the network state then) to the last model step's result, clearance included, as a model step is;
        the output becomes the network's current positions."""
        now = self.net.state
        t = time.perf_counter()
        c = self.corrector.correct(start.x_t.numpy(), now.x_t.numpy(), start.pose, pose, start.tool_t.numpy(),
                                   now.tool_t.numpy(), clearance=True)
        ms["correction"] += 1e3 * (time.perf_counter() - t)
        res.published_moved = c.moved
        res.vertex_face_after += c.vertex_face_after
        res.edge_edge_after += c.edge_edge_after
        res.penetrating_vertices_after = c.penetrating_after
        res.correction_iterations += c.iterations
        if c.fallback:
            res.fallback = True
            self.state = replace(self.state, fallbacks=self.state.fallbacks + 1)
        if c.moved:
            self.net.state = replace(now, x_t=torch.from_numpy(c.positions))

    def _correct_self(self, start, pose: np.ndarray, res: StepResult, ms: dict) -> None:
        """The self-contact stage on the published step: the straight motion from the last published state
        (``start``, the network state then; self-clean and valid by induction) to the tool-corrected result."""
        now = self.net.state
        t = time.perf_counter()
        s = self.self_contact.correct(self.corrector, start.x_t.numpy(), now.x_t.numpy(), start.pose, pose,
                                      start.tool_t.numpy(), now.tool_t.numpy(), clearance=True)
        ms["self_contact"] += 1e3 * (time.perf_counter() - t)
        res.self_pairs_before, res.self_pairs_after = s.pairs_before, s.pairs_after
        res.invalid_faces_before, res.invalid_faces_after = s.invalid_before, s.invalid_after
        res.self_fallback, res.self_moved = s.fallback, s.moved
        res.fallback = res.fallback or s.tool_fallback  # a tool pass after a self repair fell back
        if s.fallback:
            self.state = replace(self.state, self_fallbacks=self.state.self_fallbacks + 1)
        if s.moved:
            self.net.state = replace(now, x_t=torch.from_numpy(s.positions))

    def _model_step(self, pose_next: np.ndarray, res: StepResult, ms: dict, clearance: bool = True) -> None:
        net = self.net
        tool_next_np = self.scene.tool.world_vertices(pose_next)
        tool_next = torch.from_numpy(tool_next_np)
        x_raw = net.propose(pose_next, tool_next)
        ms["graph"] += net.last_ms["graph"]
        ms["gnn"] += net.last_ms["gnn"]
        released = bool(self.rest_relaxation) and self._released(pose_next, tool_next_np)
        st = self.state
        st = replace(st, free_steps=st.free_steps + 1 if released else 0)
        self.state = st
        if released:
            x_raw = x_raw + self.relaxation_rate() * (net.rest - x_raw)
            st = replace(st, relaxed_steps=st.relaxed_steps + 1)
        fallbacks = st.fallbacks
        if self.corrector is not None:
            t = time.perf_counter()
            now = net.state
            c = self.corrector.correct(now.x_t.numpy(), x_raw.numpy(), now.pose, pose_next, now.tool_t.numpy(),
                                       tool_next_np, clearance=clearance)
            ms["correction"] += 1e3 * (time.perf_counter() - t)
            res.vertex_face_before += c.vertex_face_before
            res.edge_edge_before += c.edge_edge_before
            res.vertex_face_after += c.vertex_face_after
            res.edge_edge_after += c.edge_edge_after
            res.penetrating_vertices_after = c.penetrating_after
            res.correction_iterations += c.iterations
            if c.fallback:
                res.fallback = True
                fallbacks += 1
            x_next = torch.from_numpy(c.positions)
        else:
            x_next = x_raw
        outside = self.outside_domain(pose_next, x_next)
        res.out_of_domain += int(outside)
        net.commit(x_next, tool_next, pose_next)
        self.state = replace(st, tool_vertices=tool_next_np, steps=st.steps + 1, fallbacks=fallbacks,
                             out_of_domain=st.out_of_domain + int(outside))
        self._since_trim += 1
        if self._since_trim >= TRIM_EVERY:
            self._since_trim = 0
            _release_memory()

    def _released(self, pose_next: np.ndarray, tool_next: np.ndarray) -> bool:
        """Is the object free of the tool this model step? Yes when the graph has no world edge, and also when a
        *static* tool is out of reach of the object's *rest* shape: a distorted learned state can keep brushing
        a tool that has left (world edges flickering on and off), which is not contact an elastic object keeps."""
        net = self.net
        if net.world_edges == 0:
            return True
        if net.world_edges is None or not np.array_equal(pose_next, net.state.pose):
            return False
        if self._rest_tree is None:
            self._rest_tree = cKDTree(net.rest.numpy())
        d, _ = self._rest_tree.query(tool_next, distance_upper_bound=self.template.world_radius)
        return bool(np.isinf(d).all())

    def outside_domain(self, pose_next: np.ndarray, x_next: torch.Tensor) -> bool:
        """Is this model step outside what the model was trained on? (See DOMAIN_RADIUS_FACTOR.) The tool pose
        counts only while it is within the network's reach (world edges): far from the object any pose is fine.
        Checkpoints without the training-data record are never flagged."""
        if self._domain_tree is not None and self.net.world_edges != 0:
            d, _ = self._domain_tree.query(pose_next[:3], distance_upper_bound=self.domain_radius)
            if np.isinf(d):
                return True
        if self.domain_deviation is not None:
            dev = torch.linalg.vector_norm(x_next - self.net.rest, dim=1).max()
            return bool(dev > self.domain_deviation)
        return False

    def relaxation_rate(self) -> float:
        """This step's rest-relaxation fraction: ``rest_relaxation``, ramping to 1 once the tool has been out of
        reach for ``SETTLE_AFTER_STEPS`` model steps (0 when the relaxation is off)."""
        if not self.rest_relaxation:
            return 0.0
        ramp = min(1.0, max(0.0, (self.free_steps - SETTLE_AFTER_STEPS) / SETTLE_RAMP_STEPS))
        return self.rest_relaxation + (1.0 - self.rest_relaxation) * ramp

    def lift(self, x_graph: np.ndarray, res: StepResult | None = None) -> np.ndarray:
        """Graph-node positions [N,3] -> every mesh vertex [N_mesh,3] (the ``interior`` lift); with the correction,
        interior vertices inside the tool at the current pose are moved out (counted in ``res.interior_cleared``)."""
        mesh = self.net.mesh(x_graph)
        ids = self.template.interior_ids
        if self.corrector is not None and ids is not None:
            inner = mesh[ids]
            moved = self.corrector.clear_points(inner, self.net.state.pose)
            if moved:
                mesh[ids] = inner
                if res is not None:
                    res.interior_cleared += moved
        return mesh

    # -- the rollout loop's stepper interface ---------------------------------------------------------------------
    def stepper(self) -> "PredictorStepper":
        """This predictor behind the rollout loop's Stepper protocol (graph-node positions per step)."""
        return PredictorStepper(self)


class PredictorStepper:
    """Adapter for :func:`colgnn_core.runtime.stepper.run_stepper`: records a StepResult summary per frame."""

    def __init__(self, predictor: Predictor):
        self.predictor = predictor
        self.template = predictor.template
        self.clamped = 0
        self.records: list[dict] = []

    def reset(self, x0_graph: np.ndarray, pose0: np.ndarray) -> None:
        p = self.predictor
        # Interior vertices of a surface-only model are not state: lift them from the nodes.
        p.reset(p.net.mesh(np.asarray(x0_graph, dtype=np.float64)), pose0)
        self.records = []

    def step(self, pose_next: np.ndarray) -> np.ndarray:
        r = self.predictor.step(pose_next)
        rec = r.collision_counts()
        rec["out_of_domain"] = r.out_of_domain
        rec.update({f"{k}_ms": v for k, v in r.timings_ms.items()})
        self.records.append(rec)
        return self.predictor.graph_positions

    def mesh(self, x_graph: np.ndarray) -> np.ndarray:
        """Every mesh vertex [N_mesh,3] as the Predictor published them for ``x_graph``, the graph positions the
        last ``step`` returned (already lifted there: not computed twice)."""
        return self.predictor.positions

    def extra(self) -> dict[str, np.ndarray]:
        """Per-frame arrays [T] (frame 0 = 0) of the counts and stage timings, for Sequence.extra."""
        if not self.records:
            return {}
        keys = list(self.records[0])
        return {k: np.concatenate([[0], [r[k] for r in self.records]]).astype(
            np.float64 if k.endswith("_ms") else np.int64) for k in keys}


def warm_compile_cache(scene_names: Sequence[str], threads: int | None = None) -> dict[str, float]:
    """Compile each scene's shipped model once, so that torch's on-disk cache makes later start-ups quick.

    ``make setup`` runs this for every scene, because the node compiles by default; the warm-up step also fills
    numba's on-disk cache of the collision kernels (a fresh clone has none). Returns the seconds each
    scene took (a cold cache: 10-30 s a model; a warm one: a few seconds).
    """
    seconds = {}
    for name in scene_names:
        started = time.monotonic()
        Predictor.from_checkpoint(name, compile=True, threads=threads or auto_threads(), warm_up=True,
                                  interior=REALTIME_INTERIOR)
        seconds[name] = time.monotonic() - started
    return seconds

