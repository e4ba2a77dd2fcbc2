"""Collision metrics (docs/ARCHITECTURE.md, "Metrics"): crossings per step, penetrations per frame.

* Crossings over [t, t+1] (the paper's Table 2). Object and tool vertices move
  linearly between frames. A vertex-face pair (object vertex vs tool face, or tool
  vertex vs object face) or an edge-edge pair (object edge vs tool edge) counts
  when exact CCD reports contact: the broad phase and the conservative filter
  (which never drop a colliding pair) pick the pairs, ipctk's Tight-Inclusion CCD
  decides (``exact=False`` uses our narrow phase instead). N_vf, N_ee count them;
  d_vf, d_ee are their depths on the wrong side at t+1 (mean and max, m; 0 when
  there is none).
* Penetration at frame t: object vertices inside the tool, tool vertices inside
  the object, and object-tool triangle pairs that intersect. "Inside the tool" is
  tested against the tool *mesh* (winding number), the surface the solver keeps
  the object off; pass ``tool`` to use the analytic SDF < 0 instead (which also
  counts vertices in the thin gap between an inscribed mesh and the ideal shape).

Bad input (empty meshes, NaN, mismatched shapes) raises InputError.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from colgnn_core.collision import exact as _exact
from colgnn_core.collision.broad_phase import CandidatePairs, Surface, box_pairs
from colgnn_core.collision.narrow_phase import depth_quads
from colgnn_core.collision.pipeline import CollisionDetector, pair_points, pair_quads, stacked_positions
from colgnn_core.errors import InputError
from colgnn_core.io import Sequence, load_sequence

__all__ = [
    "CROSSING_KEYS",
    "PENETRATION_KEYS",
    "step_crossings",
    "frame_penetrations",
    "triangle_pairs_intersecting",
    "sequence_metrics",
    "file_metrics",
    "pair_metrics",
]

CROSSING_KEYS = ("N_vf", "d_vf_mean", "d_vf_max", "N_ee", "d_ee_mean", "d_ee_max")
PENETRATION_KEYS = ("object_vertices_inside", "tool_vertices_inside", "intersecting_triangle_pairs")


def _positions(X, name: str, n: int | None = None) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] == 0:
        raise InputError(f"{name} must be a non-empty [N,3] array, got shape {X.shape}")
    if n is not None and X.shape[0] != n:
        raise InputError(f"{name} has {X.shape[0]} vertices, expected {n}")
    if not np.all(np.isfinite(X)):
        raise InputError(f"{name} contains NaN or inf")
    return X


def _detector(object_faces, tool_faces, n_obj, n_tool, detector):
    if detector is not None:
        if detector.object_surface.n_vertices != n_obj or detector.tool_surface.n_vertices != n_tool:
            raise InputError("detector was built for meshes of a different size")
        return detector
    return CollisionDetector(object_faces, tool_faces, n_obj, n_tool)


def step_crossings(object_t0, object_t1, object_faces, tool_t0, tool_t1, tool_faces, *,
                   detector: CollisionDetector | None = None, exact: bool = True,
                   tool_pose_t0=None, tool_pose_t1=None) -> dict:
    """Crossing metrics for the linear motion t -> t+1. Positions [N,3], [M,3] in m.

    Returns {N_vf, d_vf_mean, d_vf_max, N_ee, d_ee_mean, d_ee_max}. ``detector`` can be
    reused across steps (it caches the topology); poses enable its SDF culling.
    """
    object_t0 = _positions(object_t0, "object_t0")
    object_t1 = _positions(object_t1, "object_t1", len(object_t0))
    tool_t0 = _positions(tool_t0, "tool_t0")
    tool_t1 = _positions(tool_t1, "tool_t1", len(tool_t0))
    det = _detector(object_faces, tool_faces, len(object_t0), len(tool_t0), detector)
    res = det.detect(object_t0, object_t1, tool_t0, tool_t1, tool_pose_t0, tool_pose_t1, narrow=not exact)
    if not exact:
        return res.summary()
    X = (object_t0, object_t1, tool_t0, tool_t1)
    surf = (det.object_surface, det.tool_surface)
    X0, X1 = stacked_positions(object_t0, tool_t0), stacked_positions(object_t1, tool_t1)
    depths = {}
    for kind in ("vf", "fv", "ee"):
        pairs = getattr(res.survivors, kind)
        hit = np.zeros(0, bool)
        if len(pairs):
            ccd = _exact.ccd_edge_edge if kind == "ee" else _exact.ccd_vertex_face
            hit, _ = ccd(*pair_points(kind, pairs, *X, *surf))
        crossing = CandidatePairs()
        setattr(crossing, kind, pairs[hit] if len(pairs) else pairs)
        quads, is_ee = pair_quads(crossing, *surf)
        depths[kind] = depth_quads(X0, X1, quads, is_ee)
    dvf = np.concatenate([depths["vf"], depths["fv"]])
    dee = depths["ee"]
    return {
        "N_vf": int(len(dvf)), "d_vf_mean": float(dvf.mean()) if len(dvf) else 0.0,
        "d_vf_max": float(dvf.max()) if len(dvf) else 0.0,
        "N_ee": int(len(dee)), "d_ee_mean": float(dee.mean()) if len(dee) else 0.0,
        "d_ee_max": float(dee.max()) if len(dee) else 0.0,
    }


def _orient(p, q, r, s):
    return np.einsum("ki,ki->k", np.cross(q - p, r - p), s - p)


def _segment_hits_triangle(q0, q1, a, b, c) -> np.ndarray:
    """[K] bool: closed segment q0q1 meets triangle abc (non-coplanar cases; touching counts)."""
    s0, s1 = _orient(a, b, c, q0), _orient(a, b, c, q1)
    straddle = (s0 * s1 <= 0) & ~((s0 == 0) & (s1 == 0))
    t1, t2, t3 = _orient(q0, q1, a, b), _orient(q0, q1, b, c), _orient(q0, q1, c, a)
    same = ((t1 >= 0) & (t2 >= 0) & (t3 >= 0)) | ((t1 <= 0) & (t2 <= 0) & (t3 <= 0))
    return straddle & same


def triangle_pairs_intersecting(object_V, object_faces, tool_V, tool_faces) -> np.ndarray:
    """Object-tool triangle pairs [K,2] (object face, tool face) that intersect at one frame.

    Two non-coplanar triangles intersect iff an edge of one meets the other. Exactly
    coplanar overlapping triangles are not counted (measure-zero for real data).
    """
    object_V = _positions(object_V, "object vertices")
    tool_V = _positions(tool_V, "tool vertices")
    Fo = Surface.from_faces(object_faces, len(object_V), "object").faces
    Ft = Surface.from_faces(tool_faces, len(tool_V), "tool").faces
    To, Tt = object_V[Fo], tool_V[Ft]
    pairs = box_pairs(To.min(1), To.max(1), Tt.min(1), Tt.max(1))
    if len(pairs) == 0:
        return pairs
    A, B = To[pairs[:, 0]], Tt[pairs[:, 1]]
    hit = np.zeros(len(pairs), dtype=bool)
    for X, Y in ((A, B), (B, A)):
        for i, j in ((0, 1), (1, 2), (2, 0)):
            hit |= _segment_hits_triangle(X[:, i], X[:, j], Y[:, 0], Y[:, 1], Y[:, 2])
    return pairs[hit]


def frame_penetrations(object_V, object_faces, tool_V, tool_faces, *, tool=None, tool_pose=None) -> dict:
    """Penetration counts at one frame: {object_vertices_inside, tool_vertices_inside,
    intersecting_triangle_pairs}. All object vertices (surface and interior) are tested."""
    object_V = _positions(object_V, "object vertices")
    tool_V = _positions(tool_V, "tool vertices")
    So = Surface.from_faces(object_faces, len(object_V), "object")
    St = Surface.from_faces(tool_faces, len(tool_V), "tool")
    if tool is not None:
        if tool_pose is None:
            raise InputError("tool_pose is needed with tool")
        obj_in = int(np.count_nonzero(np.asarray(tool.sdf(object_V, tool_pose)) < 0))
    else:
        obj_in = int(np.count_nonzero(_exact.points_inside_mesh(tool_V, St.faces, object_V)))
    tool_in = int(np.count_nonzero(_exact.points_inside_mesh(object_V, So.faces, tool_V)))
    tri = len(triangle_pairs_intersecting(object_V, So.faces, tool_V, St.faces))
    return {"object_vertices_inside": obj_in, "tool_vertices_inside": tool_in, "intersecting_triangle_pairs": tri}


def _summ(values: list[float], kind: str) -> float:
    if not values:
        return 0.0
    return float(np.max(values)) if kind == "max" else float(np.mean(values))


def _pooled(parts: list[dict]) -> dict:
    """:func:`step_crossings` results of the pieces of one motion, as one: counts summed, mean depths weighted by
    the counts, max depths the largest."""
    out = {}
    for kind in ("vf", "ee"):
        n = sum(p[f"N_{kind}"] for p in parts)
        out[f"N_{kind}"] = int(n)
        out[f"d_{kind}_mean"] = float(sum(p[f"N_{kind}"] * p[f"d_{kind}_mean"] for p in parts) / n) if n else 0.0
        out[f"d_{kind}_max"] = float(max(p[f"d_{kind}_max"] for p in parts))
    return out


def sequence_metrics(seq: Sequence, *, exact: bool = True, tool=None) -> dict:
    """All collision metrics of one sequence/rollout.

    The crossings of step t -> t+1 are those of its motion (:meth:`colgnn_core.io.Sequence.motion`): the straight
    motion, or the recorded piecewise-linear path of a ground-truth frame whose straight motion is not
    collision-free (summed over the pieces).

    Returns {'steps': {key: [T-1] list} for CROSSING_KEYS, 'frames': {key: [T] list} for
    PENETRATION_KEYS, 'summary': {...}}. The summary holds, per key, the mean over steps /
    frames (``d_*_max``: the maximum), plus '<count>_max' and '<count>_total' for the
    counts, and 'd_vf_pooled_mean' / 'd_ee_pooled_mean': the mean depth over all crossing
    pairs of the sequence.
    ``tool`` (a Tool) switches object-inside-tool to the analytic SDF and enables SDF
    culling in the crossing broad phase (with seq.tool_poses).
    """
    seq.validate("sequence")
    T = seq.frames
    det = CollisionDetector(seq.object_faces, seq.tool_faces, seq.object_positions.shape[1],
                            seq.tool_positions.shape[1], tool=tool)
    steps = {k: [] for k in CROSSING_KEYS}
    for t in range(T - 1):
        states = seq.motion(t + 1)
        if len(states) == 2:
            poses = (seq.tool_poses[t], seq.tool_poses[t + 1]) if tool is not None else (None, None)
            r = step_crossings(seq.object_positions[t], seq.object_positions[t + 1], seq.object_faces,
                               seq.tool_positions[t], seq.tool_positions[t + 1], seq.tool_faces, detector=det,
                               exact=exact, tool_pose_t0=poses[0], tool_pose_t1=poses[1])
        else:  # a recorded path (ground truth): crossings of every piece; its tool states have no pose to cull by
            r = _pooled([step_crossings(a[0], b[0], seq.object_faces, a[1], b[1], seq.tool_faces, detector=det,
                                        exact=exact) for a, b in zip(states[:-1], states[1:])])
        for k in CROSSING_KEYS:
            steps[k].append(r[k])
    frames = {k: [] for k in PENETRATION_KEYS}
    for t in range(T):
        r = frame_penetrations(seq.object_positions[t], seq.object_faces, seq.tool_positions[t], seq.tool_faces,
                               tool=tool, tool_pose=seq.tool_poses[t] if tool is not None else None)
        for k in PENETRATION_KEYS:
            frames[k].append(r[k])
    summary = {}
    for k, v in list(steps.items()) + list(frames.items()):
        summary[k] = _summ(v, "max" if k.endswith("_max") else "mean")
        if not k.endswith("_max") and not k.endswith("_mean"):
            summary[f"{k}_max"] = _summ(v, "max")
            summary[f"{k}_total"] = float(np.sum(v)) if v else 0.0
    for kind in ("vf", "ee"):
        n = np.asarray(steps[f"N_{kind}"], dtype=np.float64)
        d = np.asarray(steps[f"d_{kind}_mean"], dtype=np.float64)
        # Mean depth over every crossing pair of the sequence (steps weighted by their counts).
        summary[f"d_{kind}_pooled_mean"] = float((n * d).sum() / n.sum()) if n.sum() > 0 else 0.0
    return {"steps": steps, "frames": frames, "summary": summary, "frames_count": T}


def file_metrics(path: str | os.PathLike, *, exact: bool = True, tool=None) -> dict:
    """:func:`sequence_metrics` of a sequence/rollout ``.npz`` (read with colgnn_core.io.load_sequence)."""
    out = sequence_metrics(load_sequence(path), exact=exact, tool=tool)
    out["path"] = str(Path(path))
    return out


def pair_metrics(ground_truth_path, rollout_path, *, exact: bool = True, tool=None) -> dict:
    """Metrics of a ground-truth sequence and a rollout of the same scene: {'ground_truth', 'rollout'}.

    The two files must share the object and tool topology (InputError otherwise).
    """
    a, b = load_sequence(ground_truth_path), load_sequence(rollout_path)
    if a.object_faces.shape != b.object_faces.shape or not np.array_equal(a.object_faces, b.object_faces):
        raise InputError(f"{ground_truth_path} and {rollout_path} have different object meshes")
    if a.tool_faces.shape != b.tool_faces.shape or not np.array_equal(a.tool_faces, b.tool_faces):
        raise InputError(f"{ground_truth_path} and {rollout_path} have different tool meshes")
    out = {"ground_truth": sequence_metrics(a, exact=exact, tool=tool),
           "rollout": sequence_metrics(b, exact=exact, tool=tool)}
    out["ground_truth"]["path"] = str(ground_truth_path)
    out["rollout"]["path"] = str(rollout_path)
    return out
