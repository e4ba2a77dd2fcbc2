"""Tool trajectories: the randomised family per scene (train/test by seed) and scripted motions.

A trajectory is an array of poses [T,7] ([px,py,pz,qx,qy,qz,qw], one per model
step dt) whose frame 0 is the scene's ``tool_rest_pose``. The family repeats
*strokes* until the requested number of frames is filled. One stroke:

1. pick a point in a disk of radius ``target_jitter`` around ``target_xy``; the
   surface height h there comes from a vertical ray cast on the rest mesh;
2. move (eased, ``speed`` m/step on average) from where the tool is to the pose
   whose lowest point is ``depth`` below h, turning to a random ``tilt``/``yaw``;
   the approach direction follows from the start and end points;
3. drift laterally by ``drift`` m at the same depth below the local surface
   (along the blade for the knife: a slicing cut);
4. hold for ``hold`` frames, then retract straight up to the rest height and the
   rest orientation at ``speed * retract_speed_factor``.

Randomness comes from ``numpy.random.default_rng([seed, crc32(scene name)])``:
the same seed gives the same poses. Seeds of the splits are disjoint by
construction (:func:`split_seeds`).
"""

from __future__ import annotations

import zlib

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import axis_angle_quat, interpolate_poses, quat_multiply, quat_to_matrix
from colgnn_core.scenes.scene import Scene, tool_contact_height

SPLITS = ("train", "val", "test")
FIRST_TRAVEL_FRAMES = 60  # frames drawn beyond a trimmed trajectory: a first travel and descent fit in most
MAX_TRAVEL_FRAMES = 480   # ... and at most this many, doubling (the bunny's seed 1 at ci reaches it after ~100)
SCRIPTED_KINDS = ("press", "stab", "slice", "drag", "circle", "random")


def split_seeds(split: str, count: int) -> list[int]:
    """Seeds of a dataset split: train 3i, val 3i+1, test 3i+2 (i = 0..count-1).

    Disjoint by construction and prefix-stable (the first 20 train seeds are the
    same whether 20 or 100 are asked for).
    """
    if split not in SPLITS:
        raise InputError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    if count < 0:
        raise InputError(f"count must be >= 0, got {count}")
    return [3 * i + SPLITS.index(split) for i in range(int(count))]


def _rng(scene: Scene, seed: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(scene.name.encode())])


def _ease(n: int) -> np.ndarray:
    """Fractions [n] in (0, 1] along a smoothstep: zero speed at both ends, peak 1.5x mean."""
    s = np.arange(1, n + 1) / n
    return s * s * (3 - 2 * s)


def _steps(distance: float, speed: float) -> int:
    return max(1, int(np.ceil(distance / max(speed, 1e-9))))


class _Path:
    """Growing list of poses; every move starts at the last pose."""

    def __init__(self, start: np.ndarray) -> None:
        self.poses = [np.asarray(start, dtype=np.float64)]

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def last(self) -> np.ndarray:
        return self.poses[-1]

    def move_to(self, position: np.ndarray, quat: np.ndarray, speed: float) -> None:
        """Eased move to (position, quat) at ``speed`` m/step on average (rotation rides along)."""
        target = np.concatenate([position, quat])
        n = _steps(float(np.linalg.norm(position - self.last[:3])), speed)
        self.poses.extend(interpolate_poses(self.last, target, _ease(n)))

    def follow(self, positions: np.ndarray, quat: np.ndarray) -> None:
        """Append poses at given positions [K,3] with a fixed orientation."""
        for p in positions:
            self.poses.append(np.concatenate([p, quat]))

    def hold(self, n: int) -> None:
        self.poses.extend([self.last.copy() for _ in range(int(n))])

    def array(self, frames: int) -> np.ndarray:
        out = np.array(self.poses[:frames])
        if len(out) < frames:
            out = np.concatenate([out, np.repeat(out[-1:], frames - len(out), axis=0)])
        return out


def contact_height(scene: Scene, xy: np.ndarray, quat: np.ndarray) -> float:
    """See :func:`colgnn_core.scenes.scene.tool_contact_height` (for this scene's object and tool)."""
    return tool_contact_height(scene.object, scene.tool, xy, quat)


