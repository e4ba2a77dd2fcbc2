"""Collision-aware correction: make a predicted step t -> t+1 safe against the rigid tool.

Input: the previous *safe* object surface positions ``x0`` (no contact with the tool
at pose t), the network's proposal ``x1`` (any values, finite), and the tool poses
at t and t+1. Both object and tool move linearly (vertex by vertex) over the step,
the motion ipctk's CCD checks. Output: positions ``x1'`` such that, over the motion
``x0 -> x1'`` against ``tool(t) -> tool(t+1)``, every object-surface/tool primitive pair
stays farther apart than min(CLEARANCE, CLEARANCE_RATIO x its distance at t)
(:mod:`colgnn_core.collision.clearance`: 0.18 mm and 0.5), hence no contact, no
intersection at t+1 (``x0`` being intersection-free and both surfaces closed), and no
"collision" for ipctk's ``is_step_collision_free`` with its default line-search
clearance min(0.2 d0, 1e-4 m) either. ``clearance=False`` asks for no contact only.

Algorithm (all vectorised, numpy float64):

1. **Detect** crossings over the step with the fast pipeline
   (:class:`~colgnn_core.collision.pipeline.CollisionDetector`: SDF-culled swept-box
   broad phase, the conservative deforming non-penetration filter, cubic-root narrow
   phase). Pairs flagged ``degenerate`` count as crossings. The first detection runs
   on the raw network output: its counts are the "before" counts.
2. **Project** object vertices with tool SDF below ``margin/2`` out along the SDF
   gradient to ``margin`` (plus the tool mesh's tessellation bound). Near a rim of the tool the gradient sends a
   vertex to the nearest face, which need not be the face it came through: on ``cylinder_banana`` a flank that the
   network presses against the roller's rim leaves partly through one face and partly through the other, and the
   triangles between fold (validation drag onto the flank: 0.697, 334 folded triangles after the tool pass, from a
   raw output with none). The scene's ``[correction] project = "least"`` corrects such a step twice: once leaving
   the vertices that a push of the same pass moved where the push put them (a push follows the face the vertex
   crossed), once projecting every vertex, and keeps the result that moves the proposal less, a certified one
   before a fallback. Leaving pushed vertices alone on every step (session 38) broke poor proposals: the physics
   prior alone behind the correction went from 0.45 to 4.04 on a held-out 14 mm press and drag. Only steps where
   the first way actually held a vertex below the trigger pay for the second.
3. **Resolve** crossings by moving object vertices at t+1 only, along the unit
   normal at t+1 of the crossing pair, towards the side where the pair *started*:
   an object vertex through a tool face moves itself; a tool vertex through an object
   face moves the face's vertices with minimal-norm barycentric weights
   (``w_k / sum w^2``, so the face point under the tool vertex moves by exactly the
   required amount); an object edge through a tool edge moves its end points likewise.
   Two directions come from the tool instead (session 61). An object edge through a *flat* tool edge (its two
   faces coplanar: a triangulation edge inside a blade's side, :func:`flat_edges`) leaves along that face's outward
   normal: the pair's normal e x h is then any direction in the face's plane, and on the torus's held-out press and
   drag it pushed edges through the blade's side along the blade by up to 14 mm, across the cut's opposite wall. A
   face pierced by a tool vertex moves along its own normal only where that leaves through the vertex's normal cone
   (:func:`in_vertex_cone`), else along the vertex's mean outward normal: on a torn or flipped proposal the face's
   normal is arbitrary, and faces under the blade's edge were carried along it. Pairs that crossed in and out keep
   the pair's normal where it crossed. On the torus's held-out press and drag and tilted slice, self-intersecting
   published frames 29 -> 9 and 33 -> 13 of 61-62, tool-pass fallbacks 6 -> 1 and 6 -> 3.
   The amount brings the pair to ``margin`` on its start side at t+1 (plus
   ``margin * iteration`` on later passes). A pair that ends on its start side with
   the margin to spare crossed *in and out* during the step (a face the network
   swings across the cone's tip and back): a push at t+1 would only move its
   crossing time, so it is pushed where it crossed instead, along its normal at the
   time of impact t*, by ``margin / t*`` at t+1 (the margin at t*). On the bunny's
   first three family trajectories (self stage on) this took the steps with a
   tool-pass fallback from 27 to 12 of 117. Several pushes on one vertex are merged by the scene's push rule
   (:func:`merge_pushes`): averaged (``mean``, the default), or the largest taken (``largest``). Averaging
   under-relaxes: a vertex that one pair pushes hard and a neighbouring pair only grazes moves by half what the
   first needs, so the passes repeat. Where the pushes on a vertex point to opposite sides (object edges across a
   thin blade) they cancel, and the budget runs out. On ``knife_torus`` the largest push halves the passes (66 to
   35 on its bench trajectory) and the fallback steps of its hard cuts (47 to 21-23 of 61-62). On a smooth
   roller it overshoots instead: ``cylinder_banana``'s hard press and drag goes from 0 to 2 tool fallbacks, with
   in-and-out pushes of up to 11 mm (5 mm averaged). The rule is a scene's ``[correction] push_rule``.

The margin is ``max(0.5 dhat, MIN_MARGIN)``: ipctk's CCD (the test oracle) treats pairs
closer than about 1e-4 m as colliding, so the published state keeps a 2e-4 m clearance.
4. **Keep clear** at t+1: object edges / faces closer than ``TRIGGER x margin`` to a tool
   edge / vertex (box join + exact segment and point-triangle distances) are pushed out
   along the tool's SDF gradient at their closest point, barycentric-weighted.
5. **Clearance over the step**: once 1-4 leave nothing to do, the additive CCD of
   :class:`~colgnn_core.collision.clearance.StepClearance` looks for pairs that come
   closer than the clearance *during* the step (a surface sliding along a curved tool:
   both ends at the margin, the chord between them nearer). Each one moves its object
   primitive at t+1 away from the tool primitive along their separation at the time found,
   t*, by (margin - d*) / t*, barycentric-weighted like 3.
6. Repeat 1-5 until the detection is clean, nothing is closer than ``TRIGGER x margin``
   and the clearance holds, at most ``max_iterations`` times. Each pass after the first examines (steps 1, 2
   and 4) only the primitives with a vertex that the pass before moved or flagged: every other primitive has
   the positions it had there, where it crossed nothing, needed no projection and was close to nothing, so it
   would again. The pairs are taken in sorted order, so the result is the same, bit for bit, as examining
   every primitive (``incremental=False``; tested on every scene). Step 5 always examines everything.
7. **Fallback** when the budget runs out: each vertex keeps the corrected proposal where a
   certificate (below) proves its triangles safe; the others give way (they *slide* along a
   tool that only translates, :func:`sliding_positions`, or else stay where they were), and
   only what still cannot be proved moves rigidly with the tool from the previous safe state.
   This is provably safe (below) and counted.

Safety of the fallback. Let R, p be the tool's rigid motion from t to t+1 (world
points ``y -> R y + p``); tool vertices are ``y1 = R y0 + p``. Put the region's
vertices at ``x1 = R x0 + p``. Every point of the region and of the tool then moves
as ``y(s) = [(1-s) I + s R] y0 + s p``: one affine map for all of them, invertible
for rotations below 180 degrees. An invertible affine map preserves incidence
(a point lies on a triangle / two segments meet only if their preimages do), so
primitives wholly inside the region cannot touch the tool during the step because
they did not at t. Every other object triangle gets the SDF certificate of the
broad phase: with ``s0``, ``s1`` lower bounds of the analytic SDF over the triangle
at both ends (vertex SDF minus the longest edge), ``d`` its largest vertex motion,
``D`` the tool's largest vertex motion and ``m`` the tool mesh's tessellation bound,
``s0 + s1 - d - D - 2m > 0`` proves that no point of the triangle comes within 0 of
the tool mesh during the step (the SDF is 1-Lipschitz, the tool mesh is within ``m``
of the analytic shape, and the two ends bound every intermediate time). Triangles
without a certificate join the region, which grows until every triangle is covered
(in the limit the whole object moves with the tool: safe by the affine argument).
Edges and vertices belong to triangles, so all primitive pairs are covered.

Sliding certificate. When the tool only translates, by v over the step, a point x(s) is as far
from the tool mesh at time s as z(s) = x(s) - s v is from the mesh at t, and at least
sdf(z(s)) - m (sdf the analytic SDF at t). The SDF of a convex shape is convex, so
sdf(z) >= sdf(a) + g_a . (z - a) for any point a and the analytic gradient g_a there, a
subgradient (tested for every shape). A triangle's swept points z = sum_k w_k z_k(s) are
bilinear in (w, s), so that linear bound is least at one of its six corners z_k(0), z_k(1).
Anchored at each corner in turn, a bound above c + m proves the triangle; a triangle it cannot
prove is split into four, up to SLIDING_DEPTH times (a triangle wrapped around the knife's edge),
and a piece with a corner below c + m is too close and fails at once. It proves what the
Lipschitz bound cannot: a surface that a knife slides past along its own plane. Giving way
uses it: a sliding vertex follows the proposal in the tool's frame except for any part toward
the tool along g at x0, so its own path keeps sdf >= sdf(x0). The fallback raises, in every
unproved triangle, the vertices of its lowest tier (proposal, giving way, rigid), so the
rounds end with every triangle proved or wholly rigid. On the torus's held-out 4.3 cm press
and drag (session 22) the rigid-only fallback carried the cut's walls 6.4 mm a step along with
the blade: relative error 1.87, now 0.72.

The clearance survives the fallback. The certificate with ``2 c`` more on the right,
``s0 + s1 - d - D - 2m > 2c``, keeps every point of the triangle farther than c from the
tool mesh over the step (c = CLEARANCE). For a pair inside the region the separation
vector moves by the same affine map, y(s) - z(s) = [(1-s) I + s R] (y0 - z0), whose
smallest singular value is cos(theta/2) for a rotation by theta: the distance stays at
least cos(theta/2) d0 >= CLEARANCE_RATIO d0 for theta <= 2 arccos(CLEARANCE_RATIO) = 120
degrees (the Predictor refuses larger turns in one call).

Locality: only vertices the projection, a crossing pair, a clearance push or the fallback region touch
are written; every other entry of the output is the input array's value, bit for bit.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from colgnn_core.collision.broad_phase import Surface, ToolSDFBound, active_ring
from colgnn_core.collision.clearance import CLEARANCE_RATIO, StepClearance, warm_up_clearance
from colgnn_core.collision.kernels import (barycentric_clamped, box_join, changed_rows, longest_edge, map_pairs,
                                           point_triangle, prim_boxes, prims_meeting_box, row_distance, row3,
                                           row_order, segment_distance, segment_params, sphere_bounds, vertex_boxes)
from colgnn_core.collision.pipeline import CollisionDetector
from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import quat_to_matrix

__all__ = ["CorrectionResult", "CollisionCorrector", "rigid_step", "certify_triangles", "certify_translating",
           "sliding_positions", "flat_edges", "in_vertex_cone", "merge_pushes", "MAX_ROTATION", "PROPOSED", "SLIDE",
           "STAY", "RIGID"]

DEFAULT_MARGIN_FRACTION = 0.5  # safety margin = this x the scene's dhat ...
# ... but at least this (m). ipctk's Tight-Inclusion CCD (the test oracle) reports a pair as colliding when it comes
# closer than min(0.2 x its initial distance, 1e-4 m), measured with a box (L-inf) test, i.e. up to sqrt(3) x 1e-4 m
# apart; the published state keeps every object-tool pair at least TRIGGER x MIN_MARGIN = 2e-4 m apart.
MIN_MARGIN = 2.5e-4
TRIGGER = 0.8                  # a vertex / pair closer than TRIGGER x margin at t+1 is pushed back to the margin
DEFAULT_MAX_ITERATIONS = 12  # knife_torus ci, 300 random steps: 49 fallback steps with 6, 0 with 12
MAX_ROTATION = 2.0 * math.acos(CLEARANCE_RATIO)  # rad: the largest tool turn in one step the clearance proof covers
MIN_PUSH_TIME = 0.05  # a clearance push at t+1 is (margin - d*) / max(t*, this): bounded for an early t*
SLIDING_DEPTH = 4  # the sliding certificate splits a triangle it cannot prove into four, this many times
PUSH_RULES = ("mean", "largest")  # how several pushes on one vertex merge (merge_pushes)
PROJECT_RULES = ("all", "least")  # which vertices step 2 projects (module docstring)
PROPOSED, SLIDE, STAY, RIGID = 0, 1, 2, 3  # the fallback's tiers: the corrected proposal, slide along the tool,
                                          # stay where it was at t, move rigidly with the tool


@dataclass
class CorrectionResult:
    """What :meth:`CollisionCorrector.correct` did.

    positions: [N,3] corrected positions (a new array; rows not touched equal the input's);
    *_before: crossing pairs in the raw proposal (vertex_face = object-vertex/tool-face plus
    tool-vertex/object-face); *_after: crossings the fast check finds in the output;
    penetrating_after: surface vertices with tool SDF < 0 in the output; iterations: detect
    passes used; fallback: the safe fallback was used; region: vertices moved rigidly by the
    fallback; stayed: vertices it let slide along the tool or kept where they were at t; moved: vertices whose
    position changed; clearance_pairs: pairs found closer than the clearance during the step (summed over passes);
    alternative: the step was corrected both ways of step 2 (``project="least"``; iterations and timings then
    count both); timings_ms: detect, resolve, clearance, fallback, total.
    """

    positions: np.ndarray
    vertex_face_before: int = 0
    edge_edge_before: int = 0
    vertex_face_after: int = 0
    edge_edge_after: int = 0
    penetrating_after: int = 0
    iterations: int = 0
    fallback: bool = False
    region: int = 0
    stayed: int = 0
    moved: int = 0
    clearance_pairs: int = 0
    alternative: bool = False
    timings_ms: dict = field(default_factory=dict)


def rigid_step(pose0: np.ndarray, pose1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R [3,3], p [3]) with ``world(pose1) = R world(pose0) + p`` for every tool-frame point."""
    R0 = quat_to_matrix(np.asarray(pose0[3:], dtype=np.float64))
    R1 = quat_to_matrix(np.asarray(pose1[3:], dtype=np.float64))
    R = R1 @ R0.T
    return R, np.asarray(pose1[:3], dtype=np.float64) - R @ np.asarray(pose0[:3], dtype=np.float64)


def certify_triangles(faces: np.ndarray, x0: np.ndarray, x1: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                      tool_motion: float, margin: float, clearance: float = 0.0) -> np.ndarray:
    """Bool [F]: triangles proved to stay farther than ``clearance`` (m; 0: contact-free) from the tool mesh over
    the step by the SDF bound (module docstring).

    faces [F,3]; x0, x1 [N,3] positions at both ends; s0, s1 [N] analytic tool SDF of those
    positions (m); tool_motion: largest tool vertex motion D (m); margin: tessellation bound m.
    """
    out = []
    for X, s in ((x0, s0), (x1, s1)):
        a, b, c = X[faces[:, 0]], X[faces[:, 1]], X[faces[:, 2]]
        L = np.sqrt(np.max([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=0))
        sv = s[faces]
        out.append(np.maximum(sv.max(axis=1) - L, sv.min(axis=1) - L / np.sqrt(3.0)))
    d = np.sqrt(((x1 - x0) ** 2).sum(1))[faces].max(axis=1)
    # 1e-12 relative slack absorbs rounding in the sums above (all terms are O(1e-1) m or less).
    return out[0] + out[1] - d - tool_motion - 2.0 * margin - 2.0 * clearance > 1e-12


def certify_translating(z0: np.ndarray, z1: np.ndarray, sdf_grad, margin: float, clearance: float = 0.0,
                        depth: int = SLIDING_DEPTH) -> np.ndarray:
    """Bool [K]: triangles proved to stay farther than ``clearance`` (m) from the tool mesh over a step in which the
    tool only translates, by the convexity of its SDF (module docstring, "sliding certificate").

    z0, z1 [K,3,3]: the triangles' corners at both ends in the frame that moves with the tool, expressed at its pose
    at t (z1 = x1 minus the tool's translation); sdf_grad: points [P,3] -> (analytic SDF [P] (m), unit subgradients
    [P,3]) of the tool at that pose; margin: the tessellation bound m (m). A triangle that the bound anchored at its
    corners cannot prove is split into four, ``depth`` times at most.
    """
    K = len(z0)
    Z = np.concatenate([z0, z1], axis=1)  # [K,6,3]: the corners at both ends
    f, g = sdf_grad(Z.reshape(-1, 3))
    f, g = f.reshape(K, 6), g.reshape(K, 6, 3)
    # Anchored at corner a, every point of the swept triangle has SDF >= f_a + min_j g_a . (Z_j - Z_a).
    reach = np.einsum("kac,kjc->kaj", g, Z) - np.einsum("kac,kac->ka", g, Z)[:, :, None]
    # The analytic SDFs read up to 1e-12 m high (their sqrt guard); 1e-11 m of slack covers it and the rounding.
    need = margin + clearance + 1e-11
    ok = (f + reach.min(axis=2)).max(axis=1) > need
    # Split only what may still be proved: a corner below the bound is a point of the sweep that is too close.
    todo = np.flatnonzero(~ok & (f.min(axis=1) > need))
    if depth > 0 and len(todo):
        ok[todo] = certify_translating(_split4(z0[todo]), _split4(z1[todo]), sdf_grad, margin, clearance,
                                       depth - 1).reshape(-1, 4).all(axis=1)
    return ok


def _split4(t: np.ndarray) -> np.ndarray:
    """Triangles [K,3,3] -> their four midpoint children [4K,3,3], each triangle's children contiguous. A corner's
    path over the step is linear, so the children's sweeps cover the parent's exactly."""
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
    return np.stack([np.stack(v, axis=1) for v in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))],
                    axis=1).reshape(-1, 3, 3)


