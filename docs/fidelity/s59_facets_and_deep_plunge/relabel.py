"""Relabel, in place, a dataset folder simulated on a copy of a built-in scene that only draws another family (same
mesh, same physics) as the built-in scene's, so that `colgnn train --scene NAME` reads it. Refuses when the mesh
or the physics differ.

    python docs/fidelity/s59_facets_and_deep_plunge/relabel.py data/s59/floor cylinder_banana
"""
import json
import sys
from pathlib import Path

import numpy as np

from colgnn_core.scenes import load_scene

folder, name = Path(sys.argv[1]), sys.argv[2]
scene = load_scene(name, "full")
manifest = json.loads((folder / "manifest.json").read_text())
if not scene.accepts_physics(manifest["physics_fingerprint"]):
    sys.exit(f"{folder}: other physics than {name}")
if manifest["object_fingerprint"] != scene.object.fingerprint():
    sys.exit(f"{folder}: another mesh than {name}")
for path in sorted(folder.glob("*.npz")):
    seq = dict(np.load(path))
    if str(seq["scene"]) != name:
        seq["scene"] = np.array(name)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **seq)
        tmp.replace(path)
manifest["scene"] = name
tmp = folder / "manifest.json.tmp"
tmp.write_text(json.dumps(manifest, indent=1))
tmp.replace(folder / "manifest.json")
print("relabelled", len(list(folder.glob("*.npz"))), "files in", folder)
