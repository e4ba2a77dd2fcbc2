"""Hard tool trajectories: motions at the edge of what the Predictor accepts, for every consumer of a trajectory.

The ground-truth solver must simulate them (``colgnn generate --poses``) and the Predictor must keep its guarantee
on them (no intersecting frame, no crossing step), so both test suites and the results report build them here.

Every trajectory is an array of poses [T,7] whose frame 0 is the scene's rest pose, inside the workspace. ``step``
is the tool motion of one model step the caller allows (the Predictor's per-step limit, ``tool_step_limits``);
ordinary moves advance ``pace`` x step per frame, fast ones ``jump`` x step (a Predictor splits those into model
steps). Depths are fractions of the way from the surface (where the tool first touches the rest object) down to the
*deepest valid pose*: the tool above the same point at the workspace floor.

* ``fast plunge``: straight down to the deepest valid pose at ``jump`` x step per frame, one frame held, back up.
* ``press and drag``: down to ``depth``, a drag across the object by ``drag`` x its extent each way (along the
  tool's x axis: the knife cuts) and back to the middle, then up.
* ``tilted slice``: the tool tilted by the family's largest tilt about the axis across the slice, down to
  ``depth``, back and forth along the slice, up.
* ``jitter``: down to ``depth`` and held, with uniform noise of ``noise`` m on every coordinate of every pose.
* ``release and settle``: down to ``depth``, back to the rest pose at ``jump`` x step per frame, then ``settle``
  frames held there while the object comes back to rest.
"""

from __future__ import annotations

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import axis_angle_quat, interpolate_poses, quat_multiply, quat_to_matrix
from colgnn_core.scenes.scene import Scene
from colgnn_core.scenes.trajectories import contact_height

HARD_KINDS = ("fast plunge", "press and drag", "tilted slice", "jitter", "release and settle")
DEFAULT_TILT_DEG = 20.0  # the tilt of the slice for families without tilts


def deepest_pose(scene: Scene, xy=None, quat=None) -> np.ndarray:
    """The pose [7] above ``xy`` (default: the scene's target) with orientation ``quat`` (default: rest) at the
    workspace floor: the deepest tool pose the Predictor accepts there."""
    xy = np.asarray(scene.target[:2] if xy is None else xy, dtype=np.float64)
    quat = np.asarray(scene.tool_rest_pose[3:] if quat is None else quat, dtype=np.float64)
    return np.concatenate([xy, [float(scene.workspace_min[2])], quat])


def press_pose(scene: Scene, depth: float, xy=None, quat=None) -> np.ndarray:
    """The pose [7] ``depth`` of the way from the surface to the deepest valid pose, above ``xy``."""
    if not 0.0 <= depth <= 1.0:
        raise InputError(f"depth must be a fraction in [0, 1], got {depth}")
    deep = deepest_pose(scene, xy, quat)
    h = contact_height(scene, deep[:2], deep[3:])
    if not np.isfinite(h):
        raise InputError(f"the tool misses the {scene.name} object above {deep[:2]}")
    top = min(float(h), float(scene.workspace_max[2]))
    deep[2] = top - depth * (top - deep[2])
    return deep


class _Poses:
    def __init__(self, scene: Scene):
        self.scene = scene
        self.poses = [np.asarray(scene.tool_rest_pose, dtype=np.float64).copy()]

    def move(self, target: np.ndarray, per_frame: float) -> None:
        """Straight to ``target`` (slerp for the rotation) in equal frames of at most ``per_frame`` m."""
        last = self.poses[-1]
        if np.array_equal(last, target):
            return
        n = max(1, int(np.ceil(np.linalg.norm(target[:3] - last[:3]) / per_frame - 1e-9)))
        self.poses.extend(interpolate_poses(last, target, np.arange(1, n + 1) / n))

    def hold(self, n: int) -> None:
        self.poses.extend(self.poses[-1].copy() for _ in range(int(n)))

    def array(self) -> np.ndarray:
        out = np.array(self.poses)
        out[:, :3] = np.clip(out[:, :3], self.scene.workspace_min, self.scene.workspace_max)
        out[:, 3:] /= np.linalg.norm(out[:, 3:], axis=1, keepdims=True)
        out[0] = self.scene.tool_rest_pose
        return out


def _horizontal_x(quat: np.ndarray) -> np.ndarray:
    """Unit horizontal direction [3] of the tool's x axis (world x where it points straight up or down)."""
    x = quat_to_matrix(quat)[:, 0].copy()
    x[2] = 0.0
    n = float(np.linalg.norm(x))
    return x / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])


def _extent(scene: Scene, direction: np.ndarray) -> float:
    v = np.asarray(scene.object.vertices) @ direction
    return float(v.max() - v.min())


def hard_trajectories(scene: Scene, step: float, *, pace: float = 0.9, jump: float = 4.0, depth: float = 0.85,
                      drag: float = 0.25, noise: float = 1.5e-3, settle: int = 20, seed: int = 0,
                      kinds=HARD_KINDS) -> dict[str, np.ndarray]:
    """The hard trajectories of a scene by name (module docstring). ``step``: tool motion of one model step (m)."""
    if not step > 0 or not pace > 0 or not jump > 0:
        raise InputError(f"step, pace and jump must be > 0, got {step}, {pace}, {jump}")
    unknown = set(kinds) - set(HARD_KINDS)
    if unknown:
        raise InputError(f"unknown hard trajectories {sorted(unknown)}; valid: {', '.join(HARD_KINDS)}")
    rest = np.asarray(scene.tool_rest_pose, dtype=np.float64)
    q_rest = rest[3:]
    above = np.concatenate([scene.target[:2], rest[2:]])
    slow, fast = pace * step, jump * step
    out = {}
    for kind in kinds:
        p = _Poses(scene)
        p.move(above, slow)
        if kind == "fast plunge":
            p.move(deepest_pose(scene), fast)
            p.hold(1)
            p.move(above, fast)
        elif kind in ("press and drag", "tilted slice"):
            quat = q_rest
            if kind == "tilted slice":
                tilts = scene.family.get("tilt_deg", 0.0)
                tilt = float(np.max(tilts)) if np.max(tilts) > 0 else DEFAULT_TILT_DEG
                across = np.cross([0.0, 0.0, 1.0], _horizontal_x(q_rest))
                quat = quat_multiply(axis_angle_quat(across, np.deg2rad(tilt)), q_rest)
                p.move(np.concatenate([above[:3], quat]), slow)
            u = _horizontal_x(quat)
            bottom = press_pose(scene, depth, quat=quat)
            p.move(bottom, slow)
            amp = drag * _extent(scene, u)
            for s in (1.0, -1.0, 0.0):
                p.move(np.concatenate([bottom[:3] + s * amp * u, quat]), slow)
            p.move(np.concatenate([above[:3], quat]), slow)
        elif kind == "jitter":
            bottom = press_pose(scene, depth)
            p.move(bottom, slow)
            rng = np.random.default_rng(seed)
            n = len(p.poses)
            p.hold(max(4, n // 2))
            for k in range(n, len(p.poses)):
                p.poses[k] = p.poses[k].copy()
                p.poses[k][:3] += rng.uniform(-noise, noise, 3)
            for k in range(2, n):  # the press itself shakes too
                p.poses[k] = p.poses[k].copy()
                p.poses[k][:3] += rng.uniform(-noise, noise, 3)
        else:  # release and settle
            p.move(press_pose(scene, depth), slow)
            p.move(rest, fast)
            p.hold(settle)
        out[kind] = p.array()
    return out
