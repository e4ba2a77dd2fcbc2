"""The IPC solver's cost: ms per step and Newton iterations on a scene's trajectory, and from them an estimate of
the time to generate a dataset."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from colgnn_core.evaluation.measure import stats
from colgnn_core.sim.ipc import IPCSimulator


def mesh_counts(scene) -> dict[str, int]:
    """Object / tool vertex, edge and face counts (surface counts as in the paper's Table 1)."""
    obj, tool = scene.object, scene.tool
    return {
        "object_vertices": int(len(obj.vertices)),
        "object_surface_vertices": int(len(obj.surface_vertices)),
        "object_tets": int(len(obj.tets)),
        "object_edges": int(len(obj.edges)),
        "object_faces": int(len(obj.faces)),
        "tool_vertices": int(len(tool.vertices)),
        "tool_edges": int(len(tool.edges)),
        "tool_faces": int(len(tool.faces)),
    }


def bench_ipc(scene, poses: np.ndarray, progress: bool = False, **sim_options: Any) -> dict:
    """Simulate ``poses`` [T,7] with :class:`IPCSimulator` and summarise the cost per step.

    Returns a JSON-able dict: mesh counts, ``init_s`` (setup + settling), per-step ``ms`` and
    ``newton_iterations`` lists, their median / p95 / mean over all steps and over *contact*
    steps (object–tool distance below dmin + dhat at the end of the step).
    A SimulationError propagates (a benchmark of a failing solve is meaningless).
    """
    poses = scene.check_poses(poses)
    t0 = time.perf_counter()
    sim = IPCSimulator(scene, initial_tool_pose=poses[0], **sim_options)
    init_s = time.perf_counter() - t0
    ms, iters, contact = [], [], []
    steps = range(1, len(poses))
    if progress:
        from tqdm import tqdm  # lazy: an optional progress bar, only when asked for

        steps = tqdm(steps, desc=f"bench {scene.name}/{scene.resolution}", unit="step", leave=False)
    for k in steps:
        st = sim.step(poses[k])
        ms.append(st.ms)
        iters.append(st.newton_iterations)
        contact.append(sim.tool_distance() < sim.dmin + sim.dhat)
    ms_a, it_a, c_a = np.asarray(ms), np.asarray(iters), np.asarray(contact, dtype=bool)

    def summary(mask: np.ndarray) -> dict[str, float | int | None]:
        if not mask.any():
            return {"steps": 0, "ms_median": None, "ms_p95": None, "newton_mean": None, "newton_max": None}
        st = stats(ms_a[mask])
        return {
            "steps": int(mask.sum()),
            "ms_median": st["median"],
            "ms_p95": st["p95"],
            "newton_mean": float(it_a[mask].mean()),
            "newton_max": int(it_a[mask].max()),
        }

    return {
        "scene": scene.name,
        "resolution": scene.resolution,
        **mesh_counts(scene),
        "dt": float(scene.dt),
        "dhat": sim.dhat,
        "dmin": sim.dmin,
        "init_s": init_s,
        "all": summary(np.ones(len(ms_a), dtype=bool)),
        "contact": summary(c_a),
        "ms": [float(v) for v in ms_a],
        "newton_iterations": [int(v) for v in it_a],
    }


def estimate_generation_s(result: dict, train: int = 20, test: int = 5, frames: int = 40,
                          contact_fraction: float | None = None) -> float:
    """Single-core seconds to simulate ``train + test`` sequences of ``frames`` frames, from a bench result.

    Uses the contact and free-motion medians weighted by ``contact_fraction`` (default: the
    fraction of contact steps seen in the benchmark) plus the per-sequence setup time.
    """
    c, a = result["contact"], result["all"]
    frac = (c["steps"] / max(a["steps"], 1)) if contact_fraction is None else float(contact_fraction)
    ms_contact = c["ms_median"] if c["ms_median"] is not None else a["ms_median"]
    ms_mean = np.mean(result["ms"]) if result["ms"] else 0.0
    # Medians undercount heavy-tailed Newton counts; take the larger of the mixed median and the mean.
    per_step = max(frac * ms_contact + (1 - frac) * a["ms_median"], ms_mean) / 1e3
    return float((train + test) * ((frames - 1) * per_step + result["init_s"]))
