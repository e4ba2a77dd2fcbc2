"""The banana's contact prior alone (no network, no correction) on sequences of the full family: relative
displacement error and cost per step, solved on the full mesh and on the ci mesh (session 37).

    .venv/bin/python docs/fidelity/cylinder_banana_full_s37/prior_alone.py data/banana_across_test/test_000?.npz
"""
import sys
import time

import numpy as np

from colgnn_core.evaluation.measure import relative_errors
from colgnn_core.scenes import load_scene
from colgnn_core.sim.prior import physics_prior

scene = load_scene("cylinder_banana", "full")
rest = np.load(sys.argv[1])["object_positions"][0]  # the settled rest every sequence starts from
for mesh in ("", "ci"):
    prior = physics_prior("contact", scene, rest, np.arange(len(rest)), mesh=mesh)
    for path in sys.argv[1:]:
        seq = np.load(path)
        truth, seconds = seq["object_positions"], []
        pred = np.empty_like(truth)
        for t, pose in enumerate(seq["tool_poses"]):
            start = time.perf_counter()
            _, u = prior.step(None, pose, pose)
            seconds.append(time.perf_counter() - start)
            pred[t] = rest + u
        err = relative_errors(pred, truth)
        ms = 1e3 * np.asarray(seconds)
        print(f"{mesh or 'full'} {path}: all {err['all']:.3f} contact {err['contact']:.3f}; step median "
              f"{np.median(ms):.1f} ms, p95 {np.percentile(ms, 95):.1f}, max {ms.max():.0f}")
