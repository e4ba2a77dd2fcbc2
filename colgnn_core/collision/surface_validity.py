"""A valid surface: no triangle flipped, collapsed or torn relative to the rest shape.

A surface triangle is *invalid* in positions X ([N,3], m) when, compared with the same triangle in the rest shape
(the settled rest the Predictor starts from):

* **flipped**: its normal points away from its rest normal, (Q n(X)) . n(rest) <= 0, with Q the rotation of the best
  rigid alignment of X's surface to the rest (Kabsch): the frame the object rests in, whatever it rolls to (the
  ground-truth banana rolls under the cylinder, turning faces by more than 90 degrees in the world frame);
* **collapsed**: its area is below ``MIN_AREA_RATIO`` x its rest area (a degenerate triangle has no normal, so it
  cannot be called unflipped);
* **torn**: one of its edges is longer than ``MAX_STRETCH`` x its rest length.

The bounds never trigger on physical shapes. The IPC ground truth was measured against each sequence's first frame
(``ci``, 40 frames a sequence: cone_bunny 5 sequences, the other scenes 4): largest stretch 1.26, smallest area ratio
0.86, smallest normal cosine after alignment 0.77 (0.29 below zero *without* the alignment: the rolling banana); the
full-resolution cone_bunny contact frame of the tests: stretch 1.44, area ratio 0.83, cosine 0.94.
``MAX_STRETCH`` = 3 is twice the largest stretch seen, ``MIN_AREA_RATIO`` = 0.1 an eighth of the smallest area ratio.

The predicted shape is not always physical: the issue measured edges stretched 18x and 140 flipped faces. The
self-contact stage (:mod:`.self_contact`) repairs such triangles and counts them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from colgnn_core.errors import InputError

__all__ = ["MAX_STRETCH", "MIN_AREA_RATIO", "SurfaceValidity", "ValidityCounts", "best_rotation", "rigid_fit",
           "rigid_fit_rows"]

MAX_STRETCH = 3.0      # longest allowed edge / rest length (ground truth: at most 1.44)
MIN_AREA_RATIO = 0.1   # smallest allowed area / rest area (ground truth: at least 0.83)
FLIPPED, COLLAPSED, TORN = 1, 2, 4  # bits of the per-face code


@dataclass(frozen=True)
class ValidityCounts:
    """Invalid triangles by kind (a triangle can be in more than one); ``invalid``: triangles with any defect."""

    invalid: int = 0
    flipped: int = 0
    collapsed: int = 0
    torn: int = 0


@njit(cache=True)
def _cross_covariance(X, x_ids, rest, rest_ids):
    """(sum_k (X_i - mean X)(rest_j - mean rest)^T [3,3], mean X [3], mean rest [3]) over the rows i = x_ids[k] of X
    and j = rest_ids[k] of rest (one pass, no copies: the alignment runs on every check of a step)."""
    n = x_ids.shape[0]
    sx = np.zeros(3)
    sr = np.zeros(3)
    sxr = np.zeros((3, 3))
    for k in range(n):
        i, j = x_ids[k], rest_ids[k]
        for a in range(3):
            sx[a] += X[i, a]
            sr[a] += rest[j, a]
            for b in range(3):
                sxr[a, b] += X[i, a] * rest[j, b]
    for a in range(3):
        for b in range(3):
            sxr[a, b] -= sx[a] * sr[b] / n
    return sxr, sx / n, sr / n


@njit(cache=True)
def _kabsch(A):
    """Q [3,3]: the rotation maximising trace(Q A) for a cross-covariance A = sum (x - mx)(r - mr)^T. In numba: a
    NumPy SVD call costs ~25 us of dispatch, and the self-contact stage aligns up to five times a check."""
    U, _, Vt = np.linalg.svd(A)
    if np.linalg.det(U @ Vt) < 0.0:
        U[:, 2] = -U[:, 2]  # U diag(1, 1, -1): the nearest rotation, not a reflection
    return np.ascontiguousarray((U @ Vt).T)


@njit(cache=True)
def rigid_fit_rows(X, x_ids, rest, rest_ids):
    """(R [3,3], p [3] m): the best rigid motion (least squares) carrying the rows ``rest_ids`` [K] of rest onto
    the rows ``x_ids`` [K] of X: X[x_ids] ~ rest[rest_ids] @ R.T + p (numba-callable)."""
    A, mx, mr = _cross_covariance(X, x_ids, rest, rest_ids)
    R = np.ascontiguousarray(_kabsch(A).T)
    return R, mx - R @ mr


def best_rotation(X: np.ndarray, rest: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
    """Q [3,3]: the rotation of the best rigid alignment (least squares, Kabsch) of points X[ids] [K,3] (default:
    all rows of X) onto rest [K,3]."""
    X = np.ascontiguousarray(X, dtype=np.float64)
    ids = np.arange(len(X)) if ids is None else np.ascontiguousarray(ids, dtype=np.int64)
    rest = np.ascontiguousarray(rest, dtype=np.float64)
    return _kabsch(_cross_covariance(X, ids, rest, np.arange(len(rest)))[0])


def rigid_fit(X: np.ndarray, rest: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R [3,3], p [3] m): the best rigid motion (least squares) carrying rest [K,3] onto X[ids] [K,3]:
    X[ids] ~ rest @ R.T + p."""
    rest = np.ascontiguousarray(rest, dtype=np.float64)
    return rigid_fit_rows(np.ascontiguousarray(X, dtype=np.float64), np.ascontiguousarray(ids, dtype=np.int64), rest,
                          np.arange(len(rest)))