class CollisionCorrector:
    """Per-scene collision-aware correction (topology and tool are fixed; build once).

    Args:
        faces: [F,3] object surface triangles (outward), indexing position arrays of ``n_vertices`` rows.
        n_vertices: rows of the position arrays (vertices not used by ``faces`` are never touched).
        tool: the scene's :class:`~colgnn_core.geometry.tools.Tool` (convex, analytic SDF).
        dhat: the scene's IPC distance (m); the safety margin is ``margin_fraction * dhat``.
        max_iterations: correction passes before the fallback.
        push_rule: how the pushes of one pass on one vertex merge, one of PUSH_RULES (:func:`merge_pushes`).
        project: which vertices step 2 projects, one of PROJECT_RULES: ``all`` near or in the tool, or ``least``:
            the step is also corrected with the vertices that a push of the same pass moved left out of the
            projection, and the result that moves the proposal less is kept (module docstring, step 2).
        incremental: after the first pass, each pass examines only the primitives with a vertex that the pass
            before moved or flagged (the same outcome, bit for bit, as examining every primitive: False, the
            reference that the tests compare with).
    """

    def __init__(self, faces: np.ndarray, n_vertices: int, tool, dhat: float, *,
                 margin_fraction: float = DEFAULT_MARGIN_FRACTION, max_iterations: int = DEFAULT_MAX_ITERATIONS,
                 push_rule: str = "mean", project: str = "all", incremental: bool = True):
        if not dhat > 0:
            raise InputError(f"dhat must be > 0 (m), got {dhat}")
        if max_iterations < 0:
            raise InputError(f"max_iterations must be >= 0, got {max_iterations}")
        if push_rule not in PUSH_RULES:
            raise InputError(f"push_rule must be one of {', '.join(PUSH_RULES)}, got {push_rule!r}")
        if project not in PROJECT_RULES:
            raise InputError(f"project must be one of {', '.join(PROJECT_RULES)}, got {project!r}")
        self.push_rule = push_rule
        self.project = project
        self.incremental = bool(incremental)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.n = int(n_vertices)
        self.tool = tool
        self.detector = CollisionDetector(self.faces, tool.faces, self.n, len(tool.vertices), tool)
        _warm_up_kernels()
        self.surface = self.detector.object_surface
        self.tool_surface = self.detector.tool_surface
        self.surface_ids = self.surface.vertices
        bound = ToolSDFBound(tool)
        if not bound.usable:
            raise InputError(f"the {tool.shape} tool mesh is not convex: the correction's SDF bounds need a convex "
                             "tool")
        self.mesh_margin = bound.margin              # tool mesh sticks out of the analytic shape by at most this
        self.margin = max(float(margin_fraction) * float(dhat), MIN_MARGIN)
        self.max_iterations = int(max_iterations)
        self.tool_local = np.asarray(tool.vertices, dtype=np.float64)
        # The tool lies in this ball about its frame origin: the analytic shapes are extreme at mesh vertices
        # (rims, corners); the slack covers rounding.
        self.tool_radius = float(tool.bounding_radius()) * (1 + 1e-6) + self.mesh_margin + 1e-9
        self.clearance = StepClearance(self.surface, self.tool_surface, bound)
        self.tool_flat_edges = flat_edges(self.tool_surface, self.tool_local)
        self.fallbacks = 0                           # running count over this corrector's life
        self._extra_v: list = []                     # proximity pushes of the current pass
        self._extra_d: list = []

    # -- helpers --------------------------------------------------------------------------------------------------
    def _hits(self, res, x1, T1) -> tuple[dict, dict, int]:
        """(pairs to resolve per kind, their times of impact per kind (inf: degenerate), number of real crossings).

        Real crossings are the narrow phase's hits. A *degenerate* pair (coplanar over the whole step,
        parallel edges) is not decided by the narrow phase; it is resolved too when its primitives are
        closer than the margin at t+1 (far ones cannot touch without a neighbouring non-degenerate
        pair crossing first; the exact oracle checks this in the tests)."""
        out, toi, n_hit = {}, {}, 0
        for k in ("vf", "fv", "ee"):
            nr = getattr(res, k)
            pairs = getattr(res.survivors, k)
            n_hit += int(nr.hit.sum())
            m = nr.hit.copy()
            deg = np.flatnonzero(nr.degenerate & ~nr.hit)
            if len(deg):
                m[deg[self._pair_distance(k, pairs[deg], x1, T1) < self.margin]] = True
            sel = np.flatnonzero(m)
            sel = sel[row_order(pairs[sel])]  # sorted: the pushes must not depend on which pairs were examined
            out[k] = pairs[sel]
            toi[k] = np.where(nr.hit[sel], nr.toi[sel], np.inf)
        return out, toi, n_hit

    def _flagged(self, hits: dict) -> np.ndarray:
        """Object vertex ids [K] of this pass's crossing pairs ``hits`` and proximity pairs (with repeats)."""
        F, E = self.surface.faces, self.surface.edges
        return np.concatenate([hits["vf"][:, 0], F[hits["fv"][:, 1]].ravel(), E[hits["ee"][:, 0]].ravel(),
                               *self._extra_v]).astype(np.int64)

    def _pair_distance(self, kind: str, pairs: np.ndarray, X, T) -> np.ndarray:
        """Distances [K] (m) at one time between the primitives of candidate pairs."""
        F, E = self.surface.faces, self.surface.edges
        G, H = self.tool_surface.faces, self.tool_surface.edges
        if kind == "ee":
            e, h = E[pairs[:, 0]], H[pairs[:, 1]]
            return _segment_distance(X[e[:, 0]], X[e[:, 1]], T[h[:, 0]], T[h[:, 1]])
        if kind == "vf":
            p, f, Q = X[pairs[:, 0]], G[pairs[:, 1]], T
        else:
            p, f, Q = T[pairs[:, 0]], F[pairs[:, 1]], X
        return _point_triangle_distance(p, Q[f[:, 0]], Q[f[:, 1]], Q[f[:, 2]])

    def _project(self, x1: np.ndarray, pose1: np.ndarray, sdf: np.ndarray | None = None,
                 ids: np.ndarray | None = None, held: np.ndarray | None = None) -> tuple[int, int]:
        """Push surface vertices ``ids`` (default all) with SDF < TRIGGER x margin (+ mesh bound) out to margin
        along the gradient; in place. ``sdf`` [len(ids)]: their SDF if known (exact below the trigger). ``held``:
        sorted vertex ids left where they are even below the trigger. Returns (vertices pushed, vertices held
        below the trigger)."""
        S = self.surface_ids if ids is None else ids
        level = TRIGGER * self.margin + self.mesh_margin
        d = self._surface_sdf(x1, pose1, level, S) if sdf is None else sdf
        low = np.flatnonzero(d < level)
        n_held = 0
        if held is not None and len(held) and len(low):
            keep = np.isin(S[low], held, assume_unique=True)
            n_held = int(keep.sum())
            low = low[~keep]
        if len(low):
            idx = S[low]
            dl, g = self.tool.sdf_grad(x1[idx], pose1)
            x1[idx] += (self.margin + self.mesh_margin - dl)[:, None] * g
        return len(low), n_held

    def clear_points(self, points: np.ndarray, pose: np.ndarray) -> int:
        """Move points [K,3] (m) that belong to no surface face (a tet mesh's interior vertices) out of the tool at
        ``pose`` [7]: any point closer than margin (+ mesh bound) goes to that distance along the SDF gradient; in
        place. Returns the number moved.

        Interior vertices are interpolated from the surface, so a tool deep inside the object can leave one inside
        the tool while the surface is clean; they take no part in contact, so moving them changes no face."""
        if len(points) == 0:
            return 0
        level = self.margin + self.mesh_margin
        origin = np.asarray(pose, dtype=np.float64)[:3]
        near = np.flatnonzero(np.linalg.norm(points - origin, axis=1) - self.tool_radius < level)
        if len(near) == 0:
            return 0
        d, g = self.tool.sdf_grad(points[near], pose)
        low = d < level
        points[near[low]] += (level - d[low])[:, None] * g[low]
        return int(low.sum())

    def _proximity(self, x1: np.ndarray, T1: np.ndarray, pose1: np.ndarray, sdf: np.ndarray, lmax: float,
                   ids: np.ndarray) -> tuple[list, list, int]:
        """Pushes for object edges / faces closer than TRIGGER x margin to a tool edge / vertex at t+1.

        Vertex-face proximity (object vertex, tool face) is the projection's job (the SDF bounds the
        distance to the inscribed tool mesh). ``lmax``: the longest surface edge at t+1 (m); ``sdf``: of the
        surface vertices ``ids`` [K], exact below ``self._proximity_level + lmax``; every primitive whose vertices
        are all among ``ids`` is examined. Returns (vertex id arrays, displacement arrays, pairs); the pairs in
        sorted order, so that a pass's pushes do not depend on which other primitives it examined."""
        trig = TRIGGER * self.margin
        ve, vf = self.surface.vertex_edges, self.surface.vertex_faces
        ee, ee_d, alpha, fv, fv_d, w3 = _proximity_pairs(
            x1, np.ascontiguousarray(T1), ids, sdf, self._proximity_level, lmax, trig, self.surface.edges,
            self.surface.faces, ve[0], ve[1], vf[0], vf[1], self.tool_surface.edges)
        oe, of = row_order(ee), row_order(fv)
        ee, ee_d, alpha, fv, fv_d, w3 = ee[oe], ee_d[oe], alpha[oe], fv[of], fv_d[of], w3[of]
        vids, disps = [], []
        for ids, dist, w in ((self.surface.edges[ee[:, 0]], ee_d, np.stack([1.0 - alpha, alpha], axis=1)),
                             (self.surface.faces[fv[:, 1]], fv_d, w3)):
            if len(ids) == 0:
                continue
            point = np.einsum("kj,kjc->kc", w, x1[ids])
            # Push along the tool's outward SDF direction at the object's closest point.
            _, g = self.tool.sdf_grad(point, pose1)
            scale = (self.margin - dist) / (w * w).sum(1)
            for j in range(w.shape[1]):
                vids.append(ids[:, j])
                disps.append((scale * w[:, j])[:, None] * g)
        return vids, disps, len(ee) + len(fv)

    def _surface_sdf(self, x: np.ndarray, pose: np.ndarray, below: float, ids: np.ndarray | None = None
                     ) -> np.ndarray:
        """SDF [K] (m) of the surface vertices ``ids`` (default all) at ``pose``: exact where it may be below
        ``below``, elsewhere a lower bound >= ``below``: the distance to the ball (about the tool-frame origin)
        holding the tool."""
        S = self.surface_ids if ids is None else ids
        origin = np.asarray(pose, dtype=np.float64)[:3]
        lb, _ = sphere_bounds(x, x, S, origin, origin, self.tool_radius)
        idx = np.flatnonzero(lb < below)
        if len(idx):
            lb[idx] = self.tool.sdf(x[S[idx]], pose)
        return lb

    @property
    def _proximity_level(self) -> float:
        """trigger distance + the tool mesh's tessellation bound (m): see :func:`_proximity_pairs`."""
        return TRIGGER * self.margin + self.mesh_margin

    def _pushes(self, hits: dict, toi: dict, x0, x1, T0, T1, iteration: int) -> tuple[np.ndarray, np.ndarray]:
        """Merged displacements (vertex ids [K], displacements [K,3]; :attr:`push_rule`) resolving the crossing
        pairs ``hits`` (their times of impact ``toi``, per kind [K]).

        A pair that ends on its start side at t+1 with the margin to spare crossed *in and out* during the step: a
        push along its t+1 normal moves its crossing time without removing it. Such a pair is pushed where it
        crossed instead: along its normal at the time of impact t*, away from the side it started on, by
        margin / t* at t+1, i.e. by the margin at t* (minimal-norm barycentric weights as below)."""
        F, E = self.surface.faces, self.surface.edges
        G, H = self.tool_surface.faces, self.tool_surface.edges
        extra = self.margin * iteration
        vids, disps = list(self._extra_v), list(self._extra_d)

        def unit(v):
            n = np.sqrt((v * v).sum(1))
            return v / np.maximum(n, 1e-300)[:, None], n

        def side(f0, f1):
            s = np.sign(f0)
            return np.where(s == 0, np.where(f1 == 0, 1.0, -np.sign(f1)), s)

        def crossed(kind, s, sep):
            """(in-and-out mask, time of impact clamped below by MIN_PUSH_TIME, amount at t+1) of a kind's hits."""
            t = toi[kind]
            io = np.isfinite(t) & (s * sep >= self.margin)
            tc = np.clip(np.where(np.isfinite(t), t, 1.0), MIN_PUSH_TIME, 1.0)
            return io, tc, self.margin / tc

        vf = hits["vf"]
        if len(vf):  # object vertex p vs tool face (a,b,c): move p to the face's start side
            i, f = vf[:, 0], G[vf[:, 1]]
            n1, _ = unit(np.cross(T1[f[:, 1]] - T1[f[:, 0]], T1[f[:, 2]] - T1[f[:, 0]]))
            n0 = np.cross(T0[f[:, 1]] - T0[f[:, 0]], T0[f[:, 2]] - T0[f[:, 0]])
            f0 = ((x0[i] - T0[f[:, 0]]) * n0).sum(1)
            sep = ((x1[i] - T1[f[:, 0]]) * n1).sum(1)
            s = side(f0, sep)
            amount = np.maximum(self.margin - s * sep, 0.0) + extra
            io, tc, a_io = crossed("vf", s, sep)
            if io.any():
                a, b, c = (_at(T0[f[:, k]], T1[f[:, k]], tc) for k in range(3))
                nt, _ = unit(np.cross(b - a, c - a))
                n1 = np.where(io[:, None], nt, n1)
                amount = np.where(io, a_io, amount)
            vids.append(i)
            disps.append((s * amount)[:, None] * n1)
        fv = hits["fv"]
        if len(fv):  # tool vertex p vs object face (a,b,c): move the face away from p, barycentric weights
            j, f = fv[:, 0], F[fv[:, 1]]
            a1, b1, c1 = x1[f[:, 0]], x1[f[:, 1]], x1[f[:, 2]]
            n1, _ = unit(np.cross(b1 - a1, c1 - a1))
            n0 = np.cross(x0[f[:, 1]] - x0[f[:, 0]], x0[f[:, 2]] - x0[f[:, 0]])
            f0 = ((T0[j] - x0[f[:, 0]]) * n0).sum(1)
            sep = ((T1[j] - a1) * n1).sum(1)
            s = side(f0, sep)
            amount = np.maximum(self.margin - s * sep, 0.0) + extra
            w = _barycentric_clamped(T1[j], a1, b1, c1)
            io, tc, a_io = crossed("fv", s, sep)
            if io.any():
                a, b, c = (_at(x0[f[:, k]], x1[f[:, k]], tc) for k in range(3))
                nt, _ = unit(np.cross(b - a, c - a))
                n1 = np.where(io[:, None], nt, n1)
                w = np.where(io[:, None], _barycentric_clamped(_at(T0[j], T1[j], tc), a, b, c), w)
                amount = np.where(io, a_io, amount)
            scale = amount / (w * w).sum(1)
            # The face leaves the tool through the tool vertex's normal cone: the face's own normal is arbitrary on a
            # torn or flipped proposal (module docstring, step 3).
            d = -s[:, None] * n1
            d[~io] = in_vertex_cone(d[~io], j[~io], T1, self.tool_surface)
            for k in range(3):
                vids.append(f[:, k])
                disps.append((scale * w[:, k])[:, None] * d)
        ee = hits["ee"]
        if len(ee):  # object edge (u,v) vs tool edge (k,l): move (u,v) to its start side
            e, h = E[ee[:, 0]], H[ee[:, 1]]
            u1, v1, k1, l1 = x1[e[:, 0]], x1[e[:, 1]], T1[h[:, 0]], T1[h[:, 1]]
            n1, nn = unit(np.cross(v1 - u1, l1 - k1))
            alpha, beta = _segment_params(u1, v1, k1, l1)
            # Parallel edges: use the closest-point direction instead of the (undefined) cross product.
            cp = (u1 + alpha[:, None] * (v1 - u1)) - (k1 + beta[:, None] * (l1 - k1))
            cpn, cpl = unit(cp)
            par = nn <= 1e-12 * np.maximum(np.sqrt(((v1 - u1) ** 2).sum(1) * ((l1 - k1) ** 2).sum(1)), 1e-300)
            n1 = np.where(par[:, None] & (cpl > 0)[:, None], cpn, n1)
            n0 = np.cross(x0[e[:, 1]] - x0[e[:, 0]], T0[h[:, 1]] - T0[h[:, 0]])
            f0 = ((x0[e[:, 0]] - T0[h[:, 0]]) * n0).sum(1)
            sep = ((u1 - k1) * n1).sum(1)
            s = np.where(par, 1.0, side(f0, sep))
            amount = np.maximum(self.margin - s * sep, 0.0) + extra
            io, tc, a_io = crossed("ee", s, sep)
            io &= ~par
            if io.any():
                u, v = _at(x0[e[:, 0]], x1[e[:, 0]], tc), _at(x0[e[:, 1]], x1[e[:, 1]], tc)
                k_, l_ = _at(T0[h[:, 0]], T1[h[:, 0]], tc), _at(T0[h[:, 1]], T1[h[:, 1]], tc)
                nt, nnt = unit(np.cross(v - u, l_ - k_))
                io &= nnt > 0
                at_t, _ = _segment_params(u, v, k_, l_)
                n1 = np.where(io[:, None], nt, n1)
                alpha = np.where(io, at_t, alpha)
                amount = np.where(io, a_io, amount)
            # A flat tool edge (its two faces coplanar) is no feature of the tool: e x h is then any direction in the
            # face's plane, e.g. along a blade for an object edge through its side, and the push slides the edge
            # along the face. It leaves along the face's outward normal instead (module docstring, step 3).
            d = s[:, None] * n1
            flat = np.flatnonzero(self.tool_flat_edges[ee[:, 1]])
            if len(flat):
                g = G[self.tool_surface.edge_faces[ee[flat, 1], 0]]
                tf = np.where(io[flat], tc[flat], 1.0)[:, None]  # where it crossed, or at t+1
                a, b, c = ((1.0 - tf) * T0[g[:, k]] + tf * T1[g[:, k]] for k in range(3))
                d[flat] = _unit_rows(np.cross(b - a, c - a))
                # At t+1 the amount takes the edge's point the margin beyond the face's plane (in and out: the
                # margin where it crossed, as above).
                later = ~io[flat]
                at1 = flat[later]
                depth = ((u1[at1] + alpha[at1, None] * (v1[at1] - u1[at1]) - T1[g[later, 0]]) * d[at1]).sum(1)
                amount[at1] = np.maximum(self.margin - depth, 0.0) + extra
            w = np.stack([1.0 - alpha, alpha], axis=1)
            scale = amount / (w * w).sum(1)
            for k in range(2):
                vids.append(e[:, k])
                disps.append((scale * w[:, k])[:, None] * d)
        if not vids:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        vid = np.concatenate(vids)
        disp = np.concatenate(disps)
        keep = np.abs(disp).sum(1) > 0
        return merge_pushes(vid[keep], disp[keep], self.push_rule)

    def _clearance_pushes(self, cl, x0, x1, T0, T1) -> tuple[np.ndarray, np.ndarray]:
        """Merged displacements at t+1 (vertex ids [K], [K,3]; :attr:`push_rule`) for the pairs of ``cl`` (a
        ClearanceResult) that come closer than the clearance mid-step: at the time t* found, the object primitive
        moves away from the tool primitive along their separation by (margin - d*) / t* at t+1, i.e. by margin - d*
        at t*; minimal-norm barycentric weights as for crossings."""
        F, E = self.surface.faces, self.surface.edges
        G, H = self.tool_surface.faces, self.tool_surface.edges
        vids, disps = [], []
        for kind in ("vf", "fv", "ee"):
            pairs = getattr(cl, kind)
            if len(pairs) == 0:
                continue
            t = cl.t[kind]
            amount = (self.margin - cl.d[kind]) / np.maximum(t, MIN_PUSH_TIME)
            if kind == "vf":  # object vertex vs tool face
                i, g = pairs[:, 0], G[pairs[:, 1]]
                p = _at(x0[i], x1[i], t)
                a, b, c = (_at(T0[g[:, k]], T1[g[:, k]], t) for k in range(3))
                w = _closest_barycentric(p, a, b, c)
                n = _unit_rows(p - (w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c))
                vids.append(i)
                disps.append(amount[:, None] * n)
                continue
            if kind == "fv":  # tool vertex vs object face
                j, f = pairs[:, 0], F[pairs[:, 1]]
                p = _at(T0[j], T1[j], t)
                a, b, c = (_at(x0[f[:, k]], x1[f[:, k]], t) for k in range(3))
                w = _closest_barycentric(p, a, b, c)
                n = _unit_rows(w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c - p)
                ids = f
            else:  # object edge vs tool edge
                e, h = E[pairs[:, 0]], H[pairs[:, 1]]
                u, v = _at(x0[e[:, 0]], x1[e[:, 0]], t), _at(x0[e[:, 1]], x1[e[:, 1]], t)
                k_, l_ = _at(T0[h[:, 0]], T1[h[:, 0]], t), _at(T0[h[:, 1]], T1[h[:, 1]], t)
                alpha, beta = _segment_params(u, v, k_, l_)
                n = _unit_rows(u + alpha[:, None] * (v - u) - (k_ + beta[:, None] * (l_ - k_)))
                w = np.stack([1.0 - alpha, alpha], axis=1)
                ids = e
            scale = amount / (w * w).sum(1)
            for k in range(w.shape[1]):
                vids.append(ids[:, k])
                disps.append((scale * w[:, k])[:, None] * n)
        if not vids:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        return merge_pushes(np.concatenate(vids), np.concatenate(disps), self.push_rule)

    # -- the correction -------------------------------------------------------------------------------------------
    def correct(self, x0: np.ndarray, x1: np.ndarray, pose0: np.ndarray, pose1: np.ndarray,
                tool0: np.ndarray | None = None, tool1: np.ndarray | None = None, *, clearance: bool = True
                ) -> CorrectionResult:
        """Corrected positions for the step ``x0 -> x1`` ([N,3] m, ``x0`` safe) with the tool ``pose0 -> pose1``.

        ``tool0``/``tool1`` [M,3] may pass ``tool.world_vertices(pose)`` when the caller has them.
        ``clearance``: keep the clearance over the step (module docstring); False: only no contact (the
        Predictor's inner substeps, whose motion nobody sees).
        """
        t_start = time.perf_counter()
        x0 = np.asarray(x0, dtype=np.float64)
        x1 = np.array(x1, dtype=np.float64)  # a copy: the caller's proposal is not modified
        if x0.shape != (self.n, 3) or x1.shape != (self.n, 3):
            raise InputError(f"positions must be [{self.n},3], got {x0.shape} and {x1.shape}")
        if not np.all(np.isfinite(x1)):
            raise InputError("the proposed positions contain NaN or inf")
        pose0 = np.asarray(pose0, dtype=np.float64)
        pose1 = np.asarray(pose1, dtype=np.float64)
        T0 = self.tool.world_vertices(pose0) if tool0 is None else np.asarray(tool0, dtype=np.float64)
        T1 = self.tool.world_vertices(pose1) if tool1 is None else np.asarray(tool1, dtype=np.float64)
        turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(pose0[3:], pose1[3:])))))
        if clearance and turn > MAX_ROTATION:
            raise InputError(f"the tool turns by {math.degrees(turn):.1f} deg in one step; the clearance guarantee "
                             f"covers up to {math.degrees(MAX_ROTATION):.0f} deg")
        out, held = self._tool_pass(x0, x1.copy(), pose0, pose1, T0, T1, clearance, self.project == "least")
        if held:
            # Some pushed vertex was left out of the projection: correct the step the other way too, and keep the
            # smaller correction (a certified one before a fallback).
            other, _ = self._tool_pass(x0, x1.copy(), pose0, pose1, T0, T1, clearance, False)
            cost = [(r.fallback, float(np.sum((r.positions - x1) ** 2))) for r in (out, other)]
            kept, dropped = (other, out) if cost[1] < cost[0] else (out, other)
            kept.iterations += dropped.iterations
            kept.alternative = True
            kept.timings_ms = {k: v + dropped.timings_ms.get(k, 0.0) for k, v in kept.timings_ms.items()}
            out = kept
        self.fallbacks += int(out.fallback)
        out.timings_ms["total"] = 1e3 * (time.perf_counter() - t_start)
        return out

    def step_clean(self, x0: np.ndarray, x1: np.ndarray, pose0: np.ndarray, pose1: np.ndarray, T0: np.ndarray,
                   T1: np.ndarray, *, clearance: bool = True) -> bool:
        """Whether the step ``x0 -> x1`` ([N,3] m, ``x0`` safe) with the tool ``pose0 -> pose1`` (its vertices T0, T1
        [M,3]) already meets the guarantee, by the check that ends a tool pass out of passes: no crossing, every
        surface vertex outside the tool mesh's bound, and with ``clearance`` the clearance over the step."""
        res = self.detector.detect(x0, x1, T0, T1, pose0, pose1, check=False)
        hits, _, _ = self._hits(res, x1, T1)
        n_hits = len(hits["vf"]) + len(hits["fv"]) + len(hits["ee"])
        return self._verified(n_hits, x0, x1, pose0, pose1, T0, T1, clearance)

    def _verified(self, n_hits: int, x0, x1, pose0, pose1, T0, T1, clearance: bool, known=None) -> bool:
        """The guarantee's check of a step whose detection found ``n_hits`` pairs to resolve (:meth:`step_clean`);
        ``known``: the first pass's broad phase for the clearance check (``StepClearance.check``)."""
        d = self._surface_sdf(x1, pose1, self.mesh_margin)
        if n_hits or np.any(d < self.mesh_margin):
            return False
        return not clearance or self.clearance.check(x0, x1, T0, T1, pose0, pose1, known=known).violations == 0

    def _tool_pass(self, x0: np.ndarray, x1: np.ndarray, pose0: np.ndarray, pose1: np.ndarray, T0: np.ndarray,
                   T1: np.ndarray, clearance: bool, hold_pushed: bool) -> tuple[CorrectionResult, int]:
        """Steps 1-7 in place on ``x1`` (the proposal's copy) for :meth:`correct`. ``hold_pushed``: step 2 leaves out
        the vertices that a push of the same pass moved. Returns the result (its ``timings_ms["total"]`` left to
        the caller) and how many vertices below the projection's trigger were held so."""
        raw = x1.copy()
        out = CorrectionResult(positions=x1)
        n_held = 0
        t_detect = t_resolve = t_clear = 0.0
        clean = False
        active = None  # bool [N]: the vertices whose primitives this pass examines (None: all; see below)
        # The first pass's broad phase, with the clearance's growth, also serves the clearance check at the end
        # (StepClearance.check ``known``): only primitives moved since then need a broad phase of their own.
        grow = self.clearance.clearance if clearance and self.incremental else 0.0
        known = None
        for it in range(self.max_iterations + 1):
            t = time.perf_counter()
            res = self.detector.detect(x0, x1, T0, T1, pose0, pose1, check=False, active=active,
                                       clearance=grow if it == 0 else 0.0)
            if it == 0 and grow > 0:
                known = (res.candidates, raw)  # x1 is still the proposal here: raw is its copy
            hits, toi, _ = self._hits(res, x1, T1)
            t_detect += time.perf_counter() - t
            out.iterations = it + 1
            if it == 0:
                out.vertex_face_before = int(res.vf.hit.sum() + res.fv.hit.sum())
                out.edge_edge_before = int(res.ee.hit.sum())
            t = time.perf_counter()
            n_hits = len(hits["vf"]) + len(hits["fv"]) + len(hits["ee"])
            if it == self.max_iterations:
                # Out of budget: only check whether the last pass left anything.
                clean = self._verified(n_hits, x0, x1, pose0, pose1, T0, T1, clearance, known)
                t_clear += time.perf_counter() - t
                break
            start = x1.copy()
            ids = self.surface_ids if active is None else active_ring(active, self.surface)
            lmax = longest_edge(x1, self.surface.edges)  # once per pass: SDF reach and the kernel
            sdf = self._surface_sdf(x1, pose1, self._proximity_level + lmax, ids)
            self._extra_v, self._extra_d, n_close = self._proximity(x1, T1, pose1, sdf, lmax, ids)
            flagged = self._flagged(hits)
            vid, disp = self._pushes(hits, toi, x0, x1, T0, T1, it)
            if len(vid):
                x1[vid] += disp
            held = vid if hold_pushed and len(vid) else None  # merge_pushes: sorted, unique
            pushed, n = self._project(x1, pose1, None if len(vid) or n_close else sdf, ids, held)
            n_held += n
            t_resolve += time.perf_counter() - t
            if n_hits == 0 and pushed == 0 and n_close == 0:
                if not clearance:
                    clean = True
                    break
                t = time.perf_counter()
                cl = self.clearance.check(x0, x1, T0, T1, pose0, pose1, known=known)
                if cl.violations == 0:
                    t_clear += time.perf_counter() - t
                    clean = True
                    break
                out.clearance_pairs += cl.violations
                vid, disp = self._clearance_pushes(cl, x0, x1, T0, T1)
                x1[vid] += disp
                t_clear += time.perf_counter() - t
            if self.incremental:
                # The next pass examines only primitives with a vertex that this pass moved or flagged: every other
                # primitive has the same positions as in this pass, where it crossed nothing, was close to nothing
                # and needed no projection, so it would again (the same pairs and distances: an exact shortcut).
                active = changed_rows(x1, start)
                active[flagged] = True
        out.timings_ms = {"detect": 1e3 * t_detect, "resolve": 1e3 * t_resolve, "clearance": 1e3 * t_clear,
                          "fallback": 0.0}
        if clean:
            out.vertex_face_after = out.edge_edge_after = 0
        else:
            t = time.perf_counter()
            out.region, out.stayed = self._fallback(x0, x1, pose0, pose1, T0, T1,
                                                    self.clearance.clearance if clearance else 0.0)
            out.fallback = True
            res = self.detector.detect(x0, x1, T0, T1, pose0, pose1, check=False)
            out.vertex_face_after = int(res.vf.hit.sum() + res.fv.hit.sum())
            out.edge_edge_after = int(res.ee.hit.sum())
            out.timings_ms["fallback"] = 1e3 * (time.perf_counter() - t)
        out.penetrating_after = int(np.sum(self._surface_sdf(x1, pose1, 0.0) < 0))
        out.moved = int(changed_rows(x1, raw).sum())
        return out, n_held

    def _fallback(self, x0, x1, pose0, pose1, T0, T1, clearance: float = 0.0) -> tuple[int, int]:
        """The certified fallback in place on ``x1`` (:meth:`fallback_tiers`). Returns (vertices it moved rigidly with
        the tool, vertices it let only slide along the tool or kept at ``x0``)."""
        tier = self.fallback_tiers(x0, x1, pose0, pose1, T0, T1, clearance, slide=True)
        return int((tier == RIGID).sum()), int(((tier == SLIDE) | (tier == STAY)).sum())

    def rigid_fallback(self, x0, x1, pose0, pose1, T0, T1, clearance: float = 0.0,
                       region: np.ndarray | None = None) -> np.ndarray:
        """The certified fallback without its sliding tier (module docstring), in place on ``x1`` [N,3]; returns the
        rigid region (bool [N]): the vertices of ``region`` (bool [N], default none) and those that
        :meth:`fallback_tiers` moves with the tool. With ``x1 = x0`` outside the region this is the previous state
        moved only where the tool requires (the self-contact fallback, :mod:`.self_contact`)."""
        return self.fallback_tiers(x0, x1, pose0, pose1, T0, T1, clearance, region) == RIGID

    def fallback_tiers(self, x0, x1, pose0, pose1, T0, T1, clearance: float = 0.0,
                       region: np.ndarray | None = None, *, slide: bool = False) -> np.ndarray:
        """The certified fallback in place on ``x1`` [N,3] (module docstring). Every vertex keeps ``x1`` (tier
        PROPOSED), gives way, or moves rigidly with the tool from ``x0`` to ``R x0 + p`` (RIGID); ``region`` (bool
        [N]) starts RIGID. Giving way is sliding along the tool (SLIDE, :func:`sliding_positions`) with ``slide`` and
        a tool that only translates, else going back to ``x0`` (STAY). Each round, in every triangle that no
        certificate proves to stay farther than ``clearance`` (m) from the tool over the step, the vertices of its
        lowest tier go up one; a wholly rigid triangle is safe by the affine argument, so the rounds end. Returns
        the tiers (int8 [N])."""
        R, p = rigid_step(pose0, pose1)
        D = float(np.sqrt(((T1 - T0) ** 2).sum(1)).max())
        S = self.surface_ids
        s0 = np.full(self.n, np.inf)
        move = _sliding_translation(T0, T1)
        give_way = x0.copy()
        sliding = slide and move is not None
        if sliding:  # the SDF and its gradient at t in one evaluation
            s0[S], g0 = self.tool.sdf_grad(x0[S], pose0)
            give_way[S] = sliding_positions(x0[S], x1[S], move, g0)
        else:
            s0[S] = self.tool.sdf(x0[S], pose0)
        levels = np.stack([x1, give_way, x0 @ R.T + p])  # [3,N,3], by step: proposed, giving way, rigid
        carried = len(levels) - 1  # the rigid step
        step = np.zeros(self.n, dtype=np.int8)
        if region is not None:
            step[np.asarray(region, dtype=bool)] = carried
        rows = np.arange(self.n)
        F = self.faces
        for _ in range(2 * len(S) + 1):  # every round raises a vertex: at most 2|S| rounds (in practice a few)
            cand = levels[step, rows]
            s1 = np.full(self.n, np.inf)
            s1[S] = self.tool.sdf(cand[S], pose1)
            ok = certify_triangles(F, x0, cand, s0, s1, D, self.mesh_margin, clearance)
            ok |= (step[F] == carried).all(axis=1)
            if move is not None and not ok.all():
                todo = np.flatnonzero(~ok)
                ok[todo] = certify_translating(x0[F[todo]], (cand - move)[F[todo]],
                                               lambda z: self.tool.sdf_grad(z, pose0), self.mesh_margin, clearance)
            if ok.all():
                break
            # Raise only each failing triangle's lowest step: a vertex is not carried off with the tool while a
            # neighbour can still give way.
            bad = F[~ok]
            sb = step[bad]
            step[np.unique(bad[sb == sb.min(axis=1, keepdims=True)])] += 1
        x1[:] = levels[step, rows]
        return np.array([PROPOSED, SLIDE if sliding else STAY, RIGID], dtype=np.int8)[step]


