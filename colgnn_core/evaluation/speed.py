"""``colgnn bench``: the real-time Predictor against the IPC solver, on the same scene and poses, in one run.

The trajectory is the first test trajectory of the scene's family. The IPC solver simulates it first (its per-step
cost is ``ipc_ms`` and its frames are the reference of ``rollout_rmse``); then the Predictor, started from the same
frame 0, steps through the same poses. Medians and ratios come from this one run; absolute times on a shared machine
are noisy, so quote both.
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import family_poses, relative_displacement_error, rmse_fraction, stats
from colgnn_core.runtime.predictor import REALTIME_INTERIOR, Predictor
from colgnn_core.scenes import scene_names
from colgnn_core.sim.dataset import simulate_sequence


def timed_rollout(predictor, poses: np.ndarray, x0: np.ndarray) -> dict:
    """Step ``predictor`` through ``poses[1:]`` from mesh positions ``x0`` [N,3] and ``poses[0]``, timing each step.

    Returns ``stages`` ({'total', 'graph', 'gnn', 'correction', 'self_contact'}: per-step ms lists; total = wall time of
    ``step``), ``positions`` [T,N,3] (frame 0 = x0), ``crossings_before``, ``crossings_after`` and ``fallbacks``
    and ``out_of_domain`` (totals over the steps).
    """
    predictor.reset(positions=x0, tool_pose=poses[0])
    stages: dict[str, list[float]] = {"total": [], "graph": [], "gnn": [], "correction": [], "self_contact": []}
    positions = [np.asarray(x0, dtype=np.float64)]
    before = after = fallbacks = outside = 0
    for pose in poses[1:]:
        t0 = time.perf_counter()
        res = predictor.step(pose)
        stages["total"].append(1e3 * (time.perf_counter() - t0))
        for k in ("graph", "gnn", "correction", "self_contact"):
            stages[k].append(float(res.timings_ms.get(k, 0.0)))
        positions.append(res.positions)
        before += res.vertex_face_before + res.edge_edge_before
        after += res.vertex_face_after + res.edge_edge_after
        fallbacks += int(res.fallback)
        outside += res.out_of_domain
    return {"stages": stages, "positions": np.stack(positions), "crossings_before": int(before),
            "crossings_after": int(after), "fallbacks": int(fallbacks), "out_of_domain": int(outside)}


def bench(scene_name: str, checkpoint: str | None = None, frames: int = 40, threads: int = 2,
          correction: bool = True, progress: bool = False, compile: bool = False,
          self_contact: bool | None = None, warm_up: bool = True, rollouts: int = 1) -> dict:
    """Benchmark one scene. Returns the JSON fields of the ``colgnn bench`` contract.

    Args:
        scene_name: scene whose shipped model is used unless ``checkpoint`` is given; the resolution is the
            checkpoint's.
        frames: trajectory length including the rest frame (≥ 3).
        threads: torch threads of the Predictor (the solver uses numpy/scipy's own).
        compile: torch.compile the network first (see :class:`~colgnn_core.runtime.predictor.Predictor`).
        self_contact: run the self-contact stage (its time is ``self_contact_ms``; 0 when off); None: the
            scene's default, as the node runs it (:func:`~colgnn_core.runtime.predictor.self_contact_default`).
        warm_up: :meth:`~colgnn_core.runtime.predictor.Predictor.warm_up` right before the timed steps, as the node
            does before it serves (default). False times a cold Predictor: its first steps pay first-use costs that
            the node pays during its warm-up.
        rollouts: timed passes over the trajectory, each from its frame 0 (the shapes are the same each time); the
            stage statistics are over every timed step, and ``rollout_medians_ms`` gives each pass's step median.
            On a machine whose speed drifts by a quarter from one second to the next (this project's 2-core VM:
            the banana's median read 17.0-25.7 ms in four runs of the same code), one pass of 19 steps (half a
            second) samples one phase of the drift; several passes sample more of it.
    """
    if scene_name not in scene_names():
        raise InputError(f"unknown scene {scene_name!r}; valid scenes: {', '.join(scene_names())}")
    if frames < 3:
        raise InputError(f"frames must be >= 3, got {frames}")
    if rollouts < 1:
        raise InputError(f"rollouts must be >= 1, got {rollouts}")
    predictor = Predictor.from_checkpoint(checkpoint or scene_name, correction=correction, threads=threads,
                                          compile=compile, self_contact=self_contact, interior=REALTIME_INTERIOR)
    scene = predictor.scene
    if scene.name != scene_name:
        raise InputError(f"checkpoint is for scene {scene.name!r}, not {scene_name!r}")
    poses = family_poses(scene, frames)

    truth = simulate_sequence(scene, poses, progress=progress)
    ipc_ms = truth.extra["step_ms"][1:]
    # Warmed up after the solver, right before the timed steps: the node warms up, then serves.
    warm_up_s = predictor.warm_up() if warm_up else 0.0

    runs = [timed_rollout(predictor, poses, truth.object_positions[0]) for _ in range(rollouts)]
    timed = runs[0]
    stages = {k: [v for run in runs for v in run["stages"][k]] for k in timed["stages"]}
    err = rmse_fraction(timed["positions"], truth.object_positions, scene.bbox_diagonal())
    total = stats(stages["total"])
    ipc = stats(ipc_ms)
    return {
        "scene": scene.name,
        "resolution": scene.resolution,
        "checkpoint": str(checkpoint or f"shipped:{scene_name}"),
        "correction": correction,
        "self_contact": bool(predictor.self_contact is not None),
        "frames": frames,
        "total_ms": total,
        "rollouts": int(rollouts),
        "rollout_medians_ms": [float(np.median(run["stages"]["total"])) for run in runs],
        "graph_ms": stats(stages["graph"]),
        "gnn_ms": stats(stages["gnn"]),
        "correction_ms": stats(stages["correction"]),
        "self_contact_ms": stats(stages["self_contact"]),
        "ipc_ms": ipc,
        "speedup_vs_ipc": ipc["median"] / total["median"],
        "rollout_rmse": {"step_1": float(err[1]), "step_10": float(err[min(10, len(err) - 1)]),
                         "all": float(err[1:].mean())},
        "relative_displacement_error": relative_displacement_error(timed["positions"], truth.object_positions,
                                                                   truth.object_positions[0]),
        "crossings_before_correction": timed["crossings_before"],
        "crossings_after_correction": timed["crossings_after"],
        "fallbacks": timed["fallbacks"],
        "out_of_domain_steps": timed["out_of_domain"],
        "threads": int(torch.get_num_threads()),
        # torch threads of the network itself: 1 where the compiled network was faster on 1 at warm-up
        "network_threads": int(predictor.net.network_threads or torch.get_num_threads()),
        # steps whose collision kernels ran on one thread: other processes held the cores (ContentionGuard)
        "kernel_threads_reduced_steps": int(predictor.kernel_guard.reduced_steps),
        "compiled": bool(predictor.compiled),
        "warm_up_s": float(warm_up_s),  # 0.0: timed cold (no warm-up)
        "vertices": int(len(scene.object.vertices)),
        "surface_vertices": int(len(scene.object.surface_vertices)),
        "edges": int(len(scene.object.edges)),
        "faces": int(len(scene.object.faces)),
        "load_average_1min": float(os.getloadavg()[0]),
    }


def format_bench(r: dict) -> str:
    """A readable table of one :func:`bench` result."""
    rows = [("total", r["total_ms"]), ("graph", r["graph_ms"]), ("gnn", r["gnn_ms"]),
            ("correction", r["correction_ms"]),
            ("self contact", r["self_contact_ms"]), ("IPC solver", r["ipc_ms"])]
    net = f" (network on {r['network_threads']})" if r.get("network_threads", r["threads"]) != r["threads"] else ""
    lines = [f"{r['scene']} ({r['resolution']}): {r['vertices']} vertices, {r['edges']} surface edges, "
             f"{r['faces']} faces; {r['frames'] - 1} steps, {r['threads']} "
             f"threads{net}{', compiled' if r.get('compiled') else ''}, load {r['load_average_1min']:.1f}",
             f"{'stage':<12}{'median ms':>11}{'p95 ms':>10}"]
    lines += [f"{name:<12}{s['median']:>11.2f}{s['p95']:>10.2f}" for name, s in rows]
    e = r["rollout_rmse"]
    lines.append(f"speedup vs IPC: {r['speedup_vs_ipc']:.0f}x   rollout RMSE (fraction of bbox diagonal): "
                 f"step 1 {e['step_1']:.2e}, step 10 {e['step_10']:.2e}, all {e['all']:.2e}")
    lines.append(f"crossings before/after correction: {r['crossings_before_correction']}/"
                 f"{r['crossings_after_correction']}, fallbacks {r['fallbacks']}")
    if r.get("kernel_threads_reduced_steps"):
        lines.append(f"busy machine: the collision kernels ran on 1 thread in {r['kernel_threads_reduced_steps']} "
                     f"steps (tasks waited for a CPU); these timings are not the free machine's")
    return "\n".join(lines)
