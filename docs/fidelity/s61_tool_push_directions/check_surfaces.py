"""Per-frame surface check of rollouts (session 61): self-intersection (ipctk, the object alone), intersection with
the tool and a crossing straight step (ipctk, object against tool only), and triangles invalid against frame 0.

Usage: python check_surfaces.py STRIDE ROLLOUT.npz [ROLLOUT.npz ...]   (STRIDE 1: every frame)"""
import sys

from colgnn_core.collision.exact import self_intersects, tool_intersects, tool_step_free
from colgnn_core.collision.surface_validity import SurfaceValidity
from colgnn_core.io import load_sequence

stride = int(sys.argv[1])
for path in sys.argv[2:]:
    s = load_sequence(path)
    X, F, T, G = s.object_positions, s.object_faces, s.tool_positions, s.tool_faces
    val = SurfaceValidity(F, X[0])
    frames = list(range(stride, s.frames, stride)) if stride > 1 else list(range(1, s.frames))
    si = [t for t in frames if self_intersects(X[t], F)]
    ti = [t for t in frames if tool_intersects(X[t], F, T[t], G)]
    st = [t for t in frames if not tool_step_free(X[t-1], X[t], F, T[t-1], T[t], G)]
    inv = [int(val.invalid(X[t]).sum()) for t in frames]
    print(f"{path}: checked {len(frames)}; self-int {len(si)} {si}; tool-int {len(ti)}; tool-step-crossing {len(st)}; "
          f"invalid-face frames {sum(1 for i in inv if i)} max {max(inv)}")
