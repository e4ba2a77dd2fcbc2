"""``colgnn bench --collision``: collision detection timed against ipctk on one contact step.

The step is built from a scene's rest mesh (see :func:`contact_step`): the tool
moves along its stab direction, pressed into the object, whose surface wraps the
tool at a small gap as in a solver frame, plus prediction-like noise at t+1 so
that some primitives really cross. The same step is timed for

* ours: broad phase (SDF culling + swept boxes) + filter + narrow phase;
* ipctk's Tight-Inclusion CCD over the same broad-phase candidate pairs;
* ipctk's own full step check (``is_step_collision_free``: its broad phase + CCD).
"""

from __future__ import annotations

import os
import time

import numpy as np

from colgnn_core.collision.exact import ccd_edge_edge, ccd_vertex_face, is_step_collision_free
from colgnn_core.collision.pipeline import CollisionDetector, pair_points
from colgnn_core.errors import InputError
from colgnn_core.evaluation.measure import stats
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.io import load_sequence
from colgnn_core.scenes import load_scene

__all__ = ["contact_step", "step_from_sequence", "bench_collision", "format_bench_collision"]


def _first_contact(object_vertices: np.ndarray, surface_ids: np.ndarray, tool, pose0: np.ndarray,
                   direction: np.ndarray, max_travel: float) -> float:
    """Smallest travel s >= 0 along ``direction`` where a surface vertex reaches the tool's SDF zero."""
    P = object_vertices[surface_ids]

    def gap(s):
        pose = pose0.copy()
        pose[:3] = pose0[:3] + s * direction
        return float(np.min(tool.sdf(P, pose)))

    if gap(0.0) <= 0:
        return 0.0
    # March in 1 mm steps (the gap is not monotone once the tool passes the object), then bisect.
    grid = np.arange(0.0, max_travel, 1e-3)
    hit = next((s for s in grid if gap(s) <= 0), None)
    if hit is None:
        raise InputError("the tool never reaches the object along its stab direction")
    lo, hi = hit - 1e-3, hit
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(mid) > 0 else (lo, mid)
    return hi


def contact_step(object_vertices, object_faces, tool, tool_pose, *, press: float = 0.010, advance: float = 0.003,
                 follow: float = 0.5, sigma: float | None = None, gap: float = 1e-4, noise: float = 2e-4,
                 seed: int = 0):
    """A contact step t -> t+1 for a tool stabbing along its -z axis from ``tool_pose`` [7].

    The tool is ``press`` (t) and ``press + advance`` (t+1) metres past first contact. The
    object carries a Gaussian dent (``follow`` times the tool's depth, width ``sigma``,
    default the tool's bounding radius / 4), and the vertices the tool would still
    reach are pushed out along the SDF gradient to ``gap`` m from the tool, so the
    surface wraps the tool as in a solver frame. At t+1 the surface vertices within 5 mm of
    the tool get Gaussian noise of std ``noise`` m (seeded), like a learned prediction,
    so some primitives cross. Returns dict with object_t0, object_t1 [N,3], tool_t0,
    tool_t1 [M,3], tool_pose_t0, tool_pose_t1 [7] (m).
    """
    V = np.asarray(object_vertices, dtype=np.float64)
    F = np.asarray(object_faces, dtype=np.int64)
    pose = np.asarray(tool_pose, dtype=np.float64)
    R = quat_to_matrix(pose[3:])
    d = -R[:, 2]
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    S = np.unique(F)
    s_touch = _first_contact(V, S, tool, pose, d, 2.0 * diag)
    sigma = float(sigma if sigma is not None else 0.25 * tool.bounding_radius())
    rng = np.random.default_rng(seed)
    poses, objs = [], []
    for i, depth in enumerate((press, press + advance)):
        p = pose.copy()
        p[:3] = pose[:3] + (s_touch + depth) * d
        poses.append(p)
        rel = V - p[:3]
        radial = rel - np.outer(rel @ d, d)
        w = np.exp(-0.5 * (radial * radial).sum(1) / sigma**2)
        X = V + follow * depth * w[:, None] * d
        dist, grad = tool.sdf_grad(X, p)
        push = dist < gap
        X[push] += (gap - dist[push])[:, None] * grad[push]
        if i == 1 and noise > 0:
            near = S[dist[S] < 5e-3]
            X[near] += rng.normal(scale=noise, size=(len(near), 3))
        objs.append(X)
    return {
        "object_t0": objs[0], "object_t1": objs[1],
        "tool_t0": tool.world_vertices(poses[0]), "tool_t1": tool.world_vertices(poses[1]),
        "tool_pose_t0": poses[0], "tool_pose_t1": poses[1],
    }


