"""Rigid poses: ``[px, py, pz, qx, qy, qz, qw]`` (metres, unit quaternion, ROS order)."""

from __future__ import annotations

import numpy as np

from colgnn_core.errors import InputError

QUAT_TOLERANCE = 1e-3
IDENTITY_POSE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


def validate_pose(pose: np.ndarray, tol: float = QUAT_TOLERANCE) -> np.ndarray:
    """Check a pose [7] and return a copy with a normalised quaternion.

    Raises :class:`InputError` for a wrong shape, NaN/inf, or a quaternion whose
    norm is off 1 by more than ``tol``.
    """
    pose = np.asarray(pose, dtype=np.float64).reshape(-1)
    if pose.shape != (7,):
        raise InputError(f"pose must have 7 values (px,py,pz,qx,qy,qz,qw), got {pose.size}")
    if not np.all(np.isfinite(pose)):
        raise InputError("pose contains NaN or inf")
    norm = float(np.linalg.norm(pose[3:]))
    if abs(norm - 1.0) > tol:
        raise InputError(f"quaternion is not unit length (|q| = {norm:.6g}, tolerance {tol:g})")
    out = pose.copy()
    out[3:] /= norm
    return out


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions [...,4] (xyzw) to rotation matrices [...,3,3]."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape == (4,):
        # One pose (the hot path of every step): Python floats are ~5x cheaper than 0-d arrays.
        x, y, z, w = (float(v) for v in q)
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def axis_angle_quat(axis: np.ndarray, angle: float) -> np.ndarray:
    """Quaternion [4] (xyzw) of a rotation by ``angle`` radians about ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([np.sin(angle / 2) * axis, [np.cos(angle / 2)]])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a⊗b of quaternions [...,4] (xyzw): rotate by b, then a."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Map tool-frame points [N,3] to world with ``pose`` [7]."""
    return np.asarray(points) @ quat_to_matrix(pose[3:]).T + pose[:3]


def inverse_transform_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Map world points [N,3] into the frame of ``pose`` [7]."""
    return (np.asarray(points) - pose[:3]) @ quat_to_matrix(pose[3:])


def interpolate_poses(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Poses [K,7] between ``a`` and ``b`` at fractions ``s`` [K] (lerp + slerp)."""
    s = np.asarray(s, dtype=np.float64).reshape(-1, 1)
    qa, qb = a[3:], b[3:].copy()
    dot = float(qa @ qb)
    if dot < 0:
        qb, dot = -qb, -dot
    if dot > 0.9995:
        q = qa + s * (qb - qa)
    else:
        theta = np.arccos(np.clip(dot, -1.0, 1.0))
        q = (np.sin((1 - s) * theta) * qa + np.sin(s * theta) * qb) / np.sin(theta)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([a[:3] + s * (b[:3] - a[:3]), q], axis=1)


def pose_path(a: np.ndarray, b: np.ndarray, stride: float) -> np.ndarray:
    """Poses [K,7] from ``a`` (excluded) to ``b`` (included), evenly spaced, positions at most ``stride`` m apart."""
    k = max(1, int(np.ceil(float(np.linalg.norm(b[:3] - a[:3])) / stride)))
    return interpolate_poses(a, b, np.arange(1, k + 1) / k)
