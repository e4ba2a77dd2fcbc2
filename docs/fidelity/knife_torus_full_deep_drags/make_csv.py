"""Deep-drag training trajectories for knife_torus (sessions 23-24; four of them are in knife_torus.pt's training
data): the scene's family with drags only, as deep as the workspace (drag_depth) and long (drag), seeds disjoint
from the family's train/test seeds.
usage: make_csv.py OUTDIR COUNT [SEED0]"""
import sys
from pathlib import Path
import numpy as np
from colgnn_core.scenes import load_scene
from colgnn_core.scenes.trajectories import sample_poses
from colgnn_core.io import write_poses_csv

out, count = Path(sys.argv[1]), int(sys.argv[2])
seed0 = int(sys.argv[3]) if len(sys.argv) > 3 else 5000
scene = load_scene("knife_torus", resolution="full")
scene.family.update(stroke_weights=[0.0, 1.0, 0.0], drag_depth=[0.02, 0.046], drag=[0.02, 0.07],
                    speed=[0.002, 0.004])
out.mkdir(parents=True, exist_ok=True)
for i in range(count):
    poses = sample_poses(scene, seed0 + i, 60)
    t = np.arange(len(poses)) * scene.dt
    write_poses_csv(out / f"deep_{i:02d}.csv", t, poses)
    print(i, "min z %.4f" % poses[:, 2].min(), "xy travel %.3f" % np.ptp(poses[:, :2], axis=0).max())