def _contact_heights(scene: Scene, xy: np.ndarray, quat: np.ndarray, fallback: float) -> np.ndarray:
    """:func:`contact_height` along xy [K,2]; where the tool misses the object, the previous value."""
    out = np.empty(len(xy))
    last = fallback
    for i, p in enumerate(xy):
        h = contact_height(scene, p, quat)
        last = h if np.isfinite(h) else last
        out[i] = last
    return out


def _clearance(scene: Scene) -> float:
    return float(scene.config["tool"]["rest_clearance"])


def _rest_height(scene: Scene, xy: np.ndarray) -> float:
    """Retract height at xy: the rest height, or higher if the object is higher there."""
    h = contact_height(scene, xy, scene.tool_rest_pose[3:])
    return max(float(scene.tool_rest_pose[2]), h + _clearance(scene) if np.isfinite(h) else -np.inf)


def _uniform(rng: np.random.Generator, bounds) -> float:
    lo, hi = (float(bounds[0]), float(bounds[1])) if np.ndim(bounds) else (float(bounds), float(bounds))
    return float(rng.uniform(lo, hi)) if hi > lo else lo


def _orientation(scene: Scene, tilt_deg: float, tilt_azimuth: float, yaw_deg: float) -> np.ndarray:
    """Rest orientation turned by ``yaw`` about world z, then tilted about a horizontal axis."""
    q_rest = scene.tool_rest_pose[3:]
    q = quat_multiply(axis_angle_quat([0.0, 0.0, 1.0], np.deg2rad(yaw_deg)), q_rest)
    axis = np.array([np.cos(tilt_azimuth), np.sin(tilt_azimuth), 0.0])
    return quat_multiply(axis_angle_quat(axis, np.deg2rad(tilt_deg)), q)


def _horizontal_tool_x(quat: np.ndarray) -> np.ndarray:
    """The tool's x axis projected onto the ground plane, unit (world x if vertical)."""
    x = quat_to_matrix(quat)[:, 0].copy()
    x[2] = 0.0
    n = np.linalg.norm(x)
    return x / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])


def _stroke(scene: Scene, path: _Path, rng: np.random.Generator) -> None:
    fam = scene.family
    r = float(fam.get("target_jitter", 0.0)) * np.sqrt(rng.uniform())
    phi = rng.uniform(0, 2 * np.pi)
    xy = np.asarray(fam["target_xy"], dtype=np.float64) + r * np.array([np.cos(phi), np.sin(phi)])
    depth = _uniform(rng, fam["depth"])
    speed = _uniform(rng, fam["speed"])
    retract = speed * _uniform(rng, fam.get("retract_speed_factor", [1.0, 1.0]))
    quat = _orientation(scene, _uniform(rng, fam.get("tilt_deg", 0.0)), rng.uniform(0, 2 * np.pi),
                        _uniform(rng, fam.get("yaw_deg", 0.0)))
    h = _contact_heights(scene, xy[None], quat, fallback=float(scene.tool_rest_pose[2]) - _clearance(scene))[0]
    path.move_to(np.array([xy[0], xy[1], h - depth]), quat, speed)

    drift = _uniform(rng, fam.get("drift", 0.0))
    if drift > 0:
        if fam.get("drift_along_tool_x", False):
            direction = _horizontal_tool_x(quat) * rng.choice([-1.0, 1.0])
        else:
            a = rng.uniform(0, 2 * np.pi)
            direction = np.array([np.cos(a), np.sin(a), 0.0])
        n = _steps(drift, speed)
        xy_path = xy + np.outer(_ease(n), direction[:2] * drift)
        z_path = _contact_heights(scene, xy_path, quat, fallback=h) - depth  # same indentation along the way
        path.follow(np.column_stack([xy_path, z_path]), quat)
        xy = xy_path[-1]
    lo, hi = fam.get("hold", [0, 0])
    path.hold(int(rng.integers(int(lo), int(hi) + 1)))
    _retract(scene, path, retract, along_axis=bool(fam.get("retract_along_tool_axis", False)))


STROKE_KINDS = ("press", "drag", "plunge")


