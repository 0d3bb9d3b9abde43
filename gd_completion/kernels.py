"""Compiled CPU kernels (numba) for FPS, the x-window neighbour searches of `ops` and its ball queries.

`fps_pruned` is FPS that skips the leaves of points the newly chosen point cannot bring closer; it returns
exactly what the plain scan returns and serves every finite cloud (the network input, the model's FPS, the merge).

Same semantics and the same float32 arithmetic as the torch path in `ops`: squared distances are
((dx*dx + dy*dy) + dz*dz) with dx = a_x - b_x, FPS starts at point 0 and takes the first maximum,
and a window search considers exactly the ref points whose x lies in the block's window [lo, hi).
Results are identical to the torch path except the order of exact distance ties. Each cloud is
computed on its own (batch independent); the kernels release the GIL, so threads run them in parallel.

The k nearest candidates are found by scanning the x-sorted ref points outwards from the query's x
(left, then right) and stopping once dx*dx exceeds the current k-th distance: the full distance is
never smaller than dx*dx in float32, so the pruned scan selects the same k smallest entries as a scan
of the whole window. With a grid `cell` (the kNN graph), a uniform-grid search first finds the exact k
nearest of each query whose k-th lies within the 3 x 3 x 3 cells around it; where all of them lie within
`margin` they are the window's too (the window holds every point within `margin` in x of the query), and
only the other queries are scanned.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from gd_completion.cell_grid import bucket_points

_INF = np.float32(np.inf)
FPS_LEAF = 64   # points per leaf of the pruned FPS (merge, ~3,000 points: 48 to 96 within 3 %, 32 12 % slower, 16 42 %)


@numba.njit(cache=True, nogil=True)
def _fps_cloud(xyz: np.ndarray, n: int, out: np.ndarray) -> None:
    m = xyz.shape[0]
    mind = np.full(m, _INF, np.float32)
    far = 0
    out[0] = 0
    for i in range(1, n):
        cx, cy, cz = xyz[far, 0], xyz[far, 1], xyz[far, 2]
        best = np.float32(-1.0)
        arg = 0
        for j in range(m):
            dx = xyz[j, 0] - cx
            dy = xyz[j, 1] - cy
            dz = xyz[j, 2] - cz
            d = dx * dx + dy * dy + dz * dz
            mind[j] = min(mind[j], d)
            if mind[j] > best:
                best = mind[j]
                arg = j
        far = arg
        out[i] = far


@numba.njit(cache=True, nogil=True)
def fps(xyz: np.ndarray, n: int) -> np.ndarray:
    """Indices (B, n) int64 of the farthest point sampling of each cloud of xyz (B, M, 3) float32, n <= M: the
    pruned scan (`fps_pruned`, leaves of FPS_LEAF) for a finite cloud, the plain scan otherwise (same indices)."""
    b = xyz.shape[0]
    if n < 0 or n > xyz.shape[1]:
        raise ValueError("fps: need 0 <= n <= the number of points")
    out = np.empty((b, n), np.int64)
    if n == 0:
        return out
    ones = np.ones(xyz.shape[1], np.float32)
    for c in range(b):
        if np.isfinite(xyz[c]).all():
            out[c] = _fps_pruned(np.ascontiguousarray(xyz[c]), n, FPS_LEAF, ones)
        else:
            _fps_cloud(xyz[c], n, out[c])
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _spread_bits(q: int) -> int:
    """The low 10 bits of q moved to bits 0, 3, 6, ..., 27 (a Morton code's axis interleaving)."""
    q &= 0x3FF
    q = (q | (q << 16)) & 0x030000FF
    q = (q | (q << 8)) & 0x0300F00F
    q = (q | (q << 4)) & 0x030C30C3
    return (q | (q << 2)) & 0x09249249


@numba.njit(cache=True, nogil=True)
def _morton_order(xyz: np.ndarray) -> np.ndarray:
    """A permutation of the points along a Z-order (Morton) curve over their bounding box, 10 bits per axis
    (ties in ascending index): consecutive points are spatial neighbours, so fixed-size runs of them make
    compact leaves. A stable radix sort of the 30-bit codes, 10 bits per pass."""
    m = xyz.shape[0]
    lo = np.empty(3, np.float32)
    span = np.empty(3, np.float32)
    for a in range(3):
        lo[a] = xyz[:, a].min()
        span[a] = xyz[:, a].max() - lo[a]
    codes = np.zeros(m, np.int64)
    for i in range(m):
        for a in range(3):
            q = int((xyz[i, a] - lo[a]) / span[a] * 1023.0) if span[a] > 0 else 0
            codes[i] |= _spread_bits(q) << a
    order = np.arange(m)
    scratch = np.empty(m, np.int64)
    start = np.empty(1025, np.int64)
    for shift in (0, 10, 20):
        start[:] = 0
        for i in range(m):
            start[((codes[i] >> shift) & 1023) + 1] += 1
        for digit in range(1024):
            start[digit + 1] += start[digit]
        for i in range(m):
            j = order[i]
            digit = (codes[j] >> shift) & 1023
            scratch[start[digit]] = j
            start[digit] += 1
        order, scratch = scratch, order
    return order


def fps_pruned(xyz: np.ndarray, n: int, leaf: int = FPS_LEAF, weights: np.ndarray | None = None) -> np.ndarray:
    """Indices (n,) int64 of the farthest point sampling of one finite cloud xyz (M, 3), 1 <= n <= M: the same
    indices as the plain scan `_fps_cloud` (start at point 0, ties to the lowest index, the same float32
    distances).

    `weights` (M,) in (0, 1] (default all 1): a weighted sampling that takes, each step, the point whose squared
    distance to the chosen ones times its weight is largest. A point of weight w is taken only 1/sqrt(w) times
    farther from the chosen points than one of weight 1: the weight-1 points end up that much denser.

    The points are grouped into leaves of `leaf` consecutive points in Morton order; a leaf is rescanned only
    when the new point is no farther from its bounding box than the leaf's largest current distance. Skipping
    the others is exact: float32 rounding is monotone, so a point's computed distance is never below the
    computed distance to its leaf's box (the 1e-5 shrink of the latter only adds rescans).
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not 1 <= n <= len(xyz) or leaf < 1:
        raise ValueError(f"fps_pruned: need (M, 3) points, 1 <= n <= M and leaf >= 1; got {xyz.shape}, n={n}, "
                         f"leaf={leaf}")
    if weights is None:
        weights = np.ones(len(xyz), np.float32)
    weights = np.ascontiguousarray(weights, dtype=np.float32)
    if weights.shape != (len(xyz),) or not ((weights > 0) & (weights <= 1)).all():
        raise ValueError(f"fps_pruned: weights must be ({len(xyz)},) in (0, 1]")
    # one leaf at most: its index arithmetic stays small
    return _fps_pruned(xyz, int(n), min(int(leaf), len(xyz)), weights)


@numba.njit(cache=True, nogil=True)
def _fps_pruned(xyz: np.ndarray, n: int, leaf: int, weights: np.ndarray) -> np.ndarray:
    m = xyz.shape[0]
    order = _morton_order(xyz)
    leaves = (m + leaf - 1) // leaf
    px = np.empty(m, np.float32)
    py = np.empty(m, np.float32)
    pz = np.empty(m, np.float32)
    pw = np.empty(m, np.float32)
    for i in range(m):
        px[i], py[i], pz[i], pw[i] = xyz[order[i], 0], xyz[order[i], 1], xyz[order[i], 2], weights[order[i]]
    lo = np.empty((3, leaves), np.float32)   # per axis, so that the box test below vectorises
    hi = np.empty((3, leaves), np.float32)
    low_weight = np.empty(leaves, np.float32)   # a leaf's smallest weight: its points' distances are >= that x gap
    for f in range(leaves):
        s, e = f * leaf, min(m, (f + 1) * leaf)
        low_weight[f] = pw[s:e].min()
        lo[0, f], hi[0, f] = px[s:e].min(), px[s:e].max()
        lo[1, f], hi[1, f] = py[s:e].min(), py[s:e].max()
        lo[2, f], hi[2, f] = pz[s:e].min(), pz[s:e].max()
    mind = np.full(m, _INF, np.float32)
    mind_bits = mind.view(np.int32)
    leaf_max = np.full(leaves, _INF, np.float32)
    leaf_pos = np.zeros(leaves, np.int64)   # sorted position of the leaf's farthest point (lowest index)
    # (bits of leaf_max) << 32 | (m - original index): one integer max finds the farthest point, ties to the
    # lowest index (the bits of non-negative floats order as the floats)
    leaf_key = np.zeros(leaves, np.int64)   # 0: not scanned yet (a scanned leaf's key is >= 1)
    max_bits = leaf_max.view(np.int32)
    gap = np.empty(leaves, np.float32)
    shrink = np.float32(1.0 - 1e-5)
    zero = np.float32(0.0)
    none = np.int64(m + 1) * leaf
    out = np.empty(n, np.int64)
    far = 0
    out[0] = 0
    for step in range(1, n):
        cx, cy, cz = xyz[far, 0], xyz[far, 1], xyz[far, 2]
        for f in range(leaves):   # squared distance of the new point to each leaf's box
            gx = max(lo[0, f] - cx, zero, cx - hi[0, f])
            gy = max(lo[1, f] - cy, zero, cy - hi[1, f])
            gz = max(lo[2, f] - cz, zero, cz - hi[2, f])
            gap[f] = (gx * gx + gy * gy + gz * gz) * low_weight[f] * shrink
        for f in range(leaves):
            if gap[f] > leaf_max[f]:
                continue
            # slices indexed from 0 (no negative-index wrap) and integer reductions (the bits of non-negative
            # floats order as the floats; a float max does not reassociate): these loops vectorise
            s, e = f * leaf, min(m, (f + 1) * leaf)
            lx, ly, lz, lw, ld = px[s:e], py[s:e], pz[s:e], pw[s:e], mind[s:e]
            lbits, lorder = mind_bits[s:e], order[s:e]
            for i in range(ld.shape[0]):
                dx = lx[i] - cx
                dy = ly[i] - cy
                dz = lz[i] - cz
                d = (dx * dx + dy * dy + dz * dz) * lw[i]
                old = ld[i]
                ld[i] = d if d < old else old
            top = np.int32(-1)
            for i in range(lbits.shape[0]):
                top = max(top, lbits[i])
            # distances only fall: an unchanged maximum still held by the same point keeps its lowest index
            # (a leaf not scanned yet has no such point: key 0; its max may start at inf, an overflowed distance)
            if leaf_key[f] != 0 and top == max_bits[f] and mind_bits[leaf_pos[f]] == top:
                continue
            first = none   # the lowest original index holding the maximum, as index * leaf + position in the leaf
            for i in range(lorder.shape[0]):
                first = min(first, lorder[i] * leaf + i if lbits[i] == top else none)
            top_arg = first // leaf
            max_bits[f], leaf_pos[f] = top, s + first % leaf
            leaf_key[f] = (np.int64(max_bits[f]) << 32) | (m - top_arg)
        best = np.int64(0)
        for f in range(leaves):
            best = max(best, leaf_key[f])
        far = m - (best & 0xFFFFFFFF)
        out[step] = far
    return out


@numba.njit(cache=True, nogil=True)
def _insert(dist: np.ndarray, pos: np.ndarray, count: int, k: int, d: np.float32, p: int) -> int:
    """Insert (d, p) into the ascending list dist[:count] (kept to k entries); returns the new count."""
    if count == k:
        if not d < dist[k - 1]:
            return count
        count -= 1   # the last entry drops out
    i = count
    while i > 0 and d < dist[i - 1]:
        dist[i] = dist[i - 1]
        pos[i] = pos[i - 1]
        i -= 1
    dist[i] = d
    pos[i] = p
    return count + 1


@numba.njit(cache=True, nogil=True, inline="always")
def _sq(a: np.ndarray, i: int, b: np.ndarray, j: int) -> np.float32:
    dx = a[i, 0] - b[j, 0]
    dy = a[i, 1] - b[j, 1]
    dz = a[i, 2] - b[j, 2]
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _knn_cloud(query: np.ndarray, ref: np.ndarray, k: int, margin: np.float32, block: int, windowed: bool,
               exclude_self: bool, done: np.ndarray, out_dist: np.ndarray, out_idx: np.ndarray) -> None:
    q = query.shape[0]
    n = ref.shape[0]
    rperm = np.argsort(ref[:, 0], kind="mergesort")
    rs = np.empty((n, 3), np.float32)
    for i in range(n):
        rs[i] = ref[rperm[i]]
    rx = rs[:, 0].copy()
    qperm = rperm if exclude_self else np.argsort(query[:, 0], kind="mergesort")
    dist = np.empty(k, np.float32)
    pos = np.empty(k, np.int64)
    for rank in range(q):
        qi = qperm[rank]
        if done[qi]:
            continue
        qx = query[qi, 0]
        lo, hi = 0, n
        if windowed:
            first = rank - rank % block
            last = min(first + block - 1, q - 1)
            lo = np.searchsorted(rx, query[qperm[first], 0] - margin)
            hi = np.searchsorted(rx, query[qperm[last], 0] + margin, side="right")
        p = min(max(np.searchsorted(rx, qx), lo), hi)
        seed_lo, seed_hi = max(lo, p - k), min(hi, p + k)
        count = 0
        for j in range(seed_lo, seed_hi):     # nearest in x first: a tight k-th distance early
            if exclude_self and j == rank:
                continue
            count = _insert(dist, pos, count, k, _sq(query, qi, rs, j), j)
        for j in range(seed_lo - 1, lo - 1, -1):
            dx = qx - rx[j]
            if count == k and dx * dx > dist[k - 1]:
                break
            if not (exclude_self and j == rank):
                count = _insert(dist, pos, count, k, _sq(query, qi, rs, j), j)
        for j in range(seed_hi, hi):
            dx = rx[j] - qx
            if count == k and dx * dx > dist[k - 1]:
                break
            if not (exclude_self and j == rank):
                count = _insert(dist, pos, count, k, _sq(query, qi, rs, j), j)
        fallback = rperm[min(lo, n - 1)]
        for s in range(k):
            if s < count:
                out_dist[qi, s] = dist[s]
                out_idx[qi, s] = rperm[pos[s]]
            else:
                out_dist[qi, s] = _INF
                out_idx[qi, s] = fallback


class _Grid(NamedTuple):
    """A cloud's ref points bucketed on a uniform grid (`_grid`), with the queries' buckets."""

    lo: np.ndarray       # (3,) float64, the grid's corner
    cell: float          # the cell width
    dims: np.ndarray     # (3,) int64 cells per axis, row-major (x slowest)
    start: np.ndarray    # (cells + 1,) the ref points of cell c are ref_order[start[c]:start[c + 1]]
    ref_order: np.ndarray
    ref_sorted: np.ndarray   # (3, n) float32, the ref points in that order, one row per axis
    query_start: np.ndarray
    query_order: np.ndarray


@numba.njit(cache=True, nogil=True)
def _grid(query: np.ndarray, ref: np.ndarray, cell: float, same: bool) -> tuple[bool, _Grid]:
    """(usable, grid) of cells at least `cell` wide over both clouds (`same`: query is ref). Not usable for an
    empty or non-finite cloud (a non-finite point has no cell) or where a far outlier packs the points into a
    few cells (the searches' fallbacks are cheaper then)."""
    q, n = query.shape[0], ref.shape[0]
    lo = np.zeros(3, np.float64)
    hi = np.zeros(3, np.float64)
    dims = np.ones(3, np.int64)
    empty = np.zeros(1, np.int64)
    nothing = _Grid(lo, 1.0, dims, empty, empty, np.empty((3, 0), np.float32), empty, empty)
    if q == 0 or n == 0 or not (np.isfinite(query).all() and np.isfinite(ref).all()):
        return False, nothing
    for a in range(3):
        lo[a] = min(query[:, a].min(), ref[:, a].min())
        hi[a] = max(query[:, a].max(), ref[:, a].max())
    c = max(np.float64(cell), 1e-9)
    while True:   # coarser cells where the cloud is spread out: at most ~4 cells per point (counted in float)
        estimate = 1.0
        for a in range(3):
            estimate *= (hi[a] - lo[a]) / c + 1.0
        if estimate <= 4 * (n + q) + 64:
            break
        c *= 1.5
    cells = 1
    for a in range(3):
        dims[a] = int((hi[a] - lo[a]) / c) + 1
        cells *= dims[a]
    width = np.full(3, c)
    start, ridx = bucket_points(ref, lo, width, dims)
    pairs = 0   # point pairs sharing a cell: the grid's work grows with it
    for i in range(cells):
        pairs += (start[i + 1] - start[i]) ** 2
    if pairs > 64 * (n + q):
        return False, nothing
    qstart, qidx = (start, ridx) if same else bucket_points(query, lo, width, dims)
    rs = np.empty((3, n), np.float32)
    for p in range(n):
        for a in range(3):
            rs[a, p] = ref[ridx[p], a]
    return True, _Grid(lo, c, dims, start, ridx, rs, qstart, qidx)


@numba.njit(cache=True, nogil=True)
def _block_candidates(g: _Grid, cc: int, cc3: np.ndarray, cand: np.ndarray, cand_idx: np.ndarray) -> int:
    """Gathers the ref points of the 3 x 3 x 3 cells around cell `cc` (row-major; `cc3` its cell per axis) into
    `cand` (3, n) and their indices into `cand_idx`, the cell's own points first; returns their number."""
    m = 0
    for p in range(g.start[cc], g.start[cc + 1]):
        for a in range(3):
            cand[a, m] = g.ref_sorted[a, p]
        cand_idx[m] = g.ref_order[p]
        m += 1
    for jx in range(max(cc3[0] - 1, 0), min(cc3[0] + 1, g.dims[0] - 1) + 1):
        for jy in range(max(cc3[1] - 1, 0), min(cc3[1] + 1, g.dims[1] - 1) + 1):
            row = (jx * g.dims[1] + jy) * g.dims[2]   # the block's cells along z are consecutive
            for p in range(g.start[row + max(cc3[2] - 1, 0)], g.start[row + min(cc3[2] + 1, g.dims[2] - 1) + 1]):
                if g.start[cc] <= p < g.start[cc + 1]:
                    continue   # the own cell, taken first
                for a in range(3):
                    cand[a, m] = g.ref_sorted[a, p]
                cand_idx[m] = g.ref_order[p]
                m += 1
    return m


@numba.njit(cache=True, nogil=True, inline="always")
def _distances(x: np.float32, y: np.float32, z: np.float32, cand: np.ndarray, m: int, out: np.ndarray) -> None:
    for p in range(m):   # one vectorisable pass
        dx = x - cand[0, p]
        dy = y - cand[1, p]
        dz = z - cand[2, p]
        out[p] = dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _grid_block_search(query: np.ndarray, g: _Grid, k: int, limit: np.float32, exclude_self: bool, ball: bool,
                       within: np.float32, done: np.ndarray, out_dist: np.ndarray, out_idx: np.ndarray) -> None:
    """The k nearest ref points within squared distance `limit` of each query among those in the 3 x 3 x 3 cells
    around its own cell. The block's candidates are gathered once per cell, its own cell first (a tight k-th
    distance early), and every query of the cell computes its distances to them in one vectorisable pass.

    `ball`: done where at least one was found (the caller's cells hold the whole ball of `limit`); out_idx gets
    them, ascending, then the nearest repeated. Else: done where they are its k nearest of all (the k-th lies
    within the block) and within `within`; out_dist and out_idx get them."""
    n = g.ref_order.shape[0]
    cand = np.empty((3, n), np.float32)   # the current block's candidates, their indices and distances
    cand_idx = np.empty(n, np.int64)
    cand_dist = np.empty(n, np.float32)
    shrink = 1.0 - 1e-5
    # absolute float64 error of a query's distance to a block face (its cell index and the face are computed
    # separately): the bound is lowered by it, so a point a rounding error inside a face is safe
    slack = 8.0 * np.finfo(np.float64).eps * (max(np.abs(g.lo).max(), np.abs(g.lo + g.dims * g.cell).max())
                                              + g.cell)
    face_lo = np.empty(3, np.float64)
    face_hi = np.empty(3, np.float64)
    cc3 = np.empty(3, np.int64)
    dist = np.empty(k, np.float32)
    pos = np.empty(k, np.int64)
    for cc in range(len(g.query_start) - 1):
        if g.query_start[cc] == g.query_start[cc + 1]:
            continue
        cc3[0], cc3[1], cc3[2] = cc // (g.dims[1] * g.dims[2]), (cc // g.dims[2]) % g.dims[1], cc % g.dims[2]
        if not ball:   # the block's faces (a ball needs none); none (inf) where the block reaches the grid's edge
            for a in range(3):
                face_lo[a] = g.lo[a] + (cc3[a] - 1) * g.cell if cc3[a] > 0 else -np.inf
                face_hi[a] = g.lo[a] + (cc3[a] + 2) * g.cell if cc3[a] < g.dims[a] - 1 else np.inf
        m = _block_candidates(g, cc, cc3, cand, cand_idx)
        for t in range(g.query_start[cc], g.query_start[cc + 1]):
            qi = g.query_order[t]
            _distances(query[qi, 0], query[qi, 1], query[qi, 2], cand, m, cand_dist)
            count = 0
            worst = _INF
            for p in range(m):
                d = cand_dist[p]
                if d < worst and d <= limit and not (exclude_self and cand_idx[p] == qi):
                    count = _insert(dist, pos, count, k, d, cand_idx[p])
                    if count == k:
                        worst = dist[k - 1]
            if ball:
                if count > 0:
                    done[qi] = True
                    for s in range(k):
                        out_idx[qi, s] = pos[s] if s < count else pos[0]
                continue
            # every ref point outside the block is at least `bound` away (inf: the block is the whole grid)
            bound = np.inf
            for a in range(3):
                bound = min(bound, query[qi, a] - face_lo[a], face_hi[a] - query[qi, a])
            bound = max(bound - slack, 0.0)
            if count == k and dist[k - 1] <= bound * bound * shrink and dist[k - 1] <= within:
                done[qi] = True
                for s in range(k):
                    out_dist[qi, s] = dist[s]
                    out_idx[qi, s] = pos[s]


@numba.njit(cache=True, nogil=True)
def _grid_knn_cloud(query: np.ndarray, ref: np.ndarray, k: int, margin: np.float32, cell: float, exclude_self: bool,
                    windowed: bool, done: np.ndarray, out_dist: np.ndarray, out_idx: np.ndarray) -> None:
    """The exact k nearest ref points of each query where the grid search finds them (`_grid_block_search`): sets
    done[qi] (and the outputs) only where they are its k nearest of all and, `windowed`, all k lie within `margin`
    (the window search's result then, up to the order of exact ties)."""
    usable, g = _grid(query, ref, cell, exclude_self)
    if usable:   # else the window search answers every query
        within = margin * margin * np.float32(1.0 - 1e-5) if windowed else _INF
        _grid_block_search(query, g, k, _INF, exclude_self, False, within, done, out_dist, out_idx)


@numba.njit(cache=True, nogil=True)
def _grid_ball_cloud(query: np.ndarray, ref: np.ndarray, m: int, radius: float, done: np.ndarray,
                     out: np.ndarray) -> bool:
    """For each query with a ref point within `radius`: the up to m nearest of those, ascending, then the nearest
    repeated, in out (Q, m); sets done there. Cells of `radius` (plus room for rounding), so a query's 3 x 3 x 3
    block holds its whole ball. False (nothing done) where the cloud cannot be gridded."""
    usable, g = _grid(query, ref, radius * (1.0 + 1e-4), False)
    if usable:
        r2 = np.float32(radius * radius)   # as torch compares a float32 tensor with a Python float
        _grid_block_search(query, g, m, r2, False, True, _INF, done, np.empty((0, m), np.float32), out)
    return usable


@numba.njit(cache=True, nogil=True)
def knn(query: np.ndarray, ref: np.ndarray, k: int, margin: float, block: int, windowed: bool,
        exclude_self: bool, cell: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(squared distances, indices), each (B, Q, k), of the k nearest ref points of every query, ascending.

    `windowed`: only ref points whose x lies within `margin` of the x-range of the query's block of
    `block` x-sorted queries; else every ref point. `exclude_self` (query is ref): the point itself is
    skipped. Slots without a candidate hold distance inf and the ref point at the window's start.
    `cell` > 0: a grid search with cells of that size first (`_grid_knn_cloud`; faster for dense clouds such
    as the kNN graph over P_g; the same result up to the order of exact ties), the scan for the rest.
    """
    b, q = query.shape[0], query.shape[1]
    out_dist = np.empty((b, q, k), np.float32)
    out_idx = np.empty((b, q, k), np.int64)
    m32 = np.float32(margin)
    for c in range(b):
        done = np.zeros(q, np.bool_)
        if cell > 0 and k > 0:
            _grid_knn_cloud(query[c], ref[c], k, m32, cell, exclude_self, windowed, done, out_dist[c], out_idx[c])
        _knn_cloud(query[c], ref[c], k, m32, block, windowed, exclude_self, done, out_dist[c], out_idx[c])
    return out_dist, out_idx


@numba.njit(cache=True, nogil=True)
def ball_query(query: np.ndarray, ref: np.ndarray, m: int, radius: float, block: int, windowed: bool) -> np.ndarray:
    """Indices (B, Q, m) of the m nearest ref points within `radius` of every query, ascending, the slots beyond
    them holding the nearest ref point (PointNet++ padding); m <= the number of ref points, radius >= 0
    (ValueError otherwise). The nearest of a query
    without any within `radius` is sought like `knn`'s (`windowed`: in the x-window of margin `radius` of its
    block of `block` x-sorted queries). The same indices as `ops.ball_group` over `knn`'s result up to the order
    of exact ties: a grid finds every query's ball and the scan only the nearest point of the others."""
    b, q = query.shape[0], query.shape[1]
    if not 0 <= m <= ref.shape[1] or not radius >= 0:
        raise ValueError("ball_query: need 0 <= m <= the number of ref points and radius >= 0")
    out = np.empty((b, q, m), np.int64)
    if m == 0:
        return out
    r2 = np.float32(radius * radius)
    m32 = np.float32(radius)
    for c in range(b):
        done = np.zeros(q, np.bool_)
        if _grid_ball_cloud(query[c], ref[c], m, radius, done, out[c]):
            if done.all():
                continue
            k = 1   # only the nearest is left to find
        else:
            k = m   # no grid: every query's m nearest, as `knn`
        dist = np.empty((q, k), np.float32)
        idx = np.empty((q, k), np.int64)
        _knn_cloud(query[c], ref[c], k, m32, block, windowed, False, done, dist, idx)
        for qi in range(q):
            if not done[qi]:
                for s in range(m):
                    out[c, qi, s] = idx[qi, s] if s < k and not dist[qi, s] > r2 else idx[qi, 0]
    return out


MAX_ICP_GRID_CELLS = 1 << 22  # cells of the target grid at most (the cell grows beyond max_distance past it)


@numba.njit(cache=True, nogil=True)
def icp_planar(source: np.ndarray, target: np.ndarray, max_distance: float, iterations: int
                ) -> tuple[float, float, float, int]:
    """(yaw, tx, ty, pairs) of the trimmed planar ICP of `source` onto `target` (float64 (n, 3), (m, 3))."""
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    h = max_distance
    for _ in range(64):  # grow the cell until the grid is small enough (a cell >= max_distance stays exact)
        total = 1
        for a in range(3):
            lo[a] = target[:, a].min()
            dims[a] = int((target[:, a].max() - lo[a]) / h) + 1
            total *= dims[a]
        if total <= MAX_ICP_GRID_CELLS:
            break
        h *= 2.0
    start, order = bucket_points(target, lo, np.full(3, h), dims)

    limit = max_distance * max_distance
    yaw, tx, ty, pairs = 0.0, 0.0, 0.0, 0
    k = np.empty(3, np.int64)
    q = np.empty(3)
    for _ in range(iterations):
        cs, sn = math.cos(yaw), math.sin(yaw)
        n = 0
        sax = say = sbx = sby = dot = cross = 0.0
        for i in range(source.shape[0]):
            q[0] = cs * source[i, 0] - sn * source[i, 1] + tx
            q[1] = sn * source[i, 0] + cs * source[i, 1] + ty
            q[2] = source[i, 2]
            outside = False
            for a in range(3):
                k[a] = int(math.floor((q[a] - lo[a]) / h))
                if k[a] < -1 or k[a] > dims[a]:
                    outside = True
            if outside:
                continue
            best, hit = limit, -1
            for x in range(max(k[0] - 1, 0), min(k[0] + 1, dims[0] - 1) + 1):
                for y in range(max(k[1] - 1, 0), min(k[1] + 1, dims[1] - 1) + 1):
                    for z in range(max(k[2] - 1, 0), min(k[2] + 1, dims[2] - 1) + 1):
                        c = (x * dims[1] + y) * dims[2] + z
                        for p in range(start[c], start[c + 1]):
                            j = order[p]
                            dx = target[j, 0] - q[0]
                            dy = target[j, 1] - q[1]
                            dz = target[j, 2] - q[2]
                            d = dx * dx + dy * dy + dz * dz
                            if d < best:
                                best, hit = d, j
            if hit < 0:
                continue
            ax, ay, bx, by = source[i, 0], source[i, 1], target[hit, 0], target[hit, 1]
            n += 1
            sax += ax
            say += ay
            sbx += bx
            sby += by
            dot += ax * bx + ay * by
            cross += ax * by - ay * bx
        pairs = n
        if n == 0:
            break
        # closed-form planar Procrustes on the centred pairs
        new_yaw = math.atan2(cross - (sax * sby - say * sbx) / n, dot - (sax * sbx + say * sby) / n)
        cs, sn = math.cos(new_yaw), math.sin(new_yaw)
        new_tx = (sbx - (cs * sax - sn * say)) / n
        new_ty = (sby - (sn * sax + cs * say)) / n
        moved = abs(new_yaw - yaw) + abs(new_tx - tx) + abs(new_ty - ty)
        yaw, tx, ty = new_yaw, new_tx, new_ty
        if moved < 1e-6:
            break
    return yaw, tx, ty, pairs


def kernels_cached() -> bool:
    """True when numba's on-disk cache holds compiled kernels of this module (`python -m gd_completion.warmup` made
    them): a start then does not compile for about a minute."""
    from pathlib import Path

    return any((Path(__file__).parent / "__pycache__").glob(f"{Path(__file__).stem}.*.nbi"))
