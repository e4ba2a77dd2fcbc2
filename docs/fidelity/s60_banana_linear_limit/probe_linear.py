"""Is linear elasticity at the settled rest enough for a frame of a banana truth? (session 60)

For each FRAME of a truth SEQ.npz (`colgnn generate` output, full resolution), against the truth's displacement
d = X_t - X_0 (relative displacement error over all vertices, and over the contact region, the 10% it moves most):

- inertia: |K^-1 f_inertia| / |d|, with f_inertia = M (X_t - 2 X_{t-1} + X_{t-2}) / dt^2, implicit Euler's
  inertial force (how far the frame is from quasi-static);
- linear, true force: K^-1 (grad E(X_t) - grad E(X_0)), the linear response to the truth's own elastic force
  (whether linear elasticity describes the frame at all, given the right loads);
- prior: the shipped contact prior (modal compliance, one constraint per surface vertex) at the frame's tool pose,
  and the same with one constraint per face (points="faces");
- min J: the smallest tet volume ratio of the truth and of the prior's state (below 0: inverted).

K is the stable Neo-Hookean Hessian at X_0 with the glued vertices fixed (sim.rest_stiffness), as the prior's.
Usage, from the repository root after `make setup`:
    .venv/bin/python docs/fidelity/s60_banana_linear_limit/probe_linear.py SEQ.npz FRAME [FRAME ...]
Frames need two before them (FRAME >= 2).
"""

from __future__ import annotations

import sys

import numpy as np

from colgnn_core.evaluation.measure import relative_errors
from colgnn_core.scenes import load_scene
from colgnn_core.sim.contact_prior import ContactPrior
from colgnn_core.sim.elasticity import StableNeoHookean, lumped_mass
from colgnn_core.sim.prior import physics_prior


def relative(u: np.ndarray, frame: np.ndarray, rest: np.ndarray) -> str:
    """'all (contact)': the relative displacement error of the displacement u [N,3] against the truth's frame [N,3],
    as `colgnn evaluate` measures it on the two-frame sequence (rest, frame)."""
    e = relative_errors(np.stack([rest, rest + u]), np.stack([rest, frame]))
    return f"{e['all']:.3f} ({e['contact']:.3f})"


def main(path: str, frames: list[int]) -> None:
    seq = np.load(path)
    scene = load_scene("cylinder_banana", "full")
    x, poses, dt = seq["object_positions"], seq["tool_poses"], float(seq["dt"])
    rest = x[0]
    nodes = np.arange(rest.shape[0])
    prior = physics_prior("contact", scene, rest, nodes, compliance="modal")
    faces = ContactPrior(scene, rest, nodes, stiffness=prior.stiffness, compliance=prior.compliance, points="faces")
    k = prior.stiffness
    free = np.flatnonzero(k.free_index >= 0)
    dof = (3 * free[:, None] + np.arange(3)).reshape(-1)
    energy = StableNeoHookean(scene.object, scene.material)
    g0 = energy.gradient(rest).reshape(-1)
    mass = np.broadcast_to(np.asarray(lumped_mass(scene.object, scene.material.density), dtype=np.float64)
                           .reshape(-1, 1), rest.shape).reshape(-1)

    def response(force: np.ndarray) -> np.ndarray:
        u = np.zeros_like(rest)
        u[free] = k.solve(force[dof]).reshape(-1, 3)
        return u

    print("frame | tool centre (mm) | max |d| (mm) | inertia | linear, true force | prior (vertices) | prior (faces) "
          "| min J truth / prior")
    for t in frames:
        if t < 2:
            raise SystemExit(f"frame {t}: need two frames before it")
        d = x[t] - rest
        inertia = response(mass * (x[t] - 2 * x[t - 1] + x[t - 2]).reshape(-1) / dt ** 2)
        linear = response(energy.gradient(x[t]).reshape(-1) - g0)
        up, uf = prior.displacement(poses[t]), faces.displacement(poses[t])
        centre = ", ".join(f"{v:.1f}" for v in 1e3 * poses[t, :3])
        print(f"{t} | {centre} | {1e3 * np.linalg.norm(d, axis=1).max():.1f} | "
              f"{np.linalg.norm(inertia) / np.linalg.norm(d):.3f} | {relative(linear, x[t], rest)} | "
              f"{relative(up, x[t], rest)} | {relative(uf, x[t], rest)} | "
              f"{energy.jacobians(x[t]).min():.2f} / {energy.jacobians(rest + up).min():.2f}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    main(sys.argv[1], [int(a) for a in sys.argv[2:]])
