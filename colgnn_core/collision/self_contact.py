"""Self-contact in the correction: the object never passes through itself, and its surface stays valid.

After the tool pass (:class:`~colgnn_core.collision.correction.CollisionCorrector`) has made the step x0 -> x1 safe
against the tool, this stage makes it safe against the object itself. Input: the previous published state ``x0``
(self-clean and valid, by induction) and the tool-corrected proposal ``x1``. Output: positions ``x1'`` such that

* over the straight motion x0 -> x1', every *non-adjacent* pair of object-surface primitives (a vertex and a
  triangle not containing it, two edges without a common vertex) stays farther apart than
  min(SELF_CLEARANCE, SELF_RATIO x its distance in x0), hence no self-contact during the step and no
  self-intersection in x1' (x0 having none: a new intersection must start with such a contact);
* no triangle of x1' is flipped, collapsed or torn against the rest shape (:mod:`.surface_validity`), except in the
  one case stated under *Fallback*;
* the tool guarantee of the tool pass still holds for x0 -> x1' (every repair is followed by the tool pass again,
  and the fallback is certified for both).

Detection ("check"). Only near the deformed region: a surface vertex is *hot* when it is farther than ``quiet`` (m)
from where a rigid motion of the rest puts it, at t or t+1. The rigid motions A0 = (R0, p0) at t and A1 at t+1 are
chosen per step: the identity, or the least-squares fit of the surface to the rest at each time, refitted once to
the vertices that fit left quiet; whichever leaves fewer vertices hot (a pressed bunny tilts as a whole: half its
surface is hot against the rest, a tenth against the fit). Every point of a quiet primitive then stays within
``quiet`` of M(s) r + c(s) all step (the straight motion being a convex combination), with r its rest point and
M(s) = (1-s) R0 + s R1, whose smallest singular value is cos(theta/2) for the turn theta between R0 and R1. So a pair
of quiet primitives cannot come closer than cos(theta/2) x their rest distance minus 2 quiet: such pairs are examined
only if within (2 quiet + SELF_CLEARANCE) / cos(MAX_FIT_TURN/2) at rest (a list built once), and of those only the
ones whose bound, with each primitive's own deviation, falls to the threshold; a fit that turns more than
``MAX_FIT_TURN`` within the step is not used. Pairs with a hot vertex come from swept boxes grown by SELF_CLEARANCE
(the hot primitives against every primitive whose box meets the hot region's box; the joins themselves leave out
pairs that share a vertex, most of what overlaps on a surface): boxes farther apart than that cannot hold points
closer than it. Every candidate gets the additive CCD of :mod:`.clearance` (conservative: a pair
is passed only when its distance provably stays above the threshold), the object standing in for the tool.

Repair, up to ``max_rounds`` rounds, each followed by the tool pass:

1. invalid triangles: their vertices and one ring around them take the displacement x1 - x0 of their neighbours
   (a harmonic fill: the patch follows the surface around it, its own distortion removed); from round
   ``FILL_ROUNDS`` on they return to x0 (valid) instead. A triangle invalid in x0 as well (left by the fallback's
   one unrepaired case below) cannot be repaired relative to x0: its vertices and a ring take their neighbours'
   displacement *from the rest* (any rigid or affine motion of the surroundings is reproduced exactly, so the patch
   gets its rest shape moved with them), in every round;
2. self pairs: moved apart at t+1 along their separation at the time t* the CCD found, by
   (SELF_TARGET - d*) / t* split over the pair's four vertices with minimal-norm barycentric weights (the tool
   pass's pushes, both primitives movable); from round ``PUSH_ROUNDS`` on the pair's vertices and a ring
   return to x0 instead (a pair whose vertices all stay put keeps its x0 distance).

From round ``max(FILL_ROUNDS, PUSH_ROUNDS)`` on, a round is a function of its starting state alone (the check, the
return to x0 and the tool pass are deterministic). So when such a round ends where it started, every later round
would repeat it: the rounds stop there, with the outcome that running them all would give. On the bunny's family
trajectories the tool pass left such a fixed point on eight steps in a row, one round before the last.

Fallback, when the rounds run out, in two tiers. The local tier first (since session 52): a zone around the last
round's failing pairs and new invalid triangles goes back to x0 and the rest of the state keeps the last round's
tool-corrected positions. The tool guarantee is then either the tool pass's own final check of the whole step
(:meth:`CollisionCorrector.step_clean`), or, where that fails, the tool's certified fallback applied to that state
(every triangle certified, :meth:`CollisionCorrector.rigid_fallback`); and the state counts only if the full check
(the detection above, sound for any state) finds no self pair and no invalid triangle but those already invalid in
x0, which are then repaired as below (``_repair_kept``). Otherwise the failing vertices join the zone with 1, 2, 4,
8 rings, up to ``LOCAL_ROUNDS`` tries. So its safety is that of any checked state, and it keeps the network's shape
everywhere but near the defect, where the global tier below kept x0 over the whole surface. When a pair-free
state exists and the local tier would carry a region farther than the quiet distance, the global tier decides, as
before. The global tier: the previous published state moved only where the tool requires. Surface vertices
start at x0; the tool's certified fallback (:meth:`CollisionCorrector.rigid_fallback`) moves the region it cannot
certify rigidly with the tool (R x0 + p). Then, repeatedly, every pair and triangle with vertices both inside and
outside the region is checked (CCD, validity); the vertices of a failing one join the region with a ring around
them (from the ``GROW_DOUBLING``-th round on, 2, 4, 8, ... rings: a torn step can need the region to spread across
the object, and each round costs a check, so the rounds stay logarithmic in the object's size), and the tool
certificate is redone.

The soft border comes first (since session 23): a rigid region carried several millimetres with the tool tears
every ring of triangles around it, so the growth above doubled out to the whole object (the bunny and the banana
rode with the tool). Instead, ring k of the ``BLEND_RINGS`` rings around the region takes (1 - k / (BLEND_RINGS + 1))
of its own rigid step with the tool, a ramp to the still surface; the tool certificate is redone with the region
rigid; and the state counts only if the *full* check (the detection above, sound for any state, not the rigid
region's shortcut below) finds no self pair and no invalid triangle but those already invalid in x0. Where it does,
the failing pairs' and triangles' vertices join the region with a ring, up to ``SOFT_ROUNDS`` times; then the rigid
growth below, whose safety argument follows. So the soft border's safety is that of any checked state: (I1) and the
step property by the check, (I2) by the validity test, (I3) by the certificate. Safety of the rigid growth (x0
self-clean and valid):

* a pair with all four vertices outside the region does not move: its distance stays the x0 distance
  > SELF_RATIO x it;
* a pair inside the region moves by one affine map y(s) = [(1-s) I + s R] y0 + s p, whose smallest singular value
  is cos(theta/2) >= 1/2 > SELF_RATIO for a tool turn theta <= 120 degrees (the Predictor refuses larger turns): its
  distance stays >= d0 / 2;
* mixed pairs are checked, and a failing one grows the region by at least one vertex, so the loop ends; in the limit
  the whole surface moves rigidly (safe for the tool and for itself);
* the tool: the certificate of :mod:`.correction`, redone for the final region.

Validity under the fallback: triangles outside the region are x0's (valid); mixed triangles are checked (else they
join the region); a triangle inside the region keeps its edge lengths and area, and its normal turns by the tool's
rotation theta, so it can flip only if its x0 normal was within theta of 90 degrees from its rest normal. That case is
not repaired in that step (nothing safe is left to move): it is counted in ``invalid_after``, and the next step's
repair takes it back to its rest shape (repair step 1). A triangle outside the region that the fallback keeps invalid
(it was invalid in x0) is taken to its rest shape the same way when the result then passes the full check and the
tool certificate; otherwise it stays as x0 had it.

A carried region is the worse harm. On a drag the fallback's region moves with the tool, away from the network's
proposal; the next proposal is then far from that state, fails again, and the region is carried on (the glued
banana's held-out tilted slice: 16 fallbacks in a row, the surface dragged 59 mm, relative error 8.7 against 0.35
without the stage). So when the fallback would carry its region farther than the quiet distance in this step, and
one of the round's checked states had no self pair (its only defect an invalid triangle), that state is published
instead (the region only grows, so the fallback stops as soon as its region moves that far): it went through the
tool pass (I3) and the full pair check (I1); its invalid triangles (I2) are counted in ``invalid_after`` and repaired
from the rest in the next steps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from colgnn_core.collision.broad_phase import Surface
from colgnn_core.collision.clearance import MAX_ITERATIONS, clearance_pairs
from colgnn_core.collision.correction import CollisionCorrector, merge_pushes, rigid_step
from colgnn_core.collision.kernels import (changed_rows, grid_join_apart, grid_self_join_apart, map_pairs,
                                           point_triangle, point_triangle_distance, prim_boxes, prims_meeting_box,
                                           row3, segment_distance, segment_params, vertex_boxes)
from colgnn_core.collision.surface_validity import SurfaceValidity, rigid_fit_rows
from colgnn_core.errors import InputError

__all__ = ["SELF_CLEARANCE", "SELF_RATIO", "SELF_TARGET", "SelfCheck", "SelfContact", "SelfResult",
           "warm_up_self_contact"]

SELF_CLEARANCE = 5e-5   # m: no two non-adjacent surface primitives come closer during a step ...
SELF_RATIO = 0.4        # ... unless they started closer than SELF_CLEARANCE / SELF_RATIO: then this x d0
SELF_TARGET = 1e-4      # m: the gap a self push aims for at the time the CCD found
QUIET_FRACTION = 0.25   # quiet = this x the median rest edge: a vertex within it of rest is not "hot"
MAX_FIT_TURN = 0.5      # rad: a rigid fit turning more than this within a step is not used (module docstring)
MAX_ROUNDS = 6          # repair rounds (each followed by the tool pass) before the fallback
FILL_ROUNDS = 2         # rounds in which invalid patches follow their neighbours; later: back to x0
PUSH_ROUNDS = 3         # rounds in which self pairs are pushed apart; later: back to x0
FILL_ITERATIONS = 30    # Jacobi sweeps of the harmonic fill
MIN_PUSH_TIME = 0.05    # a push at t+1 is (target - d*) / max(t*, this)
STATELESS_ROUND = max(FILL_ROUNDS, PUSH_ROUNDS)  # from this round on a round depends on its starting state alone
GROW_DOUBLING = 3       # fallback rounds that grow the region by one ring; later rounds grow by 2, 4, 8, ... rings
BLEND_RINGS = 6         # the fallback's soft border: rings of a ramp between the carried region and the still surface
LOCAL_ROUNDS = 4        # the fallback's local tier: tries, the zone sent back to x0 grown by 1, 2, 4, 8 rings
SOFT_ROUNDS = 4         # soft-border tries, the region grown by the failing pairs and triangles between them
_NO_PAIRS = np.zeros((0, 2), dtype=np.int64)


@dataclass
class SelfCheck:
    """What one check of a step found.

    vf (vertex, face) and ee (edge, edge) [K,2]: pairs that may come closer than the threshold; t, d: per kind [K]
    the time in [0,1] and distance (m) where the CCD found it; invalid: bool [F] triangles invalid at t+1;
    candidates: pairs examined; hot: surface vertices counted hot.
    """

    vf: np.ndarray = field(default_factory=lambda: _NO_PAIRS)
    ee: np.ndarray = field(default_factory=lambda: _NO_PAIRS)
    t: dict = field(default_factory=dict)
    d: dict = field(default_factory=dict)
    invalid: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    candidates: int = 0
    hot: int = 0

    @property
    def pairs(self) -> int:
        return len(self.vf) + len(self.ee)

    @property
    def clean(self) -> bool:
        return self.pairs == 0 and not self.invalid.any()


@dataclass
class SelfResult:
    """What :meth:`SelfContact.correct` did.

    positions: [N,3] the output (a new array); pairs_before / invalid_before: self pairs and invalid triangles in the
    tool-corrected input; pairs_after / invalid_after: in the output (invalid_after is 0 unless the fallback left a
    rotated triangle flipped, or a pair-free state with invalid triangles was published instead of a carried region,
    module docstring); rounds: repair rounds used; fallback: the self fallback was used; region: its rigid
    region (vertices); fallback_rounds: rounds of the fallback's region growth (0 when it did not run or stopped
    at once; logarithmic in the object's size, see ``GROW_DOUBLING``); tool_fallback: a tool pass after a repair
    used the tool's fallback; moved: vertices whose position differs from the input; timings_ms: check, repair,
    tool, fallback, total.
    """

    positions: np.ndarray
    pairs_before: int = 0
    invalid_before: int = 0
    pairs_after: int = 0
    invalid_after: int = 0
    rounds: int = 0
    fallback: bool = False
    region: int = 0
    fallback_rounds: int = 0
    tool_fallback: bool = False
    local: bool = False
    moved: int = 0
    timings_ms: dict = field(default_factory=dict)


class SelfContact:
    """Self-contact and surface validity for one object surface (build once per scene).

    Args:
        faces: [F,3] object surface triangles (outward) indexing position arrays of ``n_vertices`` rows.
        n_vertices: rows of the position arrays.
        rest: [N,3] the rest positions (m) validity and "hot" refer to (the settled rest); self-clean.
        quiet: m; default QUIET_FRACTION x the median rest edge.
        max_rounds: repair rounds before the fallback.
    """

    def __init__(self, faces: np.ndarray, n_vertices: int, rest: np.ndarray, *, quiet: float | None = None,
                 max_rounds: int = MAX_ROUNDS):
        self.surface = Surface.from_faces(faces, n_vertices, name="object")
        self.n = int(n_vertices)
        self.rest = np.ascontiguousarray(rest, dtype=np.float64)
        if self.rest.shape != (self.n, 3) or not np.all(np.isfinite(self.rest)):
            raise InputError(f"rest must be a finite [{self.n},3] array, got shape {self.rest.shape}")
        if max_rounds < 0:
            raise InputError(f"max_rounds must be >= 0, got {max_rounds}")
        self.max_rounds = int(max_rounds)
        self.S = self.surface.vertices
        E = self.surface.edges
        lengths = np.linalg.norm(self.rest[E[:, 0]] - self.rest[E[:, 1]], axis=1)
        self.quiet = float(QUIET_FRACTION * np.median(lengths)) if quiet is None else float(quiet)
        self.validity = SurfaceValidity(self.surface.faces, self.rest)
        self.neighbours = _vertex_neighbours(E, self.n)
        warm_up_self_contact()
        reach = (2.0 * self.quiet + SELF_CLEARANCE) / np.cos(0.5 * MAX_FIT_TURN)
        every = np.zeros(self.n, dtype=np.bool_)
        every[self.S] = True
        vf, ee = _candidates(self.rest, self.rest, every, self.S, self.surface.faces, E, reach)
        (self.rest_vf, self.rest_vf_d, self.rest_ee, self.rest_ee_d,
         self.rest_gap) = _close_pairs(self.rest, vf, ee, self.surface.faces, E, reach)
        # The induction starts at rest: its pairs must be apart (a pair closer than ~1e-7 m is always flagged).
        if not self.rest_gap > 1e-6:
            raise InputError(f"the rest surface touches itself (closest non-adjacent pair {self.rest_gap:.3g} m)")

    # -- detection ------------------------------------------------------------------------------------------------
    def hot(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """Bool [N]: surface vertices farther than ``quiet`` from the step's rigid frames at t or t+1."""
        return self.deviation(x0, x1)[0] > self.quiet

    def deviation(self, x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, float]:
        """([N] m, sigma): each surface vertex's larger distance at t and t+1 from where the step's rigid motions of
        the rest put it (0 off the surface), and the smallest singular value cos(theta/2) of their blend (module
        docstring: the identity, or the surface's rigid fit, whichever leaves fewer vertices hot)."""
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        x1 = np.ascontiguousarray(x1, dtype=np.float64)
        return _best_deviation(x0, x1, self.rest, self.S, self.n, self.quiet, MAX_FIT_TURN)

    def check(self, x0: np.ndarray, x1: np.ndarray, *, moving: np.ndarray | None = None) -> SelfCheck:
        """Self pairs of the straight step x0 -> x1 ([N,3] m) that may come closer than the threshold, and the
        triangles invalid in x1.

        ``moving``: bool [N] (the fallback): only vertices marked move, the others stay at x0; pairs with all four
        vertices moving are skipped (one affine map, module docstring) and the quiet argument is not used."""
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        x1 = np.ascontiguousarray(x1, dtype=np.float64)
        F, E = self.surface.faces, self.surface.edges
        dev, sigma = self.deviation(x0, x1) if moving is None else (None, 1.0)
        hot = dev > self.quiet if moving is None else moving
        vf, ee = _candidates(x0, x1, hot, self.S, F, E, SELF_CLEARANCE)
        if moving is None:
            vf = np.concatenate([vf, self.rest_vf[_rest_pairs_needed(self.rest_vf, self.rest_vf_d, dev, hot, F, E,
                                                                     False, SELF_CLEARANCE, sigma)]])
            ee = np.concatenate([ee, self.rest_ee[_rest_pairs_needed(self.rest_ee, self.rest_ee_d, dev, hot, F, E,
                                                                     True, SELF_CLEARANCE, sigma)]])
        else:
            vf = vf[~_all_hot(vf, F, E, hot, False)]
            ee = ee[~_all_hot(ee, F, E, hot, True)]
        empty = _NO_PAIRS
        ok, t, d, _ = clearance_pairs(x0, x1, x0, x1, vf, empty, ee, F, E, F, E, SELF_CLEARANCE, SELF_RATIO,
                                      MAX_ITERATIONS)
        out = SelfCheck(candidates=len(ok), hot=int(hot.sum()), invalid=self.validity.invalid(x1))
        nv = len(vf)
        bad_vf, bad_ee = ~ok[:nv], ~ok[nv:]
        out.vf, out.ee = vf[bad_vf], ee[bad_ee]
        out.t = {"vf": t[:nv][bad_vf], "ee": t[nv:][bad_ee]}
        out.d = {"vf": d[:nv][bad_vf], "ee": d[nv:][bad_ee]}
        return out

    def pair_vertices(self, chk: SelfCheck) -> np.ndarray:
        """Sorted unique vertex ids [K] of the flagged pairs of ``chk``."""
        F, E = self.surface.faces, self.surface.edges
        return np.unique(np.concatenate([chk.vf[:, 0], F[chk.vf[:, 1]].ravel(), E[chk.ee].ravel()]))

    def failing(self, chk: SelfCheck, faces: np.ndarray) -> np.ndarray:
        """Bool [N]: the vertices of the triangles ``faces`` (bool [F]) and of ``chk``'s flagged pairs."""
        mask = np.zeros(self.n, dtype=np.bool_)
        mask[self.surface.faces[faces].ravel()] = True
        if chk.pairs:
            mask[self.pair_vertices(chk)] = True
        return mask

    # -- the stage ------------------------------------------------------------------------------------------------
    def correct(self, corrector: CollisionCorrector, x0: np.ndarray, x1: np.ndarray, pose0, pose1, T0, T1, *,
                clearance: bool = True) -> SelfResult:
        """The self stage for the step x0 -> x1 ([N,3] m; ``x1`` already through ``corrector``) with the tool
        ``pose0 -> pose1`` (tool vertices T0, T1 [M,3]); ``clearance`` as for the tool pass (module docstring)."""
        t_start = time.perf_counter()
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        x = np.array(x1, dtype=np.float64)
        ms = {"check": 0.0, "repair": 0.0, "tool": 0.0, "fallback": 0.0}
        out = SelfResult(positions=x)
        clean = False
        pair_free: tuple[int, np.ndarray] | None = None  # (invalid triangles, state): the best pair-free state
        start = x  # the state the last round started from
        for r in range(self.max_rounds + 1):
            if r > STATELESS_ROUND and np.array_equal(x, start):
                break  # a fixed point (module docstring): the remaining rounds would repeat this one
            start = x
            t = time.perf_counter()
            chk = self.check(x0, x)
            ms["check"] += 1e3 * (time.perf_counter() - t)
            if r == 0:
                out.pairs_before, out.invalid_before = chk.pairs, int(chk.invalid.sum())
            out.rounds = r
            if chk.clean:
                clean = True
                break
            if not chk.pairs and (pair_free is None or chk.invalid.sum() < pair_free[0]):
                pair_free = (int(chk.invalid.sum()), x)
            if r == self.max_rounds:
                break
            t = time.perf_counter()
            x = self._repair(chk, x0, x, r)
            ms["repair"] += 1e3 * (time.perf_counter() - t)
            t = time.perf_counter()
            c = corrector.correct(x0, x, pose0, pose1, T0, T1, clearance=clearance)
            ms["tool"] += 1e3 * (time.perf_counter() - t)
            x = c.positions
            out.tool_fallback |= c.fallback
        if not clean:
            t = time.perf_counter()
            fb = self._local_fallback(corrector, x0, x, chk, pose0, pose1, T0, T1, clearance)
            if fb is not None and pair_free is not None and self.carried(x0, fb[0], fb[1]) > self.quiet:
                fb = None  # module docstring: a carried region is the worse harm; the global tiers decide
            if fb is not None:
                out.local = True
            else:
                fb = self._fallback(corrector, x0, x, pose0, pose1, T0, T1, clearance,
                                    give_way=pair_free is not None)
            if fb is not None:
                out.fallback_rounds = fb[2]
            if fb is None or (pair_free is not None and self.carried(x0, fb[0], fb[1]) > self.quiet):
                x = pair_free[1]  # module docstring: a carried region is the worse harm
            else:
                x, region = fb[0], fb[1]
                out.fallback, out.region = True, int(region.sum())
            out.invalid_after = int(self.validity.invalid(x).sum())
            ms["fallback"] = 1e3 * (time.perf_counter() - t)
        out.positions = x
        out.moved = int(changed_rows(x, np.ascontiguousarray(x1, dtype=np.float64)).sum())
        ms["total"] = 1e3 * (time.perf_counter() - t_start)
        out.timings_ms = ms
        return out

    @staticmethod
    def carried(x0: np.ndarray, x: np.ndarray, region: np.ndarray) -> float:
        """m: how far the fallback's rigid ``region`` (bool [N]) moved from x0 [N,3] to x [N,3] (0 if empty)."""
        if not region.any():
            return 0.0
        return float(np.sqrt(((x[region] - x0[region]) ** 2).sum(axis=1)).max())

    def _repair(self, chk: SelfCheck, x0: np.ndarray, x: np.ndarray, r: int) -> np.ndarray:
        """One repair round (module docstring) on a copy of x."""
        F = self.surface.faces
        x = x.copy()
        patch = np.zeros(self.n, dtype=np.bool_)
        patch[F[chk.invalid].ravel()] = True
        if r >= PUSH_ROUNDS and chk.pairs:
            patch[self.pair_vertices(chk)] = True
        if patch.any():
            patch = _grow(patch, *self.neighbours)
            disp = x - x0
            if r < FILL_ROUNDS:
                disp = _harmonic_fill(disp, patch, *self.neighbours, FILL_ITERATIONS)
            else:
                disp[patch] = 0.0
            x[patch] = x0[patch] + disp[patch]
            inherited = self._inherited(chk, x0)
            if inherited.any():
                # Invalid in x0 as well (the fallback's one unrepaired case): following x0, or returning to it, keeps
                # the defect. These patches follow their neighbours' displacement from the rest instead: a rigid or
                # affine motion of the surroundings is harmonic, so the patch takes its rest shape moved the same way.
                self._to_rest_shape(x, inherited)
        if r < PUSH_ROUNDS and chk.pairs:
            vid, push = self._pushes(chk, x0, x)
            keep = ~patch[vid]
            x[vid[keep]] += push[keep]
        return x

    def _to_rest_shape(self, x: np.ndarray, patch: np.ndarray) -> None:
        """In place: the ``patch`` rows (bool [N]) of ``x`` [N,3] take the harmonic fill of their neighbours'
        displacement from the rest (the rest shape moved as the surroundings move)."""
        u = _harmonic_fill(x - self.rest, patch, *self.neighbours, FILL_ITERATIONS)
        x[patch] = self.rest[patch] + u[patch]

    def _inherited(self, chk: SelfCheck, x0: np.ndarray) -> np.ndarray:
        """Bool [N]: the vertices, and one ring, of triangles invalid in x0 and still invalid in the step's result."""
        if not chk.invalid.any():
            return np.zeros(self.n, dtype=np.bool_)
        return self._face_ring(chk.invalid & self.validity.invalid(x0))

    def _face_ring(self, faces: np.ndarray) -> np.ndarray:
        """Bool [N]: the vertices of the triangles ``faces`` (bool [F]) and one ring around them."""
        mask = np.zeros(self.n, dtype=np.bool_)
        mask[self.surface.faces[faces].ravel()] = True
        return _grow(mask, *self.neighbours) if mask.any() else mask

    def _pushes(self, chk: SelfCheck, x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Averaged displacements at t+1 (vertex ids [K], [K,3]) moving each flagged pair apart along its separation
        at t*, by (SELF_TARGET - d*) / t* over the four vertices with minimal-norm weights c_k / sum c^2 (the
        separation grows by exactly that amount at first order)."""
        vids, disps = [], []
        F, E = self.surface.faces, self.surface.edges
        for kind, pairs in (("vf", chk.vf), ("ee", chk.ee)):
            if len(pairs) == 0:
                continue
            t = chk.t[kind]
            amount = (SELF_TARGET - chk.d[kind]) / np.maximum(t, MIN_PUSH_TIME)
            if kind == "vf":
                ids = np.concatenate([pairs[:, :1], F[pairs[:, 1]]], axis=1)
            else:
                ids = np.concatenate([E[pairs[:, 0]], E[pairs[:, 1]]], axis=1)
            n, c = _separation(x0, x1, ids, t, kind == "ee")
            scale = amount / (c * c).sum(1)
            for k in range(4):
                vids.append(ids[:, k])
                disps.append((scale * c[:, k])[:, None] * n)
        return merge_pushes(np.concatenate(vids), np.concatenate(disps), "mean")

    def _local_fallback(self, corrector: CollisionCorrector, x0, x, chk: SelfCheck, pose0, pose1, T0, T1,
                        clearance: bool) -> tuple[np.ndarray, np.ndarray, int] | None:
        """The local tier of the fallback (module docstring): (positions [N,3], rigid region bool [N], rounds), or
        None. ``x`` [N,3]: the last round's state, ``chk`` its check. A zone around its failing pairs and new invalid
        triangles goes back to x0, the tool's certified fallback moves what it cannot prove safe, and the state counts
        only if the full check then finds no pair and no invalid triangle but those invalid in x0; otherwise the
        failing vertices join the zone with 1, 2, 4, ... rings, up to ``LOCAL_ROUNDS`` times."""
        c = corrector.clearance.clearance if clearance else 0.0
        kept = self.validity.invalid(x0)
        zone = self.failing(chk, chk.invalid & ~kept)
        for k in range(LOCAL_ROUNDS):
            zone = _grow_rings(zone, 2 ** k, *self.neighbours)
            base = x.copy()
            base[zone] = x0[zone]
            if corrector.step_clean(x0, base, pose0, pose1, T0, T1, clearance=clearance):
                region = np.zeros(self.n, dtype=np.bool_)  # the tool pass's own check passes: nothing to carry
            else:
                region = corrector.rigid_fallback(x0, base, pose0, pose1, T0, T1, c)
            chk = self.check(x0, base)
            bad = chk.invalid & ~kept
            if not chk.pairs and not bad.any():
                return *self._repair_kept(corrector, x0, base, region, pose0, pose1, T0, T1, clearance), k + 1
            grow = self.failing(chk, bad)
            zone |= grow
        return None

    def _fallback(self, corrector: CollisionCorrector, x0, x, pose0, pose1, T0, T1, clearance: bool, *,
                  give_way: bool = False) -> tuple[np.ndarray, np.ndarray, int] | None:
        """The self-and-tool fallback (module docstring): (positions [N,3], rigid region bool [N], rounds of the
        region's growth). With ``give_way`` (a pair-free state exists): None as soon as the region would be carried
        farther than the quiet distance. The region only grows and moves rigidly, so the first region that does so
        decides, and the remaining rounds, the costly ones, are skipped."""
        S, F = self.S, self.surface.faces
        c = corrector.clearance.clearance if clearance else 0.0
        base = x.copy()
        base[S] = x0[S]  # non-surface graph nodes keep their values: they take no part in contact
        region = corrector.rigid_fallback(x0, base, pose0, pose1, T0, T1, c)
        if give_way and self.carried(x0, base, region) > self.quiet:
            return None
        kept = self.validity.invalid(x0)  # invalid before the step: not the region's doing (see _repair_kept)
        soft = self._soft_border(corrector, x0, base, region, kept, pose0, pose1, T0, T1, c)
        if soft is not None and not (give_way and self.carried(x0, soft[0], soft[1]) > self.quiet):
            return *self._repair_kept(corrector, x0, soft[0], soft[1], pose0, pose1, T0, T1, clearance), 0
        for k in range(len(S) + 1):  # every round adds a vertex: at most |S| rounds (in practice a few)
            if give_way and self.carried(x0, base, region) > self.quiet:
                return None
            chk = self.check(x0, base, moving=region)
            mixed = chk.invalid & ~kept & ~region[F].all(axis=1)
            grow = self.failing(chk, mixed)
            if not (grow & ~region).any():
                break
            # More rings than needed, and twice as many every round from the GROW_DOUBLING-th on: each round is a
            # check, and a torn step can need the region to spread across the object. The guarantee is the same
            # (the loop ends only when no mixed pair or triangle fails); the round count becomes logarithmic.
            grow = _grow_rings(grow, 1 if k < GROW_DOUBLING else 2 ** min(k - GROW_DOUBLING + 1, 30), *self.neighbours)
            region = corrector.rigid_fallback(x0, base, pose0, pose1, T0, T1, c, region=region | grow)
        return *self._repair_kept(corrector, x0, base, region, pose0, pose1, T0, T1, clearance), k

    def _soft_border(self, corrector: CollisionCorrector, x0, base, region, kept, pose0, pose1, T0, T1, c: float
                     ) -> tuple[np.ndarray, np.ndarray] | None:
        """The fallback with a soft border instead of a rigid region grown across the object (module docstring):
        (positions [N,3], rigid region), or None. Ring k of the ``BLEND_RINGS`` rings around the rigid region takes
        (1 - k / (BLEND_RINGS + 1)) of its rigid step with the tool, a ramp to the still surface beyond; the tool
        certificate is redone with the region rigid (a border vertex it cannot prove goes back to x0 or joins the
        region); the result counts only if the full check finds no pair and no invalid triangle but those of
        ``kept`` (bool [F], invalid in x0). Otherwise the failing pairs' and triangles' vertices, with a ring, join
        the rigid region, up to ``SOFT_ROUNDS`` times. ``base`` [N,3]: x0 with ``region`` moved rigidly."""
        R, p = rigid_step(pose0, pose1)
        region, base = region.copy(), base.copy()  # the caller's state stays as it was if this gives up
        for _ in range(SOFT_ROUNDS):
            trial = base.copy()
            inner = region
            for ring in range(1, BLEND_RINGS + 1):  # ring k takes (1 - k/(BLEND_RINGS+1)) of its own rigid step
                outer = _grow(inner, *self.neighbours)
                new = outer & ~inner
                if not new.any():
                    break
                w = 1.0 - ring / (BLEND_RINGS + 1.0)
                trial[new] = x0[new] + w * (x0[new] @ R.T + p - x0[new])
                inner = outer
            if inner is region:
                return None  # the region is the whole surface already
            rigid = corrector.rigid_fallback(x0, trial, pose0, pose1, T0, T1, c, region=region)
            chk = self.check(x0, trial)
            bad = chk.invalid & ~kept
            if not chk.pairs and not bad.any():
                return trial, region | rigid
            grow = self.failing(chk, bad)
            region = corrector.rigid_fallback(x0, base, pose0, pose1, T0, T1, c,
                                              region=rigid | _grow(grow, *self.neighbours))
        return None

    def _repair_kept(self, corrector: CollisionCorrector, x0, base, region, pose0, pose1, T0, T1, clearance: bool
                     ) -> tuple[np.ndarray, np.ndarray]:
        """The fallback's result ``base`` with its invalid triangles taken to their rest shape as in repair step 1,
        where that is safe: the result made tool-safe again, the full check of the step clean and fewer invalid
        triangles than in ``base``. Else ``base`` unchanged.

        Two tries. First every invalid triangle, then the tool pass: a triangle inside the rigid region was invalid
        in x0 (the region moves rigidly from x0) and lies at the tool, where the rigid certificate would take it back
        into the region; the pass pushes it out of the tool instead, and the try counts only if the pass did not
        fall back. Then only the triangles outside the region (the fallback keeps x0 there), their patch kept off
        the region, with the rigid certificate redone (the region may grow)."""
        F = self.surface.faces
        invalid = self.validity.invalid(base)
        if not invalid.any():
            return base, region
        c = corrector.clearance.clearance if clearance else 0.0
        for everywhere in (True, False):
            faces = invalid if everywhere else invalid & ~region[F].all(axis=1)
            if not faces.any():
                continue
            patch = self._face_ring(faces)
            if not everywhere:
                patch &= ~region
            trial = base.copy()
            self._to_rest_shape(trial, patch)
            if everywhere:
                tool = corrector.correct(x0, trial, pose0, pose1, T0, T1, clearance=clearance)
                if tool.fallback:
                    continue
                trial, grown = tool.positions, region & ~patch
            else:
                grown = corrector.rigid_fallback(x0, trial, pose0, pose1, T0, T1, c, region=region)
            chk = self.check(x0, trial)
            if not chk.pairs and chk.invalid.sum() < invalid.sum():
                return trial, grown
        return base, region


# ------------------------------------------------------------------------------------------------------ kernels
def _vertex_neighbours(edges: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (offsets [n+1], neighbour ids) of the surface graph."""
    both = np.concatenate([edges, edges[:, ::-1]])
    order = np.argsort(both[:, 0], kind="stable")
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(both[:, 0], minlength=n), out=offsets[1:])
    return offsets, np.ascontiguousarray(both[order, 1])


@njit(cache=True)
def _grow(mask, offsets, nbrs):
    """mask [N] bool plus one ring of neighbours."""
    out = mask.copy()
    for v in range(mask.shape[0]):
        if mask[v]:
            for q in range(offsets[v], offsets[v + 1]):
                out[nbrs[q]] = True
    return out


@njit(cache=True)
def _grow_rings(mask, rings, offsets, nbrs):
    """mask [N] bool plus ``rings`` rings of neighbours (fewer when the mask stops growing)."""
    out = mask.copy()
    for _ in range(rings):
        nxt = _grow(out, offsets, nbrs)
        if (nxt == out).all():
            break
        out = nxt
    return out


@njit(cache=True)
def _harmonic_fill(disp, patch, offsets, nbrs, iterations):
    """Displacements [N,3] with the rows of ``patch`` replaced by the mean of their neighbours' (Jacobi sweeps;
    rows outside the patch are the boundary values)."""
    out = disp.copy()
    for v in range(patch.shape[0]):
        if patch[v]:
            out[v, 0] = out[v, 1] = out[v, 2] = 0.0
    nxt = out.copy()
    for _ in range(iterations):
        for v in range(patch.shape[0]):
            if not patch[v]:
                continue
            k = offsets[v + 1] - offsets[v]
            if k == 0:
                continue
            s0 = s1 = s2 = 0.0
            for q in range(offsets[v], offsets[v + 1]):
                u = nbrs[q]
                s0 += out[u, 0]
                s1 += out[u, 1]
                s2 += out[u, 2]
            nxt[v, 0], nxt[v, 1], nxt[v, 2] = s0 / k, s1 / k, s2 / k
        for v in range(patch.shape[0]):
            if patch[v]:
                out[v, 0], out[v, 1], out[v, 2] = nxt[v, 0], nxt[v, 1], nxt[v, 2]
    return out


@njit(cache=True)
def _deviation(x0, x1, rest, S, n, R0, p0, R1, p1):
    """[n]: max(|x0_v - (R0 rest_v + p0)|, |x1_v - (R1 rest_v + p1)|) for v in S, 0 elsewhere (m)."""
    dev = np.zeros(n)
    for v in S:
        a = 0.0
        b = 0.0
        for k in range(3):
            da = x0[v, k] - (R0[k, 0] * rest[v, 0] + R0[k, 1] * rest[v, 1] + R0[k, 2] * rest[v, 2] + p0[k])
            db = x1[v, k] - (R1[k, 0] * rest[v, 0] + R1[k, 1] * rest[v, 1] + R1[k, 2] * rest[v, 2] + p1[k])
            a += da * da
            b += db * db
        dev[v] = np.sqrt(max(a, b))
    return dev


@njit(cache=True)
def _best_deviation(x0, x1, rest, S, n, quiet, max_turn):
    """(:func:`_deviation` [n] m, sigma) in the frames of :meth:`SelfContact.deviation`: the identity; else the
    rigid fits of the surface at t and t+1, then the fits to the vertices they left quiet, if they leave fewer
    vertices hot and turn at most ``max_turn`` rad within the step. In numba: up to four fits a check."""
    eye, zero = np.eye(3), np.zeros(3)
    best = _deviation(x0, x1, rest, S, n, eye, zero, eye, zero)
    best_hot = np.count_nonzero(best > quiet)
    sigma = 1.0
    ids = S
    for _ in range(2):  # the fit, then the fit to the vertices it left quiet
        if best_hot == 0 or ids.shape[0] < 4:
            break
        R0, p0 = rigid_fit_rows(x0, ids, rest, ids)
        R1, p1 = rigid_fit_rows(x1, ids, rest, ids)
        cos_turn = min(max(0.5 * (np.trace(R0.T @ R1) - 1.0), -1.0), 1.0)
        if np.arccos(cos_turn) > max_turn:
            break
        dev = _deviation(x0, x1, rest, S, n, R0, p0, R1, p1)
        hot = np.count_nonzero(dev > quiet)
        if hot < best_hot:
            best, best_hot, sigma = dev, hot, np.sqrt(0.5 * (1.0 + cos_turn))  # cos(theta/2)
        ids = S[dev[S] <= quiet]
    return best, sigma


@njit(cache=True)
def _candidates(X0, X1, hot, S, faces, edges, grow):
    """Non-adjacent (vertex, face) [K,2] and (edge, edge) [J,2] pairs with a hot vertex whose swept boxes come within
    ``grow`` (m): the hot primitives against every primitive whose box meets the hot region's box (uniform-grid
    joins: the hot region is many small boxes packed together)."""
    nh = 0
    for v in S:
        nh += hot[v]
    if nh == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 2), dtype=np.int64)
    hot_f = np.zeros(faces.shape[0], dtype=np.bool_)
    for f in range(faces.shape[0]):
        hot_f[f] = hot[faces[f, 0]] or hot[faces[f, 1]] or hot[faces[f, 2]]
    hot_e = np.zeros(edges.shape[0], dtype=np.bool_)
    for e in range(edges.shape[0]):
        hot_e[e] = hot[edges[e, 0]] or hot[edges[e, 1]]
    hv = np.empty(nh, dtype=np.int64)
    k = 0
    for v in S:
        if hot[v]:
            hv[k] = v
            k += 1
    hf, he = np.flatnonzero(hot_f), np.flatnonzero(hot_e)
    flo, fhi = prim_boxes(X0, X1, faces, hf)
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):  # the hot region's box (hot faces hold every hot vertex and edge), grown
        lo[a] = flo[:, a].min() - grow
        hi[a] = fhi[:, a].max() + grow
    near_f = prims_meeting_box(X0, X1, faces, lo, hi)
    near_e = prims_meeting_box(X0, X1, edges, lo, hi)
    near_v = S[prims_meeting_box(X0, X1, S.reshape(-1, 1), lo, hi)]
    cold_v = near_v[~hot[near_v]]  # hot vertices meet every near face in the first join
    cold_e = near_e[~hot_e[near_e]]  # hot edge pairs come from the self-join
    nflo, nfhi = prim_boxes(X0, X1, faces, near_f)
    vlo, vhi = vertex_boxes(X0, X1, hv)
    p1 = grid_join_apart(vlo - grow, vhi + grow, hv.reshape(-1, 1), nflo, nfhi, faces[near_f])
    cvlo, cvhi = vertex_boxes(X0, X1, cold_v)
    p2 = grid_join_apart(cvlo, cvhi, cold_v.reshape(-1, 1), flo - grow, fhi + grow, faces[hf])
    vf = np.concatenate((map_pairs(p1, hv, near_f), map_pairs(p2, cold_v, hf)))
    elo, ehi = prim_boxes(X0, X1, edges, he)
    hot_edges = edges[he]
    # two boxes grown by half: within grow of each other
    p3 = grid_self_join_apart(elo - 0.5 * grow, ehi + 0.5 * grow, hot_edges)
    celo, cehi = prim_boxes(X0, X1, edges, cold_e)
    p4 = grid_join_apart(elo - grow, ehi + grow, hot_edges, celo, cehi, edges[cold_e])
    ee = np.concatenate((map_pairs(p3, he, he), map_pairs(p4, he, cold_e)))
    return vf, ee


