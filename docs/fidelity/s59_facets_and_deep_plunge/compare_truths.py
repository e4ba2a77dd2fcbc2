"""How far apart two ground truths of the same poses are: ||X_a - X_b|| / ||X_a - X_rest|| over frames 1.. (the
relative displacement error of b against a), and per frame with --frames.

    python docs/fidelity/s59_facets_and_deep_plunge/compare_truths.py A.npz B.npz [--frames]
"""
import sys

import numpy as np

from colgnn_core.evaluation.measure import relative_displacement_error

a, b = (np.load(p)["object_positions"] for p in sys.argv[1:3])
rest = a[0]
if "--frames" in sys.argv:
    for f in range(1, len(a)):
        moved = np.linalg.norm(a[f] - rest, axis=1).max() * 1000
        print(f"frame {f}: largest displacement {moved:.2f} mm, "
              f"relative difference {relative_displacement_error(b[[0, f]], a[[0, f]], rest):.3f}")
print(f"relative difference over {len(a)} frames: {relative_displacement_error(b, a, rest):.3f}")