def step_from_sequence(seq, tool, frame: int | None = None) -> tuple[dict, int]:
    """A step t -> t+1 of a sequence (e.g. solver ground truth) in :func:`contact_step`'s format.

    ``frame`` = t; None picks the step with the most broad-phase candidate pairs (the
    deepest contact). Returns (step, t).
    """
    seq.validate("sequence")
    if seq.frames < 2:
        raise InputError("the sequence needs at least 2 frames")
    if frame is None:
        det = CollisionDetector(seq.object_faces, seq.tool_faces, seq.object_positions.shape[1],
                                seq.tool_positions.shape[1], tool=tool)
        counts = [det.detect(seq.object_positions[t], seq.object_positions[t + 1], seq.tool_positions[t],
                             seq.tool_positions[t + 1], seq.tool_poses[t], seq.tool_poses[t + 1],
                             narrow=False).candidates.total() for t in range(seq.frames - 1)]
        frame = int(np.argmax(counts))
    if not 0 <= frame < seq.frames - 1:
        raise InputError(f"frame must be in [0, {seq.frames - 2}], got {frame}")
    t = frame
    return {
        "object_t0": seq.object_positions[t], "object_t1": seq.object_positions[t + 1],
        "tool_t0": seq.tool_positions[t], "tool_t1": seq.tool_positions[t + 1],
        "tool_pose_t0": seq.tool_poses[t], "tool_pose_t1": seq.tool_poses[t + 1],
        "object_faces": seq.object_faces, "tool_faces": seq.tool_faces,
    }, t


