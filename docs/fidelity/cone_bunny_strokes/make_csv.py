r"""Random strokes over cone_bunny's body for training: drags, tilted slices and presses (sessions 54-55).

Each stroke starts at the tool's rest pose, travels above a point of the body whose contact height is 7-15 cm (the
back, the flanks, the head; not the ears), goes down 6-18 mm below the surface hit, then either holds (a press,
20%), or drags 2-5 cm in a straight line (40%, tilt 0-8 degrees) or slices (40%, tilt 8-20 degrees), partly back
for some, lifts 15 mm above the surface and holds six frames to settle. The tool moves at 0.9 x the Predictor's
step limit. Seeds 1000 + i: none is a family, test or held-out trajectory of the scene.

    .venv/bin/python docs/fidelity/cone_bunny_strokes/make_csv.py OUT COUNT

writes OUT/stroke_0000.csv ... (the 40 CSVs here are `make_csv.py docs/fidelity/cone_bunny_strokes 40`), and each
is simulated with

    .venv/bin/colgnn generate --scene cone_bunny --resolution full --poses stroke_0000.csv \
        --out data/strokes/stroke_0000
"""
import argparse
from pathlib import Path

import numpy as np

from colgnn_core.geometry.transforms import axis_angle_quat, interpolate_poses, quat_multiply
from colgnn_core.io import write_poses_csv
from colgnn_core.runtime.predictor import tool_step_limits
from colgnn_core.scenes import Scene, load_scene
from colgnn_core.scenes.trajectories import contact_height

BODY_HEIGHT = (0.07, 0.15)     # contact heights (m) that count as the body: below the ears' tips
DEPTH = (0.006, 0.018)         # how deep each stroke goes below the surface hit (m)
CLEARANCE = 0.015              # height above the surface where a stroke starts and ends (m)
TRAVEL_Z = 0.22                # height of the travel from the rest pose to above the stroke (m)
SETTLE_FRAMES = 6              # frames held at the end, for the object to return to rest


def _path(pace: float, *poses: np.ndarray) -> np.ndarray:
    """[K,7] straight interpolation through ``poses`` with steps of at most ``pace`` (m)."""
    out = [poses[0][None]]
    for a, b in zip(poses[:-1], poses[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b[:3] - a[:3]) / pace)))
        out.append(interpolate_poses(a, b, np.arange(1, n + 1) / n))
    return np.concatenate(out)


def _on_body(scene: Scene, xy: np.ndarray, quat: np.ndarray) -> bool:
    h = contact_height(scene, np.asarray(xy, float), quat)
    return bool(np.isfinite(h) and BODY_HEIGHT[0] <= h <= BODY_HEIGHT[1])


def _way(scene: Scene, rng: np.random.Generator, kind: str, quat: np.ndarray) -> list[np.ndarray]:
    """The stroke's xy waypoints (m), every one on the body."""
    for _ in range(1000):
        a = rng.uniform([-0.09, -0.07], [0.09, 0.07])
        if not _on_body(scene, a, quat):
            continue
        if kind == "press":
            return [a]
        d = rng.uniform(0.02, 0.05)
        phi = rng.uniform(0, 2 * np.pi)
        u = np.array([np.cos(phi), np.sin(phi)])
        way = [a + u * d * k / 4 for k in range(5)]
        if all(_on_body(scene, w, quat) for w in way):
            back = rng.uniform(0.0, 0.6)
            return way + ([a + u * d * (1 - back)] if back > 0.1 else [])
    raise RuntimeError("no stroke on the body in 1000 draws")


def stroke(scene: Scene, seed: int) -> tuple[str, np.ndarray]:
    """(kind, poses [T,7]) of the stroke drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    rest = scene.tool_rest_pose.copy()
    pace = 0.9 * tool_step_limits(scene)[0]
    kind = str(rng.choice(["drag", "slice", "press"], p=[0.4, 0.4, 0.2]))
    tilt = np.deg2rad(rng.uniform(8, 20) if kind == "slice" else rng.uniform(0, 8))
    az = rng.uniform(0, 2 * np.pi)
    quat = quat_multiply(axis_angle_quat([np.cos(az), np.sin(az), 0.0], tilt), rest[3:])
    depth = rng.uniform(*DEPTH)
    way = _way(scene, rng, kind, quat)

    def at(xy: np.ndarray, dz: float) -> np.ndarray:
        return np.concatenate([xy, [contact_height(scene, xy, quat) + dz], quat])

    above = at(way[0], CLEARANCE)
    above[2] = max(rest[2], above[2])
    p = _path(pace, rest, np.concatenate([rest[:2], [TRAVEL_Z], rest[3:]]),
              np.concatenate([way[0], [TRAVEL_Z], quat]), above, *[at(w, -depth) for w in way])
    if kind == "press":
        p = np.concatenate([p, np.repeat(p[-1][None], int(rng.integers(2, 5)), 0)])
    end = at(way[-1], CLEARANCE)
    end[2] = max(rest[2], end[2])
    p = np.concatenate([p, _path(pace, p[-1], end)[1:]])
    return kind, np.concatenate([p, np.repeat(p[-1][None], SETTLE_FRAMES, 0)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("count", type=int)
    args = ap.parse_args()
    scene = load_scene("cone_bunny", "full")
    args.out.mkdir(parents=True, exist_ok=True)
    for i in range(args.count):
        kind, p = stroke(scene, 1000 + i)
        scene.check_poses(p)
        write_poses_csv(args.out / f"stroke_{i:04d}.csv", np.arange(len(p)) * scene.dt, p)
        print(f"stroke_{i:04d}: {kind}, {len(p)} frames, deepest tip {np.round(p[np.argmin(p[:, 2]), :3], 3)} m")


if __name__ == "__main__":
    main()