def _close_pairs(X, vf, ee, faces, edges, reach) -> tuple:
    """(vf pairs of X within ``reach`` m, their distances, ee pairs likewise, their distances, the smallest distance
    of any non-adjacent pair in X (m; inf if none within reach))."""
    dv = _pair_distances(X, vf, ee, faces, edges)
    near = dv <= reach
    nv = len(vf)
    gap = float(dv.min()) if len(dv) else np.inf
    return vf[near[:nv]], dv[:nv][near[:nv]], ee[near[nv:]], dv[nv:][near[nv:]], gap


@njit(cache=True, parallel=True)
def _rest_pairs_needed(pairs, d_rest, dev, hot, faces, edges, is_ee, clearance, sigma):
    """Bool [K]: rest-close pairs to examine this step. A pair with a hot vertex is examined with the hot primitives;
    a quiet one only if ``sigma`` x its rest distance minus the largest deviation of each primitive's vertices
    (``dev`` [N], m, from the step's rigid frames at both ends: it bounds every point's deviation during the step)
    is not above ``clearance``."""
    keep = np.zeros(pairs.shape[0], dtype=np.bool_)
    for k in prange(pairs.shape[0]):
        if is_ee:
            a = (edges[pairs[k, 0], 0], edges[pairs[k, 0], 1])
            b = (edges[pairs[k, 1], 0], edges[pairs[k, 1], 1], edges[pairs[k, 1], 1])
        else:
            a = (pairs[k, 0], pairs[k, 0])
            f = pairs[k, 1]
            b = (faces[f, 0], faces[f, 1], faces[f, 2])
        if hot[a[0]] or hot[a[1]] or hot[b[0]] or hot[b[1]] or hot[b[2]]:
            continue
        qa = max(dev[a[0]], dev[a[1]])
        qb = max(dev[b[0]], dev[b[1]], dev[b[2]])
        keep[k] = sigma * d_rest[k] - qa - qb <= clearance
    return keep


