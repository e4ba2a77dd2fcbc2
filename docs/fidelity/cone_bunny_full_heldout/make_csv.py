"""The held-out cone_bunny trajectories of this folder (session 10, the stiff bunny), written once and never used for
training or tuning. Run from the repository root: `.venv/bin/python docs/fidelity/cone_bunny_full_heldout/make_csv.py`.

Depths are millimetres below the surface point the cone's tip first touches, within the family's 6-25 mm; the
workspace floor allows stabs of up to 95 mm into the back, which the model was not trained on (README.md)."""
from pathlib import Path

import numpy as np
from colgnn_core.geometry.transforms import axis_angle_quat, interpolate_poses, quat_multiply
from colgnn_core.io import write_poses_csv
from colgnn_core.runtime.predictor import tool_step_limits
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.trajectories import contact_height

scene = load_scene("cone_bunny", "full")
step = tool_step_limits(scene)[0]
pace, jump = 0.9 * step, 2.5 * step
rest = scene.tool_rest_pose.copy()


def path(*poses, per_frame=pace):
    out = [poses[0][None]]
    for a, b in zip(poses[:-1], poses[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b[:3] - a[:3]) / per_frame)))
        out.append(interpolate_poses(a, b, np.arange(1, n + 1) / n))
    return np.concatenate(out)


def hold(p, k, at):
    return np.concatenate([p[: at + 1], np.repeat(p[at][None], k, 0), p[at + 1:]])


def above(p):
    """``p`` lifted to 15 mm above the rest bunny (the rest clearance), at least to the rest pose's height."""
    q = p.copy()
    q[2] = max(rest[2], contact_height(scene, p[:2], p[3:]) + 0.015)
    return q


def travel(p):
    """``p`` at a height clear of the whole bunny (the ears reach 0.198 m), to move over it."""
    q = p.copy()
    q[2] = 0.22
    return q


def stab(xy, depth_m, quat=None):
    """The pose ``depth_m`` below where the tool (orientation ``quat``) first touches the rest bunny above ``xy``."""
    quat = rest[3:] if quat is None else quat
    h = contact_height(scene, np.asarray(xy, float), quat)
    assert np.isfinite(h), xy
    return np.concatenate([xy, [h - depth_m], quat])


cases = {}
# a fast plunge into the back, 24 mm deep at 2.5 model steps a frame, one frame held, back up as fast, settle 6
deep = stab((0.03, -0.02), 0.024)
p = path(rest, above(deep))
p = np.concatenate([p, path(above(deep), deep, per_frame=jump)[1:]])
p = hold(p, 1, len(p) - 1)
p = np.concatenate([p, path(deep, above(deep), per_frame=jump)[1:]])
cases["fast plunge"] = np.concatenate([p, np.repeat(p[-1][None], 6, 0)])
# a press on the head, away from the family's target, 15 mm, held 4 frames, retracted, settled 8 frames
deep = stab((-0.07, -0.03), 0.015)
p = path(rest, travel(rest), travel(deep), above(deep), deep, above(deep))
p = hold(p, 4, int(np.argmin(p[:, 2])))
cases["away press"] = np.concatenate([p, np.repeat(p[-1][None], 8, 0)])
# a press on the back, 14 mm, dragged 4 cm along the back and 2 cm back, then up
a = stab((0.045, -0.03), 0.014)
b = a.copy()
b[0] -= 0.04
c = a.copy()
c[0] -= 0.02
cases["press and drag"] = path(rest, above(a), a, b, c, above(c))
# the cone tilted 20 degrees about x, pressed 12 mm into the back's side, sliced 3 cm along x and back, up
quat = quat_multiply(axis_angle_quat([1.0, 0.0, 0.0], np.deg2rad(20.0)), rest[3:])
a = stab((0.04, -0.045), 0.012, quat)
b = a.copy()
b[0] -= 0.03
start = np.concatenate([above(a)[:3], quat])
cases["tilted slice"] = path(rest, start, a, b, a, start)
for k, p in cases.items():
    name = k.replace(" ", "_")
    scene.check_poses(p)
    write_poses_csv(Path(__file__).parent / f"{name}.csv", np.arange(len(p)) * scene.dt, p)
    low = int(np.argmin(p[:, 2] - [contact_height(scene, x[:2], x[3:]) for x in p]))
    print(name, len(p), "frames; deepest frame", low, "at", np.round(p[low, :3], 4))