def _coverage_target(scene: Scene, rng: np.random.Generator, depth: float, near: np.ndarray | None,
                     orientation) -> tuple[np.ndarray, np.ndarray, float]:
    """A target (xy [2], quat [4], contact height h) drawn uniformly over the object's tool-facing footprint.

    Rejection sampling over the object's bbox in xy, inset by ``region_margin`` (within ``near_radius`` of ``near``
    [2] when given: the next press close to the last one, so less of a sequence is spent travelling). For each
    candidate the tool orientation comes from ``orientation(xy)``; a point is kept where the tool, lowered at that
    orientation, meets the object and the pressed pose stays inside the workspace.
    """
    fam = scene.family
    lo, hi = scene.object_bbox()
    margin = float(fam.get("region_margin", 0.0))
    wlo, whi = scene.workspace_min, scene.workspace_max
    lo_xy = np.maximum(lo[:2] + margin, wlo[:2])
    hi_xy = np.minimum(hi[:2] - margin, whi[:2])
    if near is not None:
        r = float(fam.get("near_radius", 0.05))
        lo_xy, hi_xy = np.maximum(lo_xy, near - r), np.minimum(hi_xy, near + r)
    for _ in range(200):
        xy = rng.uniform(lo_xy, hi_xy)
        quat = orientation(xy)
        h = contact_height(scene, xy, quat)
        if np.isfinite(h) and wlo[2] <= h - depth and h + _clearance(scene) <= whi[2]:
            return xy, quat, float(h)
    raise InputError(f"{scene.name}: no reachable target on the object's surface for the coverage family")


def _coverage_stroke(scene: Scene, path: _Path, rng: np.random.Generator) -> None:
    """One stroke of a workspace-covering family (``family.region = "surface"``).

    Kinds, drawn with ``stroke_weights`` (press, drag, plunge): a *press* anywhere on the tool-facing surface; a
    *press-and-drag* across it (``drag`` m, at the same indentation below the local surface, drawn from
    ``drag_depth`` where given, else ``depth``; with probability ``drag_across`` the drag runs across the object's
    short side toward its nearer flank, ``drag_across_length`` m, see :func:`_across`); a *plunge* at the top speed
    to ``plunge_depth`` (m, drawn) or, without that key, the deepest press. The first stroke stops at the workspace
    floor.
    The first stroke aims at the family's target disk (``target_xy``, ``target_jitter``: contact within the first
    frames), later ones anywhere; with ``first_target = "surface"`` the first one goes anywhere too, after a travel
    from the rest pose (a long object whose sequences hold one or two strokes is otherwise pressed only near its
    target). Every stroke may be tilted
    (``tilt_deg``) and turned (``yaw_deg``, about the radial direction from the object's centre when
    ``yaw_radial``), travels above the object at the retract height before it descends (no sweep through a raised
    part), and ends with a retract and ``settle`` frames of waiting, so sequences show the object returning to rest.
    """
    fam = scene.family
    weights = np.asarray(fam.get("stroke_weights", [0.5, 0.3, 0.2]), dtype=np.float64)
    kind = STROKE_KINDS[int(rng.choice(len(STROKE_KINDS), p=weights / weights.sum()))]
    top = float(np.max(fam["speed"]))
    speed = top if kind == "plunge" else _uniform(rng, fam["speed"])
    depth = _stroke_depth(rng, fam, kind)
    tilt, azimuth, yaw = _uniform(rng, fam.get("tilt_deg", 0.0)), rng.uniform(0, 2 * np.pi), _uniform(
        rng, fam.get("yaw_deg", 0.0))
    centre = 0.5 * np.add(*scene.object_bbox())[:2]

    def orientation(xy: np.ndarray) -> np.ndarray:
        radial = np.degrees(np.arctan2(*(xy - centre)[::-1])) if fam.get("yaw_radial", False) else 0.0
        return _orientation(scene, tilt, azimuth, yaw + radial)

    first = len(path) == 1
    aimed = first and fam.get("first_target", "target") == "target"
    if aimed:  # the first stroke aims at the scene's target, as the narrow family did: contact early
        r = float(fam.get("target_jitter", 0.0)) * np.sqrt(rng.uniform())
        phi = rng.uniform(0, 2 * np.pi)
        xy = np.asarray(fam["target_xy"], dtype=np.float64) + r * np.array([np.cos(phi), np.sin(phi)])
        quat = orientation(xy)
        h = _contact_heights(scene, xy[None], quat, fallback=float(scene.tool_rest_pose[2]) - _clearance(scene))[0]
        depth = min(depth, h - float(scene.workspace_min[2]))  # a deep plunge stops at the workspace floor
    else:
        near = None if first or rng.uniform() >= float(fam.get("near_fraction", 0.5)) else path.last[:2]
        xy, quat, h = _coverage_target(scene, rng, depth, near, orientation)
    travel = max(float(path.last[2]), _rest_height(scene, xy))
    if not aimed and np.linalg.norm(xy - path.last[:2]) > 1e-9:  # out of contact: at the family's top speed
        path.move_to(np.array([path.last[0], path.last[1], travel]), path.last[3:], top)
        path.move_to(np.array([xy[0], xy[1], travel]), quat, top)
    path.move_to(np.array([xy[0], xy[1], h - depth]), quat, speed)
    if kind == "drag":
        a = rng.uniform(0, 2 * np.pi)
        if fam.get("drift_along_tool_x", False):  # a blade slices along its edge
            u = _horizontal_tool_x(quat)[:2]
            a = np.arctan2(u[1], u[0]) + (np.pi if rng.uniform() < 0.5 else 0.0)
        length = _uniform(rng, fam.get("drag", [0.02, 0.05]))
        if float(fam.get("drag_across", 0.0)) > 0 and rng.uniform() < float(fam["drag_across"]):
            a, length = _across(scene, xy, rng)
        xy_path = xy + np.outer(_ease(_steps(length, speed)), np.array([np.cos(a), np.sin(a)]) * length)
        z_path = _contact_heights(scene, xy_path, quat, fallback=h) - depth
        keep = np.all((xy_path >= scene.workspace_min[:2]) & (xy_path <= scene.workspace_max[:2]), axis=1)
        keep &= z_path >= scene.workspace_min[2]
        stop = int(np.argmin(keep)) if not keep.all() else len(keep)
        path.follow(np.column_stack([xy_path, z_path])[:stop], quat)
    lo, hi = fam.get("hold", [0, 0])
    path.hold(int(rng.integers(int(lo), int(hi) + 1)))
    retract = speed * _uniform(rng, fam.get("retract_speed_factor", [1.0, 1.0]))
    _retract(scene, path, retract, along_axis=bool(fam.get("retract_along_tool_axis", False)))
    s_lo, s_hi = fam.get("settle", [0, 0])
    path.hold(int(rng.integers(int(s_lo), int(s_hi) + 1)))