@njit(cache=True)
def _pair_distances(X, vf, ee, faces, edges):
    out = np.empty(vf.shape[0] + ee.shape[0])
    for k in range(vf.shape[0]):
        f = vf[k, 1]
        out[k] = point_triangle_distance(row3(X, vf[k, 0]), row3(X, faces[f, 0]), row3(X, faces[f, 1]),
                                         row3(X, faces[f, 2]))
    for k in range(ee.shape[0]):
        a, b = ee[k, 0], ee[k, 1]
        out[vf.shape[0] + k] = segment_distance(row3(X, edges[a, 0]), row3(X, edges[a, 1]), row3(X, edges[b, 0]),
                                                row3(X, edges[b, 1]))[0]
    return out


def _all_hot(pairs, faces, edges, hot, is_ee) -> np.ndarray:
    """Bool [K]: pairs all of whose vertices are hot (moving)."""
    return ~_any_vertex(pairs, faces, edges, ~hot, is_ee)


def _any_vertex(pairs, faces, edges, mask, is_ee) -> np.ndarray:
    """Bool [K]: pairs (vertex, face) or (edge, edge) with a vertex in ``mask`` [N]."""
    if len(pairs) == 0:
        return np.zeros(0, dtype=bool)
    ids = (np.concatenate([edges[pairs[:, 0]], edges[pairs[:, 1]]], axis=1) if is_ee
           else np.concatenate([pairs[:, :1], faces[pairs[:, 1]]], axis=1))
    return mask[ids].any(axis=1)


