"""The numba helpers shared by the collision stages: small vector algebra, the coplanarity cubic of the
non-penetration filter, swept boxes and their joins (sort-and-sweep, uniform grid), point, segment and triangle
distances.

Every function here is compiled by numba (``@njit``) or inlined into the kernels that call it
(``@register_jitable``: plain Python on arrays, tensors or tuples too), so :mod:`.filter`,
:mod:`.narrow_phase`, :mod:`.broad_phase`, :mod:`.correction` and :mod:`.clearance` share one implementation of
each formula.
The floating-point reasoning behind the filter's bounds (``ERROR_FACTOR``, ``UNDERFLOW_GUARD``) is in
:mod:`.filter`'s docstring.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange
from numba.extending import register_jitable

ERROR_FACTOR = 32.0
UNDERFLOW_GUARD = 2.0**-1000  # absolute slack for subnormal / underflowed products
UNIT_ROUNDOFF = float(np.finfo(np.float64).eps / 2)
BRUTE_FORCE_PAIRS = 4096  # box_join compares all pairs directly up to this many


def use_kernel_threads(threads: int) -> int:
    """Run the parallel kernels (the joins, the clearance CCD, the validity check) on ``threads`` of numba's threads,
    at most ``NUMBA_NUM_THREADS`` (the machine's cores unless set); returns the count used.

    numba keeps this per calling thread, so a caller that steps from another thread (a ROS executor) sets it there.
    Results do not depend on it: the parallel loops write disjoint rows, and joins keep the serial order.
    """
    n = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


# ---------------------------------------------------------------------------------------------- vector algebra
@register_jitable
def vec_cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@register_jitable
def abs_cross(ax, ay, az, bx, by, bz):
    # Same expression tree as vec_cross on absolute values: bounds its rounding error.
    return ay * bz + az * by, az * bx + ax * bz, ax * by + ay * bx


@register_jitable
def vec_dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@register_jitable
def vec_sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@register_jitable
def vec_add(a, b):
    return a[0] + b[0], a[1] + b[1], a[2] + b[2]


# ---------------------------------------------------------------------------------- the coplanarity cubic
@register_jitable
def bernstein_terms(P0, A0, B0, C0, P1, A1, B1, C1):
    """The one implementation of the coefficients: on [3,K] arrays/tensors (rows indexable) and,
    compiled by numba, on (x, y, z) float tuples of a single pair."""
    # Leaves: positions relative to a, at t0 and t1 (one rounding each).
    d0, e0, g0 = vec_sub(P0, A0), vec_sub(B0, A0), vec_sub(C0, A0)
    d1, e1, g1 = vec_sub(P1, A1), vec_sub(B1, A1), vec_sub(C1, A1)
    n0 = vec_cross(e0[0], e0[1], e0[2], g0[0], g0[1], g0[2])
    n1 = vec_cross(e1[0], e1[1], e1[2], g1[0], g1[1], g1[2])
    # (v_b - v_a) = (b1 - a1) - (b0 - a0), exactly in reals.
    ve, vg = vec_sub(e1, e0), vec_sub(g1, g0)
    w = vec_cross(ve[0], ve[1], ve[2], vg[0], vg[1], vg[2])
    nh2 = vec_sub(vec_add(n0, n1), w)  # 2 * n-hat (minus sign!)
    coef = (vec_dot(d0, n0), vec_dot(d0, nh2) + vec_dot(d1, n0), vec_dot(d1, nh2) + vec_dot(d0, n1), vec_dot(d1, n1))

    ad0 = (abs(d0[0]), abs(d0[1]), abs(d0[2]))
    ae0 = (abs(e0[0]), abs(e0[1]), abs(e0[2]))
    ag0 = (abs(g0[0]), abs(g0[1]), abs(g0[2]))
    ad1 = (abs(d1[0]), abs(d1[1]), abs(d1[2]))
    ae1 = (abs(e1[0]), abs(e1[1]), abs(e1[2]))
    ag1 = (abs(g1[0]), abs(g1[1]), abs(g1[2]))
    an0 = abs_cross(ae0[0], ae0[1], ae0[2], ag0[0], ag0[1], ag0[2])
    an1 = abs_cross(ae1[0], ae1[1], ae1[2], ag1[0], ag1[1], ag1[2])
    ave, avg = vec_add(ae1, ae0), vec_add(ag1, ag0)
    aw = abs_cross(ave[0], ave[1], ave[2], avg[0], avg[1], avg[2])
    anh2 = vec_add(vec_add(an0, an1), aw)
    mag = (vec_dot(ad0, an0), vec_dot(ad0, anh2) + vec_dot(ad1, an0), vec_dot(ad1, anh2) + vec_dot(ad0, an1),
           vec_dot(ad1, an1))
    return coef, mag


@register_jitable
def keep_mask(coef, mag, unit_roundoff):
    """Arrays, tensors or (numba) scalars alike."""
    scale = ERROR_FACTOR * unit_roundoff
    bound = mag[0] * scale + UNDERFLOW_GUARD
    pos = coef[0] > bound
    neg = coef[0] < -bound
    for i in range(1, 4):
        bound = mag[i] * scale + UNDERFLOW_GUARD
        pos = pos & (coef[i] > bound)
        neg = neg & (coef[i] < -bound)
    # NaN/inf make every comparison False, so such pairs are kept. (x ^ True: "not" for bool
    # scalars, numpy arrays and torch tensors alike.)
    return (pos | neg) ^ True


@register_jitable
def quad_points(X0, X1, quads, k):
    """The 8 (x, y, z) tuples (p, a, b, c at t0, then t1) of quad k."""
    p, a, b, c = quads[k, 0], quads[k, 1], quads[k, 2], quads[k, 3]
    return ((X0[p, 0], X0[p, 1], X0[p, 2]), (X0[a, 0], X0[a, 1], X0[a, 2]),
            (X0[b, 0], X0[b, 1], X0[b, 2]), (X0[c, 0], X0[c, 1], X0[c, 2]),
            (X1[p, 0], X1[p, 1], X1[p, 2]), (X1[a, 0], X1[a, 1], X1[a, 2]),
            (X1[b, 0], X1[b, 1], X1[b, 2]), (X1[c, 0], X1[c, 1], X1[c, 2]))


# ------------------------------------------------------------------------------ boxes and distances
JOIN_CHUNKS = 8  # row blocks of a join run in parallel; fixed, so the output is the serial order at any thread count


@njit(cache=True, parallel=True)
def box_join(lo_a, hi_a, lo_b, hi_b):
    """Sort-and-sweep join of two box sets [Ka,3], [Kb,3] -> pairs [K,2].

    Along the axis where the boxes are smallest relative to the spread of their corners,
    two intervals overlap iff lo_b lies in [lo_a, hi_a] or lo_a lies in (lo_b, hi_b]: both
    are contiguous runs of the sorted lower corners (the two cases are disjoint). Both sweeps run in
    ``JOIN_CHUNKS`` row blocks on numba's threads (:func:`concat_pairs`: the serial order).
    """
    na, nb = lo_a.shape[0], lo_b.shape[0]
    if na == 0 or nb == 0:
        return np.empty((0, 2), dtype=np.int64)
    if na * nb <= BRUTE_FORCE_PAIRS:
        # Small sets: comparing all pairs is cheaper than sorting.
        out = np.empty((max(16, 2 * (na + nb)), 2), dtype=np.int64)
        n = 0
        for i in range(na):
            for j in range(nb):
                if boxes_overlap(lo_a, hi_a, i, lo_b, hi_b, j):
                    if n == out.shape[0]:
                        out = grow_pairs(out)
                    out[n, 0], out[n, 1] = i, j
                    n += 1
        return out[:n].copy()
    k, best = 0, -1.0
    for ax in range(3):
        size = (hi_a[:, ax] - lo_a[:, ax]).sum() / na + (hi_b[:, ax] - lo_b[:, ax]).sum() / nb
        spread = max(hi_a[:, ax].max(), hi_b[:, ax].max()) - min(lo_a[:, ax].min(), lo_b[:, ax].min())
        r = spread / max(size, 1e-300)
        if r > best:
            k, best = ax, r
    oa = np.argsort(lo_a[:, k])
    ob = np.argsort(lo_b[:, k])
    sa = lo_a[oa, k]
    sb = lo_b[ob, k]
    blocks = [np.empty((0, 2), dtype=np.int64) for _ in range(2 * JOIN_CHUNKS)]
    for c in prange(2 * JOIN_CHUNKS):
        if c < JOIN_CHUNKS:  # a's boxes, each against the b boxes whose lower corner lies in its interval
            blocks[c] = _sweep_rows(lo_a, hi_a, lo_b, hi_b, sb, ob, k, c * na // JOIN_CHUNKS,
                                    (c + 1) * na // JOIN_CHUNKS, False)
        else:  # b's boxes, each against the a boxes whose lower corner lies strictly inside its interval
            c1 = c - JOIN_CHUNKS
            blocks[c] = _sweep_rows(lo_b, hi_b, lo_a, hi_a, sa, oa, k, c1 * nb // JOIN_CHUNKS,
                                    (c1 + 1) * nb // JOIN_CHUNKS, True)
    return concat_pairs(blocks)


@register_jitable
def _sweep_rows(lo_q, hi_q, lo_s, hi_s, s_sorted, s_order, k, i0, i1, swapped):
    """Pairs of query boxes i0..i1-1 with the boxes of the other set whose lower corner on axis k lies in the query's
    interval (closed below, or open below when ``swapped``); rows (query, other), or (other, query) if swapped."""
    out = np.empty((max(16, 2 * (i1 - i0)), 2), dtype=np.int64)
    n = 0
    ns = s_sorted.shape[0]
    for i in range(i0, i1):
        j = np.searchsorted(s_sorted, lo_q[i, k], side="right") if swapped else np.searchsorted(s_sorted, lo_q[i, k])
        while j < ns and s_sorted[j] <= hi_q[i, k]:
            js = s_order[j]
            if boxes_overlap(lo_q, hi_q, i, lo_s, hi_s, js):
                if n == out.shape[0]:
                    out = grow_pairs(out)
                if swapped:
                    out[n, 0], out[n, 1] = js, i
                else:
                    out[n, 0], out[n, 1] = i, js
                n += 1
            j += 1
    return out[:n]


@register_jitable
def map_pairs(pairs, ids_a, ids_b):
    """[K,2]: a join's rows (i, j) [K,2] as (ids_a[i], ids_b[j]) (the joined boxes' primitive ids)."""
    out = np.empty_like(pairs)
    for k in range(pairs.shape[0]):
        out[k, 0] = ids_a[pairs[k, 0]]
        out[k, 1] = ids_b[pairs[k, 1]]
    return out


@register_jitable
def concat_pairs(blocks):
    """The pair blocks [K_c,2] one after the other, in block order [sum K_c, 2]: a parallel join's blocks cover
    consecutive rows, so this is the order of the serial loop."""
    total = 0
    for b in blocks:
        total += b.shape[0]
    out = np.empty((total, 2), dtype=np.int64)
    n = 0
    for b in blocks:
        out[n:n + b.shape[0]] = b
        n += b.shape[0]
    return out


GRID_CELLS_PER_BOX = 4  # grid_join: at most this many cells per box on average (the grid coarsens beyond)


NO_PRIMS = np.zeros((0, 0), dtype=np.int64)  # grid joins: no vertex ids, so no pair is skipped as adjacent


@njit(cache=True)
def grid_join(lo_a, hi_a, lo_b, hi_b):
    """Uniform-grid join of two box sets [Ka,3], [Kb,3] -> pairs [K,2] (i, j) of overlapping closed boxes.

    The same pairs as :func:`box_join`, in another order. Faster where both sets are many small boxes packed in a
    region (a surface against its own neighbourhood): a box meets only the boxes in the cells it covers, where a
    sweep along one axis meets a whole slab. The cell is the sets' mean largest box extent, coarsened until the grid
    has at most ``GRID_CELLS_PER_BOX`` cells per box; a pair is reported in the first cell both boxes cover. The rows
    of ``a`` run in ``JOIN_CHUNKS`` blocks on numba's threads.
    """
    return grid_join_apart(lo_a, hi_a, NO_PRIMS, lo_b, hi_b, NO_PRIMS)


@njit(cache=True, parallel=True)
def grid_join_apart(lo_a, hi_a, prims_a, lo_b, hi_b, prims_b):
    """:func:`grid_join` without the pairs whose primitives share a vertex: ``prims_a`` [Ka,m], ``prims_b`` [Kb,k]
    are the vertex ids of each box's primitive (a vertex [K,1], an edge [K,2], a triangle [K,3]; [0,0]: skip none).
    On a surface most overlapping pairs of a neighbourhood are adjacent (a vertex meets its own faces, an edge its
    neighbours): leaving them out here saves writing, mapping and filtering them."""
    na, nb = lo_a.shape[0], lo_b.shape[0]
    if na == 0 or nb == 0:
        return np.empty((0, 2), dtype=np.int64)
    org, dims, inv = _grid(lo_a, hi_a, lo_b, hi_b)
    cl, ch, start, ids = _grid_cells(lo_b, hi_b, org, dims, inv)
    blocks = [np.empty((0, 2), dtype=np.int64) for _ in range(JOIN_CHUNKS)]
    for c in prange(JOIN_CHUNKS):
        blocks[c] = _grid_rows(lo_a, hi_a, prims_a, lo_b, hi_b, prims_b, org, dims, inv, cl, start, ids,
                               c * na // JOIN_CHUNKS, (c + 1) * na // JOIN_CHUNKS)
    return concat_pairs(blocks)


@register_jitable
def share_vertex(prims_a, i, prims_b, j):
    """Whether primitive rows ``prims_a[i]`` and ``prims_b[j]`` (vertex ids) have a vertex in common (False for
    primitives without ids, shape [K,0])."""
    for u in range(prims_a.shape[1]):
        for v in range(prims_b.shape[1]):
            if prims_a[i, u] == prims_b[j, v]:
                return True
    return False


@register_jitable
def _grid_rows(lo_a, hi_a, prims_a, lo_b, hi_b, prims_b, org, dims, inv, cl, start, ids, i0, i1):
    """Pairs (i, j) of :func:`grid_join_apart` for the rows i0..i1-1 of ``a``."""
    out = np.empty((max(16, 2 * (i1 - i0)), 2), dtype=np.int64)
    n = 0
    al = np.empty(3, dtype=np.int64)
    ah = np.empty(3, dtype=np.int64)
    for i in range(i0, i1):
        for a in range(3):
            al[a] = min(max(int((lo_a[i, a] - org[a]) * inv), 0), dims[a] - 1)
            ah[a] = min(max(int((hi_a[i, a] - org[a]) * inv), 0), dims[a] - 1)
        a0, a1, a2 = al[0], al[1], al[2]
        for x in range(a0, ah[0] + 1):
            for y in range(a1, ah[1] + 1):
                for z in range(a2, ah[2] + 1):
                    c = (x * dims[1] + y) * dims[2] + z
                    for q in range(start[c], start[c + 1]):
                        j = ids[q]
                        if x != max(a0, cl[j, 0]) or y != max(a1, cl[j, 1]) or z != max(a2, cl[j, 2]):
                            continue  # not the first cell both cover: the pair is met there
                        if boxes_overlap(lo_a, hi_a, i, lo_b, hi_b, j) and not share_vertex(prims_a, i, prims_b, j):
                            if n == out.shape[0]:
                                out = grow_pairs(out)
                            out[n, 0], out[n, 1] = i, j
                            n += 1
    return out[:n]


@njit(cache=True)
def grid_self_join(lo, hi):
    """Pairs [K,2] (i, j), i < j, of overlapping closed boxes within one set [K,3] (see :func:`grid_join`)."""
    return grid_self_join_apart(lo, hi, NO_PRIMS)


@njit(cache=True, parallel=True)
def grid_self_join_apart(lo, hi, prims):
    """:func:`grid_self_join` without the pairs whose primitives (vertex ids ``prims`` [K,m]; [0,0]: skip none)
    share a vertex (see :func:`grid_join_apart`)."""
    nb = lo.shape[0]
    if nb < 2:
        return np.empty((0, 2), dtype=np.int64)
    org, dims, inv = _grid(lo, hi, lo, hi)
    cl, ch, start, ids = _grid_cells(lo, hi, org, dims, inv)
    blocks = [np.empty((0, 2), dtype=np.int64) for _ in range(JOIN_CHUNKS)]
    for c in prange(JOIN_CHUNKS):
        blocks[c] = _self_rows(lo, hi, prims, dims, cl, ch, start, ids, c * nb // JOIN_CHUNKS,
                               (c + 1) * nb // JOIN_CHUNKS)
    return concat_pairs(blocks)


@register_jitable
def _self_rows(lo, hi, prims, dims, cl, ch, start, ids, i0, i1):
    """Pairs (i, j), j > i, of :func:`grid_self_join_apart` for the rows i0..i1-1."""
    out = np.empty((max(16, 4 * (i1 - i0)), 2), dtype=np.int64)
    n = 0
    for i in range(i0, i1):
        a0, a1, a2 = cl[i, 0], cl[i, 1], cl[i, 2]
        for x in range(a0, ch[i, 0] + 1):
            for y in range(a1, ch[i, 1] + 1):
                for z in range(a2, ch[i, 2] + 1):
                    c = (x * dims[1] + y) * dims[2] + z
                    for q in range(start[c], start[c + 1]):
                        j = ids[q]
                        if j <= i or x != max(a0, cl[j, 0]) or y != max(a1, cl[j, 1]) or z != max(a2, cl[j, 2]):
                            continue
                        if boxes_overlap(lo, hi, i, lo, hi, j) and not share_vertex(prims, i, prims, j):
                            if n == out.shape[0]:
                                out = grow_pairs(out)
                            out[n, 0], out[n, 1] = i, j
                            n += 1
    return out[:n]


@register_jitable
def _grid(lo_a, hi_a, lo_b, hi_b):
    """(origin [3], cells per axis [3], 1 / cell size) of a grid over both box sets."""
    ext = 0.0
    for i in range(lo_a.shape[0]):
        ext += max(hi_a[i, 0] - lo_a[i, 0], hi_a[i, 1] - lo_a[i, 1], hi_a[i, 2] - lo_a[i, 2]) / lo_a.shape[0]
    ext_b = 0.0
    for j in range(lo_b.shape[0]):
        ext_b += max(hi_b[j, 0] - lo_b[j, 0], hi_b[j, 1] - lo_b[j, 1], hi_b[j, 2] - lo_b[j, 2]) / lo_b.shape[0]
    org = np.empty(3)
    span = np.empty(3)
    for a in range(3):
        org[a] = min(lo_a[:, a].min(), lo_b[:, a].min())
        span[a] = max(hi_a[:, a].max(), hi_b[:, a].max()) - org[a]
    h = max(ext, ext_b, 1e-300, span.max() * 1e-6)
    dims = np.empty(3, dtype=np.int64)
    limit = GRID_CELLS_PER_BOX * (lo_a.shape[0] + lo_b.shape[0]) + 64
    while True:
        for a in range(3):
            dims[a] = int(span[a] / h) + 1
        if dims[0] * dims[1] * dims[2] <= limit:
            break
        h *= 1.5
    return org, dims, 1.0 / h


@register_jitable
def _grid_cells(lo, hi, org, dims, inv):
    """Cell ranges (lowest [K,3], highest [K,3]) of each box and the CSR (start [cells+1], box ids) of the
    boxes in each cell."""
    nb = lo.shape[0]
    nc = dims[0] * dims[1] * dims[2]
    cl = np.empty((nb, 3), dtype=np.int64)
    ch = np.empty((nb, 3), dtype=np.int64)
    start = np.zeros(nc + 1, dtype=np.int64)
    for j in range(nb):
        for a in range(3):
            cl[j, a] = min(max(int((lo[j, a] - org[a]) * inv), 0), dims[a] - 1)
            ch[j, a] = min(max(int((hi[j, a] - org[a]) * inv), 0), dims[a] - 1)
        for x in range(cl[j, 0], ch[j, 0] + 1):
            for y in range(cl[j, 1], ch[j, 1] + 1):
                for z in range(cl[j, 2], ch[j, 2] + 1):
                    start[(x * dims[1] + y) * dims[2] + z + 1] += 1
    for c in range(nc):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    ids = np.empty(start[nc], dtype=np.int64)
    for j in range(nb):
        for x in range(cl[j, 0], ch[j, 0] + 1):
            for y in range(cl[j, 1], ch[j, 1] + 1):
                for z in range(cl[j, 2], ch[j, 2] + 1):
                    c = (x * dims[1] + y) * dims[2] + z
                    ids[fill[c]] = j
                    fill[c] += 1
    return cl, ch, start, ids


@register_jitable
def boxes_overlap(lo_a, hi_a, i, lo_b, hi_b, j):
    # Branch-free (&, not "and"): the outcomes are unpredictable, mispredictions cost more.
    return ((lo_a[i, 0] <= hi_b[j, 0]) & (lo_b[j, 0] <= hi_a[i, 0]) & (lo_a[i, 1] <= hi_b[j, 1])
            & (lo_b[j, 1] <= hi_a[i, 1]) & (lo_a[i, 2] <= hi_b[j, 2]) & (lo_b[j, 2] <= hi_a[i, 2]))


@register_jitable
def grow_pairs(out):
    """``out`` [n,2] copied into a buffer twice as long. Callers append a pair as ``if n == out.shape[0]: out =
    grow_pairs(out)``, then write row n: an array returned from a call on every append (in a tuple with n) costs
    reference counting per pair, measured at 0.5-1 ms per 10^5 pair tests in the joins below."""
    grown = np.empty((2 * out.shape[0], 2), dtype=np.int64)
    grown[:out.shape[0]] = out
    return grown


@njit(cache=True)
def sphere_bounds(X0, X1, ids, c0, c1, radius):
    """Distances [K] of points X0[ids], X1[ids] to the bounding spheres at t0 / t1 (centres c0, c1; m)."""
    K = ids.shape[0]
    lb0 = np.empty(K)
    lb1 = np.empty(K)
    for k in range(K):
        lb0[k] = point_distance(X0, ids[k], c0) - radius
        lb1[k] = point_distance(X1, ids[k], c1) - radius
    return lb0, lb1


@register_jitable
def point_distance(P, k, c):
    d0, d1, d2 = P[k, 0] - c[0], P[k, 1] - c[1], P[k, 2] - c[2]
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@register_jitable
def row_distance(X, i, Y, j):
    d0, d1, d2 = X[i, 0] - Y[j, 0], X[i, 1] - Y[j, 1], X[i, 2] - Y[j, 2]
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(cache=True)
def longest_edge(X, edges):
    m = 0.0
    for e in range(edges.shape[0]):
        m = max(m, row_distance(X, edges[e, 0], X, edges[e, 1]))
    return m


def row_order(pairs: np.ndarray) -> np.ndarray:
    """Indices [K] that sort the rows of ``pairs`` [K,2] lexicographically (a canonical order: pushes merged from
    pairs in this order do not depend on which other pairs a pass examined)."""
    return np.lexsort((pairs[:, 1], pairs[:, 0])) if len(pairs) > 1 else np.arange(len(pairs))


@njit(cache=True)
def changed_rows(A, B):
    """Bool [N]: rows of A [N,3] that differ from B [N,3] in any entry (as ``np.any(A != B, axis=1)``, without
    its temporaries)."""
    out = np.zeros(A.shape[0], dtype=np.bool_)
    for i in range(A.shape[0]):
        out[i] = (A[i, 0] != B[i, 0]) | (A[i, 1] != B[i, 1]) | (A[i, 2] != B[i, 2])
    return out


@register_jitable
def vertex_boxes(X0, X1, ids):
    lo = np.empty((len(ids), 3))
    hi = np.empty((len(ids), 3))
    for k in range(len(ids)):
        v = ids[k]
        for a in range(3):
            lo[k, a] = min(X0[v, a], X1[v, a])
            hi[k, a] = max(X0[v, a], X1[v, a])
    return lo, hi


@register_jitable
def prim_boxes(X0, X1, prims, ids):
    """Swept boxes [K,3] of primitives ``prims[ids]`` (edges or faces)."""
    lo = np.full((len(ids), 3), np.inf)
    hi = np.full((len(ids), 3), -np.inf)
    for k in range(len(ids)):
        for i in range(prims.shape[1]):
            v = prims[ids[k], i]
            for a in range(3):
                lo[k, a] = min(lo[k, a], X0[v, a], X1[v, a])
                hi[k, a] = max(hi[k, a], X0[v, a], X1[v, a])
    return lo, hi


# ------------------------------------------------------------------------- segment and triangle distances
@njit(cache=True, parallel=True)
def prims_meeting_box(X0, X1, prims, lo, hi):
    """Ids [K] of the primitives ``prims`` [P,m] (vertex ids) whose swept boxes over X0 -> X1 meet the box [lo, hi]
    (without building the P boxes: this runs over the whole surface every step)."""
    keep = np.zeros(prims.shape[0], dtype=np.bool_)
    for k in prange(prims.shape[0]):
        meets = True
        for a in range(3):
            b_lo, b_hi = np.inf, -np.inf
            for i in range(prims.shape[1]):
                v = prims[k, i]
                b_lo = min(b_lo, X0[v, a], X1[v, a])
                b_hi = max(b_hi, X0[v, a], X1[v, a])
            if b_lo > hi[a] or b_hi < lo[a]:
                meets = False
                break
        keep[k] = meets
    return np.flatnonzero(keep)


@register_jitable
def row3(X, i):
    """Row i of an [N,3] array as an (x, y, z) tuple."""
    return X[i, 0], X[i, 1], X[i, 2]


@register_jitable
def lerp(a, b, t):
    return a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2])


@register_jitable
def clip01(x):
    return min(max(x, 0.0), 1.0)


@register_jitable
def segment_params(u, v, k, l):
    """(alpha on u-v, beta on k-l) in [0,1] of (approximately) closest points of two segments."""
    d1, d2, r = vec_sub(v, u), vec_sub(l, k), vec_sub(u, k)
    a, e, f = vec_dot(d1, d1), vec_dot(d2, d2), vec_dot(d2, r)
    b, c = vec_dot(d1, d2), vec_dot(d1, r)
    den = a * e - b * b
    s = (b * f - c * e) / den if den > 1e-300 else 0.5
    s = 0.5 if math.isnan(s) else clip01(s)
    t = (b * s + f) / e if e > 1e-300 else 0.5
    t = 0.5 if math.isnan(t) else clip01(t)
    s = (b * t - c) / a if a > 1e-300 else 0.5
    s = 0.5 if math.isnan(s) else clip01(s)
    return s, t


@register_jitable
def point_segment_distance(p, a, b):
    ab = vec_sub(b, a)
    t = clip01(vec_dot(vec_sub(p, a), ab) / max(vec_dot(ab, ab), 1e-300))
    d = vec_sub(p, lerp(a, b, t))
    return math.sqrt(vec_dot(d, d))


@register_jitable
def segment_distance(u, v, k, l):
    """(distance, alpha) of two segments: closest points, with the end-point distances as a safeguard."""
    alpha, beta = segment_params(u, v, k, l)
    d = vec_sub(lerp(u, v, alpha), lerp(k, l, beta))
    dist = min(math.sqrt(vec_dot(d, d)), point_segment_distance(u, k, l), point_segment_distance(v, k, l),
               point_segment_distance(k, u, v), point_segment_distance(l, u, v))
    return dist, alpha


@register_jitable
def point_triangle_distance(p, a, b, c):
    """Exact point-triangle distance: the plane distance when p projects inside, else the nearest edge."""
    e0, e1 = vec_sub(b, a), vec_sub(c, a)
    n = (e0[1] * e1[2] - e0[2] * e1[1], e0[2] * e1[0] - e0[0] * e1[2], e0[0] * e1[1] - e0[1] * e1[0])
    nn = math.sqrt(vec_dot(n, n))
    dist = min(point_segment_distance(p, a, b), point_segment_distance(p, b, c), point_segment_distance(p, c, a))
    if nn > 0:
        inside = True
        for x, y in ((a, b), (b, c), (c, a)):
            xy, xp = vec_sub(y, x), vec_sub(p, x)
            cr = (xy[1] * xp[2] - xy[2] * xp[1], xy[2] * xp[0] - xy[0] * xp[2], xy[0] * xp[1] - xy[1] * xp[0])
            inside = inside and vec_dot(cr, n) >= 0
        if inside:
            dist = min(dist, abs(vec_dot(vec_sub(p, a), n)) / nn)
    return dist


@register_jitable
def point_triangle(p, a, b, c):
    """(distance, w0, w1, w2): exact point-triangle distance and the barycentric weights of the closest
    point (candidates: the clamped projection and the nearest point of each edge; the nearest wins)."""
    dist = point_triangle_distance(p, a, b, c)
    w = barycentric_clamped(p, a, b, c)
    q = (w[0] * a[0] + w[1] * b[0] + w[2] * c[0], w[0] * a[1] + w[1] * b[1] + w[2] * c[1],
         w[0] * a[2] + w[1] * b[2] + w[2] * c[2])
    best = vec_dot(vec_sub(p, q), vec_sub(p, q))
    for i in range(3):
        x, y = (a, b, c)[i], (a, b, c)[(i + 1) % 3]
        xy = vec_sub(y, x)
        t = clip01(vec_dot(vec_sub(p, x), xy) / max(vec_dot(xy, xy), 1e-300))
        d = vec_sub(p, lerp(x, y, t))
        dd = vec_dot(d, d)
        if dd < best:
            best = dd
            ww = [0.0, 0.0, 0.0]
            ww[i] = 1.0 - t
            ww[(i + 1) % 3] = t
            w = (ww[0], ww[1], ww[2])
    return dist, w[0], w[1], w[2]


@register_jitable
def barycentric_clamped(p, a, b, c):
    """Barycentric weights of p's projection on triangle (a,b,c), clamped to the triangle, summing to 1."""
    e0, e1, e2 = vec_sub(b, a), vec_sub(c, a), vec_sub(p, a)
    d00, d01, d11 = vec_dot(e0, e0), vec_dot(e0, e1), vec_dot(e1, e1)
    d20, d21 = vec_dot(e2, e0), vec_dot(e2, e1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den if den != 0 else np.nan
    w = (d00 * d21 - d01 * d20) / den if den != 0 else np.nan
    if not (math.isfinite(v) and math.isfinite(w)):
        v = w = 1.0 / 3.0
    b0, b1, b2 = max(1.0 - v - w, 0.0), max(v, 0.0), max(w, 0.0)
    s = b0 + b1 + b2
    if not s > 0:
        return 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0
    return b0 / s, b1 / s, b2 / s