def _median_ms(fn, repeats: int) -> tuple[float, list[float], object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(1e3 * (time.perf_counter() - t))
    return stats(times)["median"], times, out


def bench_collision(scene_name: str = "cone_bunny", resolution: str = "full", *, repeats: int = 30,
                    exact_repeats: int = 3, press: float = 0.010, advance: float = 0.003, step=None,
                    scene=None, sequence=None, frame: int | None = None) -> dict:
    """Time the fast pipeline against ipctk on one contact step; returns a JSON-ready dict.

    The step: ``step`` (a dict as returned by :func:`contact_step`), else the deepest-contact
    step of ``sequence`` (a Sequence or a path; ``frame`` picks another), else a synthetic
    :func:`contact_step` of the scene. Keys: scene, resolution, step_source, threads, sizes (surface vertices,
    faces, edges, tool vertices), candidates / survivors / crossings per kind, culled_fraction (filter
    culls among broad-phase candidates), culled_fraction_of_noncolliding (the same among
    candidates ipctk finds contact-free), median ms for broad, filter_narrow (one fused kernel) and total
    (``ours_ms``), ipctk
    per-pair CCD over the same candidates (``ipctk_pairs_ms``) and ipctk's full step
    check (``ipctk_step_ms``), ``speedup_vs_ipctk_pairs``, and agreement of our
    crossings with ipctk's hits.
    """
    if scene is None:
        scene = load_scene(scene_name, resolution)
    tool = scene.tool
    source = "given step"
    if step is None and sequence is not None:
        seq = sequence if hasattr(sequence, "object_positions") else load_sequence(sequence)
        step, frame = step_from_sequence(seq, tool, frame)
        source = f"sequence frame {frame} -> {frame + 1}"
    elif step is None:
        source = f"synthetic contact step (press {press} m, advance {advance} m)"
        step = contact_step(scene.object.vertices, scene.object.faces, tool, scene.tool_rest_pose, press=press,
                            advance=advance)
    X = (step["object_t0"], step["object_t1"], step["tool_t0"], step["tool_t1"])
    poses = (step["tool_pose_t0"], step["tool_pose_t1"])
    object_faces = step["object_faces"] if "object_faces" in step else scene.object.faces
    tool_faces = step["tool_faces"] if "tool_faces" in step else tool.faces
    det = CollisionDetector(object_faces, tool_faces, len(X[0]), len(X[2]), tool=tool)
    det.detect(*X, *poses)  # warm-up
    timings = {k: [] for k in ("broad", "filter_narrow", "total")}
    cpu_ms = []
    res = None
    for _ in range(repeats):
        c0 = time.thread_time()
        res = det.detect(*X, *poses, check=False)
        # CPU time of this thread: what the wall time would be without other processes on the cores.
        cpu_ms.append(1e3 * (time.thread_time() - c0))
        for k in timings:
            timings[k].append(res.timings_ms[k])
    cand, surv = res.candidates, res.survivors
    surf = (det.object_surface, det.tool_surface)

    def ipctk_pairs():
        hits = {}
        for kind in ("vf", "fv", "ee"):
            pts = pair_points(kind, getattr(cand, kind), *X, *surf)
            fn = ccd_edge_edge if kind == "ee" else ccd_vertex_face
            hits[kind] = fn(*pts)[0] if len(pts[0]) else np.zeros(0, bool)
        return hits

    ipctk_ms, _, hits = _median_ms(ipctk_pairs, exact_repeats)
    step_ms, _, free = _median_ms(
        lambda: is_step_collision_free(X[0], X[1], object_faces, X[2], X[3], tool_faces), exact_repeats)

    # Agreement: every ipctk hit must be among our survivors (conservative filter).
    missed = 0
    ours_hits = 0
    agree = 0
    for kind in ("vf", "fv", "ee"):
        pairs = getattr(cand, kind)
        key = pairs[:, 0] * (1 << 32) + pairs[:, 1]
        skey = getattr(surv, kind)
        skey = skey[:, 0] * (1 << 32) + skey[:, 1]
        ipc_hit_keys = key[hits[kind]]
        missed += int((~np.isin(ipc_hit_keys, skey)).sum())
        our = getattr(res, kind).hit
        ours_hits += int(our.sum())
        agree += int(np.isin(skey[our], ipc_hit_keys).sum())
    n_c, n_s = cand.total(), surv.total()
    n_hits = sum(int(h.sum()) for h in hits.values())
    med = {k: stats(v)["median"] for k, v in timings.items()}
    So = det.object_surface
    return {
        "scene": getattr(scene, "name", scene_name), "resolution": getattr(scene, "resolution", resolution),
        "step_source": source,
        "threads": os.environ.get("OMP_NUM_THREADS"), "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "surface_vertices": int(len(So.vertices)), "surface_faces": int(len(So.faces)),
        "surface_edges": int(len(So.edges)), "tool_vertices": int(len(X[2])),
        "tool_faces": int(len(tool_faces)),
        "candidates": cand.counts(), "survivors": surv.counts(),
        "crossings": {k: int(getattr(res, k).hit.sum()) for k in ("vf", "fv", "ee")},
        "ipctk_hits": {k: int(hits[k].sum()) for k in ("vf", "fv", "ee")},
        "ipctk_hits_culled_by_filter": missed,
        "our_crossings_confirmed_by_ipctk": agree, "our_crossings": ours_hits,
        "ipctk_step_collision_free": bool(free),
        "culled_fraction": (1.0 - n_s / n_c) if n_c else None,
        "culled_fraction_of_noncolliding": ((n_c - n_s) / (n_c - n_hits)) if n_c > n_hits else None,
        "broad_ms": med["broad"], "filter_narrow_ms": med["filter_narrow"], "ours_ms": med["total"],
        "ours_ms_sum_of_stage_medians": med["broad"] + med["filter_narrow"],
        "ours_cpu_ms": stats(cpu_ms)["median"],
        "ours_ms_p95": stats(timings["total"])["p95"],
        "ipctk_pairs_ms": ipctk_ms, "ipctk_step_ms": step_ms,
        "speedup_vs_ipctk_pairs": ipctk_ms / med["total"] if med["total"] > 0 else None,
        # Like for like: the same candidate pairs in, the same question out (does it collide?).
        "speedup_filter_narrow_vs_ipctk_pairs": ipctk_ms / med["filter_narrow"] if med["filter_narrow"] > 0 else None,
        "ours_ms_min": float(np.min(timings["total"])),
        "speedup_vs_ipctk_step": step_ms / med["total"] if med["total"] > 0 else None,
        "repeats": repeats,
    }


def format_bench_collision(r: dict) -> str:
    """A readable table of a :func:`bench_collision` result."""
    def kinds(d):
        return " / ".join(f"{d[k]}" for k in ("vf", "fv", "ee"))

    rows = [
        ("step", r["step_source"]),
        ("object surface (V/F/E), tool (V/F)", f"{r['surface_vertices']}/{r['surface_faces']}/{r['surface_edges']}, "
                                               f"{r['tool_vertices']}/{r['tool_faces']}"),
        ("candidates vf / fv / ee", kinds(r["candidates"])),
        ("kept by the filter", kinds(r["survivors"])),
        ("crossings (ours / ipctk)", f"{kinds(r['crossings'])}  /  {kinds(r['ipctk_hits'])}"),
        ("ipctk hits culled by the filter", str(r["ipctk_hits_culled_by_filter"])),
        ("culled (of all / of non-colliding)", f"{100 * (r['culled_fraction'] or 0):.1f}% / "
                                                f"{100 * (r['culled_fraction_of_noncolliding'] or 0):.1f}%"),
        ("broad phase ms (median)", f"{r['broad_ms']:.3f}"),
        ("filter + narrow ms (median)", f"{r['filter_narrow_ms']:.3f}"),
        ("ours total ms (median / p95)", f"{r['ours_ms']:.3f} / {r['ours_ms_p95']:.3f}"),
        ("ipctk CCD, same pairs ms", f"{r['ipctk_pairs_ms']:.3f}"),
        ("ipctk full step check ms", f"{r['ipctk_step_ms']:.3f}"),
        ("speed-up vs ipctk same pairs", f"{r['speedup_vs_ipctk_pairs']:.1f}x"),
        ("speed-up vs ipctk full step", f"{r['speedup_vs_ipctk_step']:.1f}x"),
    ]
    w = max(len(k) for k, _ in rows)
    head = (f"collision benchmark: {r['scene']} ({r['resolution']}), {r['repeats']} repeats, "
            f"load {r['load_average_1min']:.2f}")
    return "\n".join([head] + [f"  {k.ljust(w)}  {v}" for k, v in rows])
