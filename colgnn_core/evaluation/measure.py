"""Where each number of the evaluation is measured: the statistics and data selections every report shares.

* :func:`stats`: median and p95 (ms per step everywhere: speed, solver, frontier, stability, the ROS node);
* :func:`relative_displacement_error`: ||X - X_gt|| / ||X_gt - X_rest|| over frames 1.. and the vertices (all, or
  the :func:`contact_region`): 1.0 is no better than "nothing moves" (the primary accuracy figure);
* :func:`rmse_fraction`: position RMSE per frame as a fraction of the object's rest bounding-box diagonal (secondary:
  it hides a model that never moves, because most vertices barely move);
* :func:`mean_std`: mean ± std over test sequences;
* :func:`collision_aggregate`: crossings and penetrations pooled over sequences
  (:func:`colgnn_core.collision.metrics.sequence_metrics` per sequence);
* :func:`test_files`: a dataset folder's checked held-out test sequences;
* :func:`family_poses`: the held-out test trajectories of a scene's family (what ``bench`` and ``stability`` run);
* :func:`finite`: every number of a JSON-like report finite.

The definitions are those of docs/ARCHITECTURE.md, "Metrics".
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from colgnn_core.collision.metrics import PENETRATION_KEYS
from colgnn_core.errors import InputError
from colgnn_core.learn.data import check_manifest, dataset_files, read_manifest
from colgnn_core.scenes.trajectories import sample_pressing_poses, split_seeds


def stats(values, empty: float | None = None) -> dict[str, float]:
    """Median and p95 of ``values`` ({'median', 'p95'}); with no values both are ``empty`` (when given)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0 and empty is not None:
        return {"median": float(empty), "p95": float(empty)}
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95))}


CONTACT_FRACTION = 0.1  # the contact region: this fraction of the vertices, those the ground truth moves most


def contact_region(truth: np.ndarray, rest: np.ndarray, fraction: float = CONTACT_FRACTION) -> np.ndarray:
    """Vertex ids [K] (K = round(fraction * N), at least 1) that the ground truth ``truth`` [T,N,3] moves farthest
    from ``rest`` [N,3] at any frame, ascending by that distance."""
    if not 0 < fraction <= 1:
        raise InputError(f"fraction must be in (0, 1], got {fraction}")
    d = np.linalg.norm(np.asarray(truth) - np.asarray(rest)[None], axis=2).max(axis=0)
    k = max(1, int(round(fraction * d.shape[0])))
    return np.argsort(d, kind="stable")[-k:]


def relative_displacement_error(pred: np.ndarray, truth: np.ndarray, rest: np.ndarray,
                                vertices: np.ndarray | None = None) -> float:
    """``||pred - truth|| / ||truth - rest||`` (Frobenius norms over frames 1..T-1 and ``vertices``, default all).

    pred, truth: [T,N,3] m; rest: [N,3] the state at frame 0 (the settled rest the ground truth starts from).
    0 is exact, 1.0 is what predicting "nothing moves" scores; inf when the ground truth does not move at all.
    """
    pred, truth, rest = np.asarray(pred), np.asarray(truth), np.asarray(rest)
    if pred.shape != truth.shape or truth.shape[1:] != rest.shape:
        raise InputError(f"shapes differ: pred {pred.shape}, truth {truth.shape}, rest {rest.shape}")
    if vertices is not None:
        pred, truth, rest = pred[:, vertices], truth[:, vertices], rest[vertices]
    num = float(np.sqrt(((pred[1:] - truth[1:]) ** 2).sum()))
    den = float(np.sqrt(((truth[1:] - rest[None]) ** 2).sum()))
    return num / den if den > 0 else (0.0 if num == 0 else math.inf)


def relative_errors(pred: np.ndarray, truth: np.ndarray, contact: np.ndarray | None = None) -> dict[str, float]:
    """{'all', 'contact'}: :func:`relative_displacement_error` of ``pred`` against ``truth`` [T,N,3] from the
    truth's frame 0, over every vertex and over ``contact`` (default :func:`contact_region` of the truth)."""
    truth = np.asarray(truth)
    rest = truth[0]
    ids = contact_region(truth, rest) if contact is None else contact
    return {"all": relative_displacement_error(pred, truth, rest),
            "contact": relative_displacement_error(pred, truth, rest, ids)}