def _across(scene: Scene, xy: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """(direction angle, length m) of a drag across the object: along the short side of its footprint, away from the
    middle line toward the nearer flank, ``drag_across_length`` long (default ``drag``), so that it leaves the top
    for the flank (a long object's drags in a random direction rarely do: the banana's family pressed beyond 45 mm
    from its middle line in 19 of 609 pressing frames, docs/FIDELITY.md session 35)."""
    lo, hi = scene.object_bbox()
    axis = int(np.argmin(hi[:2] - lo[:2]))
    outward = 1.0 if xy[axis] >= 0.5 * (lo[axis] + hi[axis]) else -1.0
    a = (0.0 if axis == 0 else 0.5 * np.pi) + (0.0 if outward > 0 else np.pi)
    fam = scene.family
    return a, _uniform(rng, fam.get("drag_across_length", fam.get("drag", [0.02, 0.05])))


def _stroke_depth(rng: np.random.Generator, fam: dict, kind: str) -> float:
    """A stroke's depth below the surface point hit, m. A plunge's is drawn from ``plunge_depth`` where the family
    gives it (down to the workspace floor, deeper than any press), else it is the deepest press; a drag's from
    ``drag_depth`` where given (slices as deep as the workspace), else from ``depth`` like a press. Scenes without
    those keys draw exactly as before, so their sequences stay as they were."""
    if kind == "plunge":
        return _uniform(rng, fam["plunge_depth"]) if "plunge_depth" in fam else float(np.max(fam["depth"]))
    if kind == "drag" and "drag_depth" in fam:
        return _uniform(rng, fam["drag_depth"])
    return _uniform(rng, fam["depth"])


def _retract(scene: Scene, path: _Path, speed: float, along_axis: bool) -> None:
    """Pull the tool out to the rest height keeping its orientation, then turn back to rest.

    Turning only once clear avoids sweeping a tilted tool through the object.
    ``along_axis``: pull out along the tool's +z axis (a stabbing cone leaves
    the way it went in) rather than straight up.
    """
    quat = path.last[3:]
    z_up = _rest_height(scene, path.last[:2])
    direction = np.array([0.0, 0.0, 1.0])
    if along_axis:
        axis = quat_to_matrix(quat)[:, 2]
        if axis[2] > 0.5:  # only if the axis points mostly up
            direction = axis / axis[2]
    rise = max(z_up - path.last[2], 0.0)
    if rise > 0:
        path.move_to(path.last[:3] + rise * direction, quat, speed)
    angle = 2 * np.arccos(min(1.0, abs(float(np.dot(quat, scene.tool_rest_pose[3:])))))
    if angle > 1e-6:  # turn back in place, about 3 degrees per step (peak 4.5 with easing)
        n = max(1, int(np.ceil(np.rad2deg(angle) / 3.0)))
        path.poses.extend(interpolate_poses(path.last, np.concatenate([path.last[:3], scene.tool_rest_pose[3:]]),
                                            _ease(n)))


def _finish(scene: Scene, path: _Path, frames: int, clip: bool) -> np.ndarray:
    poses = path.array(frames)
    if clip:  # a safety net: the families are designed to stay inside (tests run with clip=False)
        poses[:, :3] = np.clip(poses[:, :3], scene.workspace_min, scene.workspace_max)
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    poses[0] = scene.tool_rest_pose
    return poses


def _gaps(scene: Scene, poses: np.ndarray) -> np.ndarray:
    """[T] m: the tool's signed distance to the object's rest shape (its vertices) at each pose [T,7]."""
    v = np.asarray(scene.object.vertices)
    return np.array([float(scene.tool.sdf(v, p).min()) for p in poses])


def approach_start(scene: Scene, poses: np.ndarray) -> int:
    """Index of the pose [T,7] where the first descent onto the object begins: the last pose before the tool first
    reaches into the object's rest shape that is still ``rest_clearance`` from it (0 if none is, or if the tool
    never reaches the object). A family whose first stroke travels (``first_target = "surface"``) spends its first
    frames above the object; a short trajectory that must press (a bench) starts here."""
    gap = _gaps(scene, poses)
    inside = np.flatnonzero(gap < 0)
    if not len(inside):
        return 0
    clear = np.flatnonzero(gap[: inside[0]] >= _clearance(scene) - 1e-9)
    return int(clear[-1]) if len(clear) else 0


def sample_pressing_poses(scene: Scene, seed: int, frames: int) -> np.ndarray:
    """:func:`sample_poses`, except that where the family's first stroke travels (``first_target = "surface"``) the
    [frames,7] window starts at :func:`approach_start`, so a short trajectory presses as an aimed family's does. The
    draw is ``FIRST_TRAVEL_FRAMES`` longer, doubled while the tool has not reached the object, up to
    ``MAX_TRAVEL_FRAMES`` (a slow tool's travel to a far target can take longer). The family's paths are
    prefix-stable, so the longer draw holds the shorter."""
    if scene.family.get("first_target", "target") == "target":
        return sample_poses(scene, seed, frames)
    extra = FIRST_TRAVEL_FRAMES
    while True:
        poses = sample_poses(scene, seed, frames + extra)
        if extra >= MAX_TRAVEL_FRAMES or _gaps(scene, poses).min() < 0:
            start = approach_start(scene, poses)
            return poses[start:start + frames]
        extra *= 2


def _check_frames(frames: int) -> int:
    if int(frames) < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    return int(frames)


def sample_poses(scene: Scene, seed: int, frames: int, *, clip: bool = True) -> np.ndarray:
    """Poses [frames,7] of the scene's trajectory family for ``seed``; frame 0 = rest pose.

    ``clip`` clamps positions into the workspace (a no-op for the shipped scenes).
    """
    frames = _check_frames(frames)
    rng = _rng(scene, seed)
    path = _Path(scene.tool_rest_pose)
    stroke = _coverage_stroke if scene.family.get("region") == "surface" else _stroke
    while len(path) < frames:
        stroke(scene, path, rng)
    return _finish(scene, path, frames, clip)


def _mid(bounds) -> float:
    return float(np.mean(bounds)) if np.ndim(bounds) else float(bounds)


def scripted_poses(scene: Scene, kind: str, frames: int, seed: int = 0, *, clip: bool = True) -> np.ndarray:
    """Scripted motions [frames,7] from the rest pose (e.g. for a ROS pose publisher).

    kinds: ``press`` (straight down to the mean depth, hold, up; repeated), ``stab``
    (fast, to the deepest family depth; repeated), ``slice`` (down, then back and
    forth along the tool's x axis), ``drag`` (down, then a straight drag across
    the target), ``circle`` (down, then circles around the target), ``random``
    (smooth random waypoints in the family's range; uses ``seed``). ``clip`` as in
    :func:`sample_poses`.
    """
    if kind not in SCRIPTED_KINDS:
        raise InputError(f"unknown scripted motion {kind!r}; valid: {', '.join(SCRIPTED_KINDS)}")
    frames = _check_frames(frames)
    fam = scene.family
    q_rest = scene.tool_rest_pose[3:]
    c = scene.target
    path = _Path(scene.tool_rest_pose)
    up = scene.tool_rest_pose[:3]
    speed = _mid(fam["speed"])
    depth_lo, depth_hi = (fam["depth"][0], fam["depth"][1])
    amp = max(float(fam.get("target_jitter", 0.0)), float(np.max(fam.get("drift", 0.0))), 0.005)

    h_target = contact_height(scene, c[:2], q_rest)

    def bottom(xy: np.ndarray, depth: float) -> np.ndarray:
        return np.array([xy[0], xy[1], _contact_heights(scene, xy[None], q_rest, h_target)[0] - depth])

    def surface_path(xy: np.ndarray, depth: float) -> np.ndarray:
        return np.column_stack([xy, _contact_heights(scene, xy, q_rest, h_target) - depth])

    if kind in ("press", "stab"):
        depth = _mid(fam["depth"]) if kind == "press" else float(depth_hi)
        v = speed if kind == "press" else float(np.max(fam["speed"]))
        while len(path) < frames:
            path.move_to(bottom(c[:2], depth), q_rest, v)
            path.hold(2 if kind == "press" else 0)
            path.move_to(up, q_rest, v)
            path.hold(1)
    elif kind in ("slice", "drag", "circle"):
        u = _horizontal_tool_x(q_rest)[:2]
        depth = float(depth_lo)
        if kind == "slice":
            start = c[:2]
        elif kind == "drag":
            start = c[:2] - amp * u
        else:
            start = c[:2] + np.array([amp, 0.0])
        path.move_to(np.array([start[0], start[1], up[2]]), q_rest, speed)
        path.move_to(bottom(start, depth), q_rest, speed)
        n_up = _steps(float(up[2] - bottom(start, depth)[2]), speed)
        n_mid = max(frames - len(path) - n_up, 1)
        k = np.arange(1, n_mid + 1)
        if kind == "slice":
            period = max(8, int(np.ceil(4 * amp / speed)))
            xy = start + np.outer(amp * np.sin(2 * np.pi * k / period), u)
        elif kind == "drag":
            s = np.minimum(k * speed / (2 * amp), 1.0)
            xy = start + np.outer(2 * amp * s * s * (3 - 2 * s), u)
        else:
            w = speed / amp  # rad per step: arc length per step = speed
            xy = c[:2] + amp * np.column_stack([np.cos(w * k), np.sin(w * k)])
        path.follow(surface_path(xy, depth), q_rest)
        _retract(scene, path, speed, along_axis=False)
    else:  # random
        rng = _rng(scene, seed)
        while len(path) < frames:
            r = float(fam.get("target_jitter", 0.0)) * np.sqrt(rng.uniform())
            a = rng.uniform(0, 2 * np.pi)
            xy = c[:2] + r * np.array([np.cos(a), np.sin(a)])
            quat = _orientation(scene, _uniform(rng, fam.get("tilt_deg", 0.0)), rng.uniform(0, 2 * np.pi),
                                _uniform(rng, fam.get("yaw_deg", 0.0)))
            lowest = _contact_heights(scene, xy[None], quat, h_target)[0] - float(depth_hi)
            z = rng.uniform(lowest, _rest_height(scene, xy))
            path.move_to(np.array([xy[0], xy[1], z]), quat, _uniform(rng, fam["speed"]))
    return _finish(scene, path, frames, clip)