@njit(cache=True, parallel=True)
def _face_codes(X, Q, faces, rest_normals, rest_lengths, max_stretch, min_area_ratio):
    """Per-face defect bits (FLIPPED | COLLAPSED | TORN) [F] int8 of positions X [N,3], Q [3,3] the alignment."""
    F = faces.shape[0]
    out = np.zeros(F, dtype=np.int8)
    for f in prange(F):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e0 = (X[b, 0] - X[a, 0], X[b, 1] - X[a, 1], X[b, 2] - X[a, 2])
        e1 = (X[c, 0] - X[a, 0], X[c, 1] - X[a, 1], X[c, 2] - X[a, 2])
        e2 = (X[c, 0] - X[b, 0], X[c, 1] - X[b, 1], X[c, 2] - X[b, 2])
        m0 = e0[1] * e1[2] - e0[2] * e1[1]
        m1 = e0[2] * e1[0] - e0[0] * e1[2]
        m2 = e0[0] * e1[1] - e0[1] * e1[0]
        n0 = Q[0, 0] * m0 + Q[0, 1] * m1 + Q[0, 2] * m2
        n1 = Q[1, 0] * m0 + Q[1, 1] * m1 + Q[1, 2] * m2
        n2 = Q[2, 0] * m0 + Q[2, 1] * m1 + Q[2, 2] * m2
        # rest_normals is the rest normal scaled to unit length / rest |n|, so dot = cos x area ratio.
        r0, r1, r2 = rest_normals[f, 0], rest_normals[f, 1], rest_normals[f, 2]
        code = 0
        if n0 * r0 + n1 * r1 + n2 * r2 <= 0.0:
            code |= FLIPPED
        area2 = n0 * n0 + n1 * n1 + n2 * n2
        rest2 = r0 * r0 + r1 * r1 + r2 * r2  # = 1 / |n_rest|^2
        if not area2 * rest2 >= min_area_ratio * min_area_ratio:
            code |= COLLAPSED
        l0 = e0[0] * e0[0] + e0[1] * e0[1] + e0[2] * e0[2]
        l1 = e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2]
        l2 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]
        s2 = max_stretch * max_stretch
        if not (l0 <= s2 * rest_lengths[f, 0] ** 2 and l1 <= s2 * rest_lengths[f, 1] ** 2
                and l2 <= s2 * rest_lengths[f, 2] ** 2):
            code |= TORN
        out[f] = code
    return out


class SurfaceValidity:
    """Validity of one surface against its rest shape (build once per scene).

    Args:
        faces: [F,3] triangles (outward) indexing position arrays of N rows.
        rest: [N,3] rest positions (m); every triangle must have a positive rest area.
        max_stretch, min_area_ratio: the bounds of the module docstring.
    """

    def __init__(self, faces: np.ndarray, rest: np.ndarray, *, max_stretch: float = MAX_STRETCH,
                 min_area_ratio: float = MIN_AREA_RATIO):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        rest = np.asarray(rest, dtype=np.float64)
        self.vertices = np.unique(self.faces)
        self.rest = rest[self.vertices]
        a, b, c = (rest[self.faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        area2 = (n * n).sum(1)
        if not np.all(area2 > 0):
            raise InputError(f"{int(np.sum(~(area2 > 0)))} rest triangles have no area")
        if not (max_stretch > 1 and 0 < min_area_ratio < 1):
            raise InputError(f"need max_stretch > 1 and 0 < min_area_ratio < 1, got {max_stretch}, {min_area_ratio}")
        # n / |n|^2: its dot with a current normal is cos x (current area / rest area).
        self.rest_normals = np.ascontiguousarray(n / area2[:, None])
        self.rest_lengths = np.ascontiguousarray(np.stack(
            [np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)], axis=1))
        self.max_stretch = float(max_stretch)
        self.min_area_ratio = float(min_area_ratio)

    def codes(self, X: np.ndarray) -> np.ndarray:
        """Per-face defect bits [F] int8 (FLIPPED=1, COLLAPSED=2, TORN=4; 0: valid) of positions X [N,3] (m)."""
        X = np.ascontiguousarray(X, dtype=np.float64)
        Q = best_rotation(X, self.rest, self.vertices)
        return _face_codes(X, Q, self.faces, self.rest_normals, self.rest_lengths, self.max_stretch,
                           self.min_area_ratio)

    def invalid(self, X: np.ndarray) -> np.ndarray:
        """Bool [F]: triangles flipped, collapsed or torn in X [N,3]."""
        return self.codes(X) != 0

    def counts(self, X: np.ndarray) -> ValidityCounts:
        """How many triangles of X [N,3] are invalid, by kind."""
        c = self.codes(X)
        return ValidityCounts(invalid=int(np.count_nonzero(c)), flipped=int(np.count_nonzero(c & FLIPPED)),
                              collapsed=int(np.count_nonzero(c & COLLAPSED)), torn=int(np.count_nonzero(c & TORN)))