def _separation(x0, x1, ids, t, is_ee) -> tuple[np.ndarray, np.ndarray]:
    """(unit separation n [K,3] from the second primitive to the first at time t [K], signed weights c [K,4]) of
    pairs ``ids`` [K,4] (vertex + triangle, or edge + edge): the gap along n changes by sum_k c_k (dx_k . n)."""
    P = x0[ids] + t[:, None, None] * (x1[ids] - x0[ids])  # [K,4,3]
    return _separation_kernel(np.ascontiguousarray(P), is_ee)


@njit(cache=True)
def _separation_kernel(P, is_ee):
    K = P.shape[0]
    n = np.empty((K, 3))
    c = np.empty((K, 4))
    for k in range(K):
        p0, p1, p2, p3 = row3(P[k], 0), row3(P[k], 1), row3(P[k], 2), row3(P[k], 3)
        if is_ee:
            a, b = segment_params(p0, p1, p2, p3)
            w = (1.0 - a, a, -(1.0 - b), -b)
        else:
            _, w1, w2, w3 = point_triangle(p0, p1, p2, p3)
            w = (1.0, -w1, -w2, -w3)
        s = [0.0, 0.0, 0.0]
        for i in range(3):
            s[i] = w[0] * P[k, 0, i] + w[1] * P[k, 1, i] + w[2] * P[k, 2, i] + w[3] * P[k, 3, i]
        norm = np.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
        if norm > 0:
            n[k, 0], n[k, 1], n[k, 2] = s[0] / norm, s[1] / norm, s[2] / norm
        else:  # touching: fall back to the triangle's normal / the edges' common normal
            if is_ee:
                u = (p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2])
                v = (p3[0] - p2[0], p3[1] - p2[1], p3[2] - p2[2])
            else:
                u = (p2[0] - p1[0], p2[1] - p1[1], p2[2] - p1[2])
                v = (p3[0] - p1[0], p3[1] - p1[1], p3[2] - p1[2])
            m = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
            mn = max(np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]), 1e-300)
            n[k, 0], n[k, 1], n[k, 2] = m[0] / mn, m[1] / mn, m[2] / mn
        for i in range(4):
            c[k, i] = w[i]
    return n, c


_READY = False


def warm_up_self_contact() -> None:
    """Load (the first time on a machine: compile) the stage's numba kernels on a tiny case."""
    global _READY
    if _READY:
        return
    faces = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]], dtype=np.int64)
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    s = Surface.from_faces(faces, 4)
    hot = np.ones(4, dtype=np.bool_)
    vf, ee = _candidates(X, X + 0.01, hot, s.vertices, faces, s.edges, 0.1)
    _best_deviation(X, X + 0.01, X, s.vertices, 4, 0.001, MAX_FIT_TURN)
    _pair_distances(X, vf, ee, faces, s.edges)
    for pairs, is_ee in ((vf, False), (ee, True)):
        _rest_pairs_needed(pairs, np.zeros(len(pairs)), np.zeros(4), hot, faces, s.edges, is_ee, 0.0, 1.0)
    off, nb = _vertex_neighbours(s.edges, 4)
    _harmonic_fill(X.copy(), hot, off, nb, 2)
    _grow(hot, off, nb)
    P = np.ascontiguousarray(np.tile(X[None], (1, 1, 1)))
    _separation_kernel(P, True)
    _separation_kernel(P, False)
    _READY = True
