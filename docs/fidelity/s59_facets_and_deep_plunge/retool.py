"""Relabel a ground truth simulated on a copy of a built-in scene that presses with a finer tool mesh, so that
`colgnn evaluate --scene NAME` reads it: the scene name, and the built-in tool mesh placed at the recorded poses.
The physics fingerprint and the sub-frame records (whose tool poses are not stored) are dropped.

    python docs/fidelity/s59_facets_and_deep_plunge/retool.py TRUTH.npz OUT/test_0000.npz cylinder_banana
"""
import sys

import numpy as np

from colgnn_core.scenes import load_scene

src, dst, name = sys.argv[1:4]
scene = load_scene(name, "full")
seq = dict(np.load(src))
seq["scene"] = np.array(name)
seq["tool_positions"] = np.stack([scene.tool.world_vertices(p) for p in seq["tool_poses"]]).astype(
    seq["tool_positions"].dtype)
seq["tool_faces"] = scene.tool.faces
for key in ("physics_fingerprint", "subframe_frame", "subframe_object_positions", "subframe_tool_positions"):
    seq.pop(key, None)
np.savez_compressed(dst, **seq)
print(dst, seq["tool_positions"].shape)