def flat_edges(surface: Surface, V: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Bool [E]: the edges of a closed ``surface`` (vertex positions V [N,3]) whose two faces are coplanar, the sine
    of the angle between their normals at most ``tol`` (a triangulation edge inside a flat side)."""
    G = surface.faces
    a, b, c = (V[G[:, k]] for k in range(3))
    n = _unit_rows(np.cross(b - a, c - a))
    fa, fb = surface.edge_faces.T
    ok = fb >= 0
    s = np.sqrt((np.cross(n[fa], n[np.where(ok, fb, fa)]) ** 2).sum(1))
    return ok & (s <= tol) & ((n[fa] * n[np.where(ok, fb, fa)]).sum(1) > 0)


def in_vertex_cone(d: np.ndarray, verts: np.ndarray, T: np.ndarray, surface: Surface) -> np.ndarray:
    """Unit directions [K,3]: each ``d`` [K,3] (unit) where it lies in the normal cone of its convex tool vertex
    ``verts`` [K] (positions T [M,3] of ``surface``'s vertices), i.e. where it points away from every edge at the
    vertex, d . (T[u] - T[v]) <= 0; else the vertex's mean outward normal (the normalised sum of its faces'
    normals), which lies inside the cone. On a blade's cutting edge that is straight down; the nearer of the faces'
    normals instead would push a face under the edge sideways, and the passes stop converging."""
    ve_off, ve_ids = surface.vertex_edges
    vf_off, vf_ids = surface.vertex_faces
    return _vertex_cone_kernel(np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(verts, dtype=np.int64),
                               np.ascontiguousarray(T, dtype=np.float64), ve_off, ve_ids, surface.edges, vf_off,
                               vf_ids, surface.faces)


@njit(cache=True)
def _vertex_cone_kernel(d, verts, T, ve_off, ve_ids, edges, vf_off, vf_ids, faces):
    out = d.copy()
    for k in range(d.shape[0]):
        v = verts[k]
        inside = True
        for q in range(ve_off[v], ve_off[v + 1]):
            e = ve_ids[q]
            u = edges[e, 0] if edges[e, 1] == v else edges[e, 1]
            w0, w1, w2 = T[u, 0] - T[v, 0], T[u, 1] - T[v, 1], T[u, 2] - T[v, 2]
            if d[k, 0] * w0 + d[k, 1] * w1 + d[k, 2] * w2 > 1e-9 * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2):
                inside = False
                break
        if inside:
            continue
        m0 = m1 = m2 = 0.0
        for q in range(vf_off[v], vf_off[v + 1]):
            a, b, c = faces[vf_ids[q], 0], faces[vf_ids[q], 1], faces[vf_ids[q], 2]
            p0, p1, p2 = T[b, 0] - T[a, 0], T[b, 1] - T[a, 1], T[b, 2] - T[a, 2]
            r0, r1, r2 = T[c, 0] - T[a, 0], T[c, 1] - T[a, 1], T[c, 2] - T[a, 2]
            n0, n1, n2 = p1 * r2 - p2 * r1, p2 * r0 - p0 * r2, p0 * r1 - p1 * r0
            ln = max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2), 1e-300)
            m0 += n0 / ln
            m1 += n1 / ln
            m2 += n2 / ln
        lm = max(math.sqrt(m0 * m0 + m1 * m1 + m2 * m2), 1e-300)
        out[k, 0], out[k, 1], out[k, 2] = m0 / lm, m1 / lm, m2 / lm
    return out


def merge_pushes(vid: np.ndarray, disp: np.ndarray, rule: str = "mean") -> tuple[np.ndarray, np.ndarray]:
    """One displacement per vertex from several: (sorted unique vertex ids [K], displacements [K,3] m) from the
    pushes ``disp`` [P,3] (m) on vertices ``vid`` [P]. ``mean``: their average; ``largest``: the one of largest
    norm (the last in input order among equal norms)."""
    uniq, inv = np.unique(vid, return_inverse=True)
    if rule == "largest":
        order = np.lexsort(((disp * disp).sum(1), inv))  # by vertex, then by norm: each vertex's last is its largest
        last = np.r_[inv[order][1:] != inv[order][:-1], True] if len(order) else np.zeros(0, dtype=bool)
        return uniq, disp[order[last]]
    if rule != "mean":
        raise InputError(f"push rule must be one of {', '.join(PUSH_RULES)}, got {rule!r}")
    cnt = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    acc = np.stack([np.bincount(inv, weights=disp[:, c], minlength=len(uniq)) for c in range(3)], axis=1)
    return uniq, acc / cnt[:, None]


def sliding_positions(x0: np.ndarray, x1: np.ndarray, move: np.ndarray, g0: np.ndarray) -> np.ndarray:
    """The fallback's SLIDE positions [K,3] (m): in the frame that moves with a tool that only translates by ``move``
    [3], each vertex follows the proposal ``x1`` [K,3] from ``x0`` [K,3] except for any part of it toward the tool
    along the unit SDF subgradient ``g0`` [K,3] at ``x0``. The SDF is convex, so no point of that straight path in
    the tool's frame is nearer the tool than ``x0`` was."""
    u = x1 - x0 - move
    toward = np.minimum((u * g0).sum(axis=1), 0.0)
    return x0 + move + u - toward[:, None] * g0


def _sliding_translation(T0: np.ndarray, T1: np.ndarray) -> np.ndarray | None:
    """The tool's translation [3] (m) over a step in which it does not turn (every vertex moves by the same vector
    within 1e-12 m), else None."""
    move = T1 - T0
    if np.ptp(move, axis=0).max() > 1e-12:
        return None
    return move.mean(axis=0)


@njit(cache=True)
def _segment_params_kernel(u, v, k, l):
    K = u.shape[0]
    alpha, beta = np.empty(K), np.empty(K)
    for i in range(K):
        alpha[i], beta[i] = segment_params(row3(u, i), row3(v, i), row3(k, i), row3(l, i))
    return alpha, beta


@njit(cache=True)
def _segment_distance_kernel(u, v, k, l):
    out = np.empty(u.shape[0])
    for i in range(u.shape[0]):
        out[i] = segment_distance(row3(u, i), row3(v, i), row3(k, i), row3(l, i))[0]
    return out


@njit(cache=True)
def _point_triangle_kernel(p, a, b, c):
    dist = np.empty(p.shape[0])
    w = np.empty((p.shape[0], 3))
    for i in range(p.shape[0]):
        dist[i], w[i, 0], w[i, 1], w[i, 2] = point_triangle(row3(p, i), row3(a, i), row3(b, i), row3(c, i))
    return dist, w


@njit(cache=True)
def _barycentric_clamped_kernel(p, a, b, c):
    w = np.empty((p.shape[0], 3))
    for i in range(p.shape[0]):
        w[i, 0], w[i, 1], w[i, 2] = barycentric_clamped(row3(p, i), row3(a, i), row3(b, i), row3(c, i))
    return w


def _unit_rows(v: np.ndarray) -> np.ndarray:
    """The rows of ``v`` [K,3] scaled to unit length (zero rows stay zero)."""
    return v / np.maximum(np.sqrt((v * v).sum(1)), 1e-300)[:, None]


def _rows(*arrays):
    return tuple(np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3) for x in arrays)


