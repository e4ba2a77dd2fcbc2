"""``colgnn bench --stability``: a long random-motion rollout through the Predictor, then the tool leaves.

The tool follows the scene's ``random`` scripted motion (smooth random waypoints with tilts, in the training
family's range) for ``steps`` steps, moves back to its rest pose at the training speed, and holds there for
``settle`` steps. Reported:

* every published frame finite (else the run stops and says where);
* object–tool intersecting frames (ipctk, every ``check_every`` frames and every frame with a correction
  fallback) and object self-intersecting frames (same frames): the first is the product guarantee, the second
  is shape quality;
* fallbacks, crossings before the correction;
* resident memory (VmRSS) every ``memory_every`` steps and its slope after the first quarter (MB per 1,000
  steps);
* the shape error after the tool left: RMSE and max vertex distance from the rest shape after the best rigid
  alignment (Kabsch: a sliding, still undeformed object counts as at rest), as fractions of the bbox
  diagonal. Target: within 1%.
"""

from __future__ import annotations

import time

import numpy as np

from colgnn_core.collision.exact import self_intersects, tool_intersects, tool_step_free
from colgnn_core.collision.surface_validity import SurfaceValidity
from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import family_poses, stats
from colgnn_core.geometry.transforms import interpolate_poses
from colgnn_core.runtime.predictor import Predictor, tool_step_limits
from colgnn_core.scenes.hard_cases import hard_trajectories
from colgnn_core.scenes.trajectories import scripted_poses