def rmse_fraction(pred: np.ndarray, truth: np.ndarray, diagonal: float) -> np.ndarray:
    """Per-frame position RMSE [T] of ``pred`` vs ``truth`` [T,N,3], as a fraction of the bbox ``diagonal``."""
    return np.sqrt(((pred - truth) ** 2).sum(-1).mean(-1)) / diagonal


def mean_std(values) -> dict:
    """{'mean', 'std', 'n'} of ``values`` (None, None, 0 when there are none)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"mean": None, "std": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std()), "n": int(v.size)}


def collision_aggregate(per_seq: list[dict]) -> dict:
    """Pool per-sequence :func:`~colgnn_core.collision.metrics.sequence_metrics` results.

    N_* is crossings per step (all steps pooled), N_*_total their sum and N_*_max the most in one step;
    d_*_mean the mean depth over every crossing pair, d_*_max the largest; "intersecting frames" counts frames
    with any penetration (an object vertex inside the tool, a tool vertex inside the object, or intersecting
    triangles).
    """
    steps = sum(len(m["steps"]["N_vf"]) for m in per_seq)
    frames = sum(m["frames_count"] for m in per_seq)
    out: dict = {"steps": int(steps), "frames": int(frames)}
    for kind in ("vf", "ee"):
        n = np.concatenate([np.asarray(m["steps"][f"N_{kind}"], dtype=np.float64) for m in per_seq])
        d = np.concatenate([np.asarray(m["steps"][f"d_{kind}_mean"], dtype=np.float64) for m in per_seq])
        dmax = np.concatenate([np.asarray(m["steps"][f"d_{kind}_max"], dtype=np.float64) for m in per_seq])
        total = float(n.sum())
        out[f"N_{kind}"] = total / steps if steps else 0.0
        out[f"N_{kind}_total"] = int(total)
        out[f"N_{kind}_max"] = int(n.max()) if n.size else 0
        out[f"d_{kind}_mean"] = float((n * d).sum() / total) if total > 0 else 0.0
        out[f"d_{kind}_max"] = float(dmax.max()) if dmax.size else 0.0
    hit = np.concatenate([np.any([np.asarray(m["frames"][k]) > 0 for k in PENETRATION_KEYS], axis=0)
                          for m in per_seq])
    out["intersecting_frames"] = int(hit.sum())
    out["intersecting_frames_fraction"] = float(hit.mean()) if hit.size else 0.0
    for k in PENETRATION_KEYS:
        v = np.concatenate([np.asarray(m["frames"][k], dtype=np.float64) for m in per_seq])
        out[f"{k}_total"] = int(v.sum())
        out[f"{k}_max"] = int(v.max()) if v.size else 0
    return out


def test_files(data_dir, scene) -> list[Path]:
    """The ``test_XXXX.npz`` files of a dataset folder made for ``scene`` (InputError naming ``--data`` when
    there is no folder, or when its manifest is of another scene or resolution)."""
    if data_dir is None:
        raise InputError("no test data: pass --data DIR, a dataset folder made by `colgnn generate` "
                         "(datasets are not shipped)")
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise InputError(f"no such dataset folder (--data): {data_dir}")
    check_manifest(read_manifest(data_dir), scene, str(data_dir / "manifest.json"))
    return dataset_files(data_dir, "test")


def family_poses(scene, frames: int, index: int = 0) -> np.ndarray:
    """The ``index``-th held-out test trajectory of the scene's family, ``frames`` long [frames,7]; where the family's
    first stroke travels, from where it descends (:func:`~colgnn_core.scenes.trajectories.sample_pressing_poses`)."""
    return sample_pressing_poses(scene, split_seeds("test", index + 1)[index], frames)


def finite(obj) -> bool:
    """True when every number in a JSON-like structure is finite (None allowed)."""
    if isinstance(obj, dict):
        return all(finite(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(finite(v) for v in obj)
    if isinstance(obj, float):
        return math.isfinite(obj)
    return True