def _at(A0: np.ndarray, A1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows [K,3] of the straight motion A0 -> A1 ([K,3]) at the times t [K] in [0,1]."""
    return A0 + t[:, None] * (A1 - A0)


def _segment_params(u, v, k, l) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (alpha on u-v, beta on k-l), each [K] in [0,1], of (approximately) closest points."""
    return _segment_params_kernel(*_rows(u, v, k, l))


def _segment_distance(u, v, k, l) -> np.ndarray:
    """Segment-segment distances [K] (closest points, with the end-point distances as a safeguard)."""
    return _segment_distance_kernel(*_rows(u, v, k, l))


def _point_triangle_distance(p, a, b, c) -> np.ndarray:
    """Exact point-triangle distances [K]: plane distance when the projection is inside, else the nearest edge."""
    return _point_triangle_kernel(*_rows(p, a, b, c))[0]


def _closest_barycentric(p, a, b, c) -> np.ndarray:
    """Barycentric weights [K,3] of the point of triangle (a,b,c) closest to p."""
    return _point_triangle_kernel(*_rows(p, a, b, c))[1]


def _barycentric_clamped(p, a, b, c) -> np.ndarray:
    """Barycentric weights [K,3] of p's projection on triangle (a,b,c), clamped to the triangle, summing to 1."""
    return _barycentric_clamped_kernel(*_rows(p, a, b, c))


@njit(cache=True)
def _proximity_pairs(x1, T1, S, sdf, level, lmax, trig, edges, faces, ve_off, ve_ids, vf_off, vf_ids, tool_edges):
    """Object edges / faces within ``trig`` (m) of a tool edge / vertex at t+1.

    Candidates: primitives around surface vertices with SDF < ``level`` + ``lmax`` (the longest surface edge)
    whose bound (min vertex SDF - their longest edge) is below ``level`` (= trig + the tool mesh's
    tessellation bound); then a box join (boxes grown by ``trig``) and exact distances. Returns (ee [K,2] (object
    edge, tool edge), ee_dist, ee_alpha, fv [J,2] (tool vertex, object face), fv_dist, fv_w [J,3]).
    """
    n = x1.shape[0]
    s = np.full(n, np.inf)
    for i in range(len(S)):
        s[S[i]] = sdf[i]
    reach = level + lmax
    seen_e = np.zeros(edges.shape[0], dtype=np.bool_)
    seen_f = np.zeros(faces.shape[0], dtype=np.bool_)
    cand_e = np.empty(edges.shape[0], dtype=np.int64)
    cand_f = np.empty(faces.shape[0], dtype=np.int64)
    ne = nf = 0
    for i in range(len(S)):
        v = S[i]
        if not sdf[i] < reach:
            continue
        for q in range(ve_off[v], ve_off[v + 1]):
            e = ve_ids[q]
            if not seen_e[e]:
                seen_e[e] = True
                a, b = edges[e, 0], edges[e, 1]
                if min(s[a], s[b]) - row_distance(x1, a, x1, b) < level:
                    cand_e[ne] = e
                    ne += 1
        for q in range(vf_off[v], vf_off[v + 1]):
            f = vf_ids[q]
            if not seen_f[f]:
                seen_f[f] = True
                a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
                L = max(row_distance(x1, a, x1, b), row_distance(x1, b, x1, c), row_distance(x1, c, x1, a))
                if min(s[a], s[b], s[c]) - L < level:
                    cand_f[nf] = f
                    nf += 1
    cand_e, cand_f = cand_e[:ne], cand_f[:nf]
    elo, ehi = prim_boxes(x1, x1, edges, cand_e)
    flo, fhi = prim_boxes(x1, x1, faces, cand_f)
    elo -= trig
    ehi += trig
    flo -= trig
    fhi += trig
    # Only the tool's primitives that meet the candidates' region (their grown boxes' box) can pair with them.
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for blo, bhi in ((elo, ehi), (flo, fhi)):
        for a in range(3):
            if blo.shape[0]:
                lo[a], hi[a] = min(lo[a], blo[:, a].min()), max(hi[a], bhi[:, a].max())
    tsel = prims_meeting_box(T1, T1, np.arange(T1.shape[0]).reshape(-1, 1), lo, hi)
    hsel = prims_meeting_box(T1, T1, tool_edges, lo, hi)
    tvlo, tvhi = vertex_boxes(T1, T1, tsel)
    hlo, hhi = prim_boxes(T1, T1, tool_edges, hsel)
    pe = box_join(elo, ehi, hlo, hhi)
    ee = map_pairs(pe, cand_e, hsel)
    ee_dist, ee_alpha = _edge_tool_distances(x1, T1, edges, tool_edges, ee)
    ke = ee_dist < trig
    pf = box_join(tvlo, tvhi, flo, fhi)
    fv = map_pairs(pf, tsel, cand_f)
    fv_dist, fv_w = _tool_vertex_face_distances(x1, T1, faces, fv)
    kf = fv_dist < trig
    return ee[ke], ee_dist[ke], ee_alpha[ke], fv[kf], fv_dist[kf], fv_w[kf]


@njit(cache=True, parallel=True)
def _edge_tool_distances(x1, T1, edges, tool_edges, ee):
    """(distance [K], alpha [K] on the object edge) of the rows (object edge, tool edge) of ``ee`` at t+1."""
    dist, alpha = np.empty(ee.shape[0]), np.empty(ee.shape[0])
    for r in prange(ee.shape[0]):
        e, h = ee[r, 0], ee[r, 1]
        dist[r], alpha[r] = segment_distance(row3(x1, edges[e, 0]), row3(x1, edges[e, 1]), row3(T1, tool_edges[h, 0]),
                                             row3(T1, tool_edges[h, 1]))
    return dist, alpha


@njit(cache=True, parallel=True)
def _tool_vertex_face_distances(x1, T1, faces, fv):
    """(distance [K], barycentric weights [K,3]) of the rows (tool vertex, object face) of ``fv`` at t+1."""
    dist, w = np.empty(fv.shape[0]), np.empty((fv.shape[0], 3))
    for r in prange(fv.shape[0]):
        t, f = fv[r, 0], fv[r, 1]
        dist[r], w[r, 0], w[r, 1], w[r, 2] = point_triangle(row3(T1, t), row3(x1, faces[f, 0]), row3(x1, faces[f, 1]),
                                                            row3(x1, faces[f, 2]))
    return dist, w


_KERNELS_READY = False


def _warm_up_kernels() -> None:
    """Load (the first time on a machine: compile) the correction's numba kernels on a tiny case, so that
    the first real step is not the slow one."""
    global _KERNELS_READY
    if _KERNELS_READY:
        return
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    surf = Surface.from_faces(np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]]), 4)
    tool = x + [0.2, 0.2, 0.2]
    ve, vf = surf.vertex_edges, surf.vertex_faces
    _proximity_pairs(x, tool, surf.vertices, np.zeros(4), 1.0, 1.5, 1.0, surf.edges, surf.faces, ve[0], ve[1], vf[0],
                     vf[1], surf.edges)
    _segment_params(x, tool, x, tool)
    _segment_distance(x, tool, x, tool)
    _point_triangle_distance(x, x, tool, tool + 1)
    _barycentric_clamped(x, x, tool, tool + 1)
    warm_up_clearance()
    _KERNELS_READY = True