def rss_mb() -> float:
    """Resident memory of this process (MB), from /proc (NaN where there is none)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def rigid_shape_error(x: np.ndarray, rest: np.ndarray) -> tuple[float, float]:
    """(RMSE, max distance) in m between ``x`` [N,3] and ``rest`` [N,3] after the best rigid alignment of x."""
    a, b = x - x.mean(0), rest - rest.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, 1.0, d]) @ vt
    diff = a @ r - b
    dist = np.linalg.norm(diff, axis=1)
    return float(np.sqrt((dist**2).mean())), float(dist.max())


def _leave_and_settle(scene, last: np.ndarray, max_translation: float, settle: int) -> np.ndarray:
    """Poses from ``last`` back to the rest pose in steps of at most ``max_translation``, then ``settle`` holds."""
    rest = scene.tool_rest_pose
    n = max(1, int(np.ceil(np.linalg.norm(rest[:3] - last[:3]) / (0.9 * max_translation))))
    back = interpolate_poses(last, rest, np.arange(1, n + 1) / n)
    return np.concatenate([back, np.repeat(rest[None], settle, axis=0)])


def hard_cases(scene, frames: int = 40, random_steps: int = 2000, step: float | None = None
               ) -> dict[str, np.ndarray]:
    """The hard-case tool trajectories [T,7] of a scene, by name.

    * ``test sequence``: a held-out family trajectory;
    * ``3x faster``: a family trajectory at three times the training speed (every third pose);
    * ``grazing``: a drag across the target at the shallowest family depth minus 0.3 dhat: the tool just
      touches the surface;
    * ``jitter``: the scripted press with ±1.5 mm of uniform noise on every pose;
    * ``leave and re-enter``: repeated fast stabs to the deepest family depth;
    * ``press and drag``, ``fast plunge``: :func:`colgnn_core.scenes.hard_cases.hard_trajectories` (85% of the way
      to the deepest valid pose, then a quarter of the object's extent each way; straight to the deepest valid
      pose at 4 model steps per frame), with ``step`` the per-model-step tool motion (default: the scene family's,
      :func:`~colgnn_core.runtime.predictor.tool_step_limits`);
    * ``random with tilts``: ``random_steps`` steps of smooth random motion with the family's tilts (left out
      when ``random_steps`` is 0).
    """
    graze = scripted_poses(scene, "drag", frames)
    graze[:, 2] += float(scene.family["depth"][0]) - 0.3 * scene.dhat
    jitter = scripted_poses(scene, "press", frames)
    rng = np.random.default_rng(3)
    jitter[1:, :3] += rng.uniform(-1.5e-3, 1.5e-3, size=(len(jitter) - 1, 3))
    jitter[:, :3] = np.clip(jitter[:, :3], scene.workspace_min, scene.workspace_max)
    cases = {"test sequence": family_poses(scene, frames + 1), "3x faster": family_poses(scene, 3 * frames, 2)[::3],
             "grazing": graze, "jitter": jitter, "leave and re-enter": scripted_poses(scene, "stab", frames)}
    step = tool_step_limits(scene)[0] if step is None else float(step)
    cases.update(hard_trajectories(scene, step, kinds=("press and drag", "fast plunge")))
    if random_steps:
        cases["random with tilts"] = scripted_poses(scene, "random", random_steps + 1, seed=7)
    return cases


def check_rollout(pred, poses: np.ndarray, check_every: int = 1) -> dict:
    """Step the Predictor ``pred`` through ``poses[1:]`` (from ``poses[0]``, rest shape) and check the published
    frames and steps with ipctk's exact oracle.

    Every ``check_every``-th frame, and every frame whose step needed a correction, a fallback or model substeps,
    is checked for object–tool intersection, and the step into it, the straight motion from the previous
    published frame (split into model steps or not), by ipctk's ``is_step_collision_free`` with its default
    line-search clearance (``crossing``: what the Predictor guarantees not to happen) and for a real touch
    (``contact``). Raises InputError if a published frame is not finite. Returns counts: steps, checked,
    intersecting, crossing, contact, fallback_steps, fallbacks_total, before (crossings found before the
    correction), after_nonzero (steps the Predictor itself reported unclean after its correction), substeps.
    """
    scene = pred.scene
    F, TF = scene.object.faces, scene.tool.faces
    pred.reset(tool_pose=poses[0])
    prev, prev_tool = pred.positions, scene.tool.world_vertices(pred.tool_pose)
    counts = {"steps": 0, "checked": 0, "intersecting": 0, "crossing": 0, "contact": 0, "fallback_steps": 0,
             "before": 0, "after_nonzero": 0, "substeps": 0}
    for k in range(1, len(poses)):
        r = pred.step(poses[k])
        if not np.isfinite(r.positions).all():
            raise InputError(f"the rollout became non-finite at step {k}")
        counts["steps"] += 1
        counts["fallback_steps"] += int(r.fallback)
        before = r.vertex_face_before + r.edge_edge_before
        counts["before"] += before
        counts["substeps"] += r.substeps
        counts["after_nonzero"] += bool(r.vertex_face_after or r.edge_edge_after or r.penetrating_vertices_after)
        if k % check_every == 0 or before or r.fallback or r.substeps > 1 or r.published_moved:
            counts["checked"] += 1
            counts["intersecting"] += tool_intersects(r.positions, F, r.tool_vertices, TF)
            if not tool_step_free(prev, r.positions, F, prev_tool, r.tool_vertices, TF):
                counts["crossing"] += 1
                counts["contact"] += not tool_step_free(prev, r.positions, F, prev_tool, r.tool_vertices, TF,
                                                       contact_only=True)
        prev, prev_tool = r.positions, r.tool_vertices
    counts["fallbacks_total"] = pred.fallbacks
    return counts


def stability(checkpoint_or_scene, *, steps: int = 10_000, settle: int = 300, seed: int = 0,
              check_every: int = 10, memory_every: int = 250, threads: int = 2, compile: bool = False,
              limits: str = "none", rest_relaxation: float = 0.0, self_contact: bool | None = None,
              progress: bool = True) -> dict:
    """Run the long rollout (see the module docstring) and return a JSON-ready report.

    ``limits``: output caps of the Predictor ('none' or 'data', see :meth:`Predictor.from_checkpoint`);
    ``rest_relaxation``, ``self_contact`` (None: the scene's default): see
    :class:`~colgnn_core.runtime.predictor.Predictor`."""
    if steps < 1 or settle < 1 or check_every < 1 or memory_every < 1:
        raise InputError("steps, settle, check_every and memory_every must be >= 1")
    pred = Predictor.from_checkpoint(checkpoint_or_scene, threads=threads, compile=compile, limits=limits,
                                     rest_relaxation=rest_relaxation, self_contact=self_contact)
    scene = pred.scene
    poses = scripted_poses(scene, "random", steps + 1, seed=seed)
    poses = np.concatenate([poses, _leave_and_settle(scene, poses[-1], pred.max_translation, settle)])
    faces, tool_faces = scene.object.faces, scene.tool.faces
    pred.reset(tool_pose=poses[0])
    rest = pred.rest_mesh  # the settled rest the Predictor starts from and returns to (one rest state)
    validity = SurfaceValidity(faces, rest)
    counts = {"tool_intersecting_frames": 0, "self_intersecting_frames": 0, "invalid_surface_frames": 0,
              "checked_frames": 0, "fallbacks": 0, "self_fallbacks": 0, "crossings_before": 0, "steps_done": 0}
    memory: list[tuple[int, float]] = [(0, rss_mb())]
    step_ms: list[float] = []
    frames = range(1, len(poses))
    if progress:
        from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

        frames = tqdm(frames, desc=f"{scene.name} stability", unit="step", mininterval=1.0)
    t_start = time.perf_counter()
    for k in frames:
        r = pred.step(poses[k])
        if not np.isfinite(r.positions).all():
            raise InputError(f"the rollout became non-finite at step {k}")
        step_ms.append(r.timings_ms["total"])
        counts["steps_done"] = k
        counts["fallbacks"] += int(r.fallback)
        counts["self_fallbacks"] += int(r.self_fallback)
        counts["crossings_before"] += r.vertex_face_before + r.edge_edge_before
        if k % check_every == 0 or r.fallback or k == len(poses) - 1:
            counts["checked_frames"] += 1
            counts["tool_intersecting_frames"] += tool_intersects(r.positions, faces, r.tool_vertices, tool_faces)
            counts["self_intersecting_frames"] += self_intersects(r.positions, faces)
            counts["invalid_surface_frames"] += bool(validity.invalid(r.positions).any())
        if k % memory_every == 0:
            memory.append((k, rss_mb()))
    diagonal = scene.bbox_diagonal()
    rmse, worst = rigid_shape_error(pred.positions, rest)
    ks = np.array([k for k, _ in memory], dtype=np.float64)
    mb = np.array([m for _, m in memory])
    late = ks >= 0.25 * ks[-1]
    slope = float(np.polyfit(ks[late], mb[late], 1)[0] * 1000.0) if late.sum() >= 3 else float("nan")
    step = stats(step_ms)
    return {
        "scene": scene.name, "resolution": scene.resolution, "checkpoint": str(checkpoint_or_scene),
        "random_steps": steps, "leave_and_settle_steps": len(poses) - 1 - steps, "seed": seed,
        "threads": pred.threads, "compiled": pred.compiled, "limits": limits, "rest_relaxation": rest_relaxation,
        "self_contact": pred.self_contact is not None,
        "relaxed_steps": pred.relaxed_steps, **counts,
        "step_ms_median": step["median"], "step_ms_p95": step["p95"],
        "rss_mb_start": float(mb[0]), "rss_mb_end": float(mb[-1]), "rss_mb_per_1000_steps": slope,
        "rss_mb_samples": [[int(k), round(float(m), 1)] for k, m in memory],
        "rest_rmse_fraction": rmse / diagonal, "rest_max_fraction": worst / diagonal,
        "returned_to_rest_within_1pct": bool(rmse / diagonal <= 0.01),
        "wall_s": time.perf_counter() - t_start,
    }


def format_stability(r: dict) -> str:
    """A short readable report of :func:`stability`."""
    return "\n".join([
        f"{r['scene']} ({r['resolution']}): {r['random_steps']} random steps + {r['leave_and_settle_steps']} "
        f"leaving/settling, {r['threads']} threads{', compiled' if r['compiled'] else ''}, limits {r['limits']}, "
        f"rest relaxation {r.get('rest_relaxation', 0.0):g} ({r.get('relaxed_steps', 0)} steps), "
        f"{r['wall_s']:.0f} s",
        f"  step ms median / p95           {r['step_ms_median']:.2f} / {r['step_ms_p95']:.2f}",
        f"  object-tool intersecting frames {r['tool_intersecting_frames']} of {r['checked_frames']} checked",
        f"  object self-intersecting frames {r['self_intersecting_frames']} of {r['checked_frames']} checked",
        f"  frames with invalid faces       {r.get('invalid_surface_frames', '-')} of {r['checked_frames']} checked",
        f"  fallbacks / crossings before    {r['fallbacks']} / {r['crossings_before']}",
        f"  memory MB start / end / slope   {r['rss_mb_start']:.1f} / {r['rss_mb_end']:.1f} / "
        f"{r['rss_mb_per_1000_steps']:+.2f} per 1000 steps",
        f"  shape after the tool left       RMSE {100 * r['rest_rmse_fraction']:.2f}%, max "
        f"{100 * r['rest_max_fraction']:.2f}% of the bbox diagonal (rigid-aligned; target <= 1%: "
        f"{'met' if r['returned_to_rest_within_1pct'] else 'NOT met'})",
    ])
