"""The held-out cylinder_banana trajectories of this folder (session 8), written once and never used for training
or tuning. Run from the repository root: `.venv/bin/python docs/fidelity/cylinder_banana_full_heldout/make_csv.py`."""
from pathlib import Path

import numpy as np
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.hard_cases import hard_trajectories, press_pose
from colgnn_core.geometry.transforms import interpolate_poses
from colgnn_core.runtime.predictor import tool_step_limits
from colgnn_core.io import write_poses_csv

scene = load_scene("cylinder_banana", "full")
step = tool_step_limits(scene)[0]
pace = 0.9 * step
print("step limit", step)
hard = hard_trajectories(scene, step, kinds=("fast plunge", "press and drag", "tilted slice"))
rest = scene.tool_rest_pose.copy()
V = scene.object.vertices

def top_xy(x):
    near = np.abs(V[:, 0] - x) < 0.003
    i = np.flatnonzero(near)[np.argmax(V[near, 2])]
    return V[i, :2]

def path(*poses):
    out = [poses[0][None]]
    for a, b in zip(poses[:-1], poses[1:]):
        d = np.linalg.norm(b[:3] - a[:3])
        n = max(1, int(np.ceil(d / pace)))
        out.append(interpolate_poses(a, b, np.arange(1, n + 1) / n))
    return np.concatenate(out)

def with_hold(p, k_hold, at):
    return np.concatenate([p[: at + 1], np.repeat(p[at][None], k_hold, 0), p[at + 1:]])

def above(p):
    q = p.copy()
    q[2] = rest[2]
    return q

cases = dict(hard)
# a press near the banana's thin end, 70% of the way to the floor, held 4 frames, retracted, settled 8 frames
xy = top_xy(0.075)
deep = press_pose(scene, 0.7, xy)
p = path(rest, above(deep), deep, above(deep))
at = int(np.argmin(p[:, 2]))
p = with_hold(p, 4, at)
cases["away press"] = np.concatenate([p, np.repeat(p[-1][None], 8, 0)])
# press at the middle 60% of the way, then push sideways across the banana (along y) +-14 mm, back, up
mid = press_pose(scene, 0.6, scene.target[:2])
side_a, side_b = mid.copy(), mid.copy()
side_a[1] += 0.014
side_b[1] -= 0.014
cases["sideways drag"] = path(rest, above(mid), mid, side_a, side_b, mid, above(mid))
for k, p in cases.items():
    name = k.replace(" ", "_")
    scene.check_poses(p)
    write_poses_csv(Path(__file__).parent / f"{name}.csv", np.arange(len(p)) * scene.dt, p)
    print(name, len(p), "z min", p[:, 2].min(), "xy", p[np.argmin(p[:, 2]), :2])
