"""Compiled CPU kernels (numba) for FPS and the x-window neighbour searches of `ops`.

`fps_pruned` is the same FPS for large clouds (the measured merge): it skips the kd leaves that the newly
chosen point cannot bring closer, and returns exactly what the plain scan returns.

Same semantics and the same float32 arithmetic as the torch path in `ops`: squared distances are
((dx*dx + dy*dy) + dz*dz) with dx = a_x - b_x, FPS starts at point 0 and takes the first maximum,
and a window search considers exactly the ref points whose x lies in the block's window [lo, hi).
Results are identical to the torch path except the order of exact distance ties. Each cloud is
computed on its own (batch independent); the kernels release the GIL, so threads run them in parallel.

The k nearest candidates are found by scanning the x-sorted ref points outwards from the query's x
(left, then right) and stopping once dx*dx exceeds the current k-th distance: the full distance is
never smaller than dx*dx in float32, so the pruned scan selects the same k smallest entries as a scan
of the whole window.
"""
from __future__ import annotations

import numba
import numpy as np

_INF = np.float32(np.inf)


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
    """Indices (B, n) int64 of the farthest point sampling of each cloud of xyz (B, M, 3) float32, n <= M."""
    b = xyz.shape[0]
    out = np.empty((b, n), np.int64)
    for c in range(b):
        _fps_cloud(xyz[c], n, out[c])
    return out


@numba.njit(cache=True, nogil=True)
def _kd_leaves(xyz: np.ndarray, leaf: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A permutation of the points into kd-tree leaves of at most `leaf` points (median splits on the widest
    axis), and the leaves' [start, end) ranges into it."""
    m = xyz.shape[0]
    order = np.arange(m)
    starts = np.empty(2 * m // leaf + 2, np.int64)
    ends = np.empty(2 * m // leaf + 2, np.int64)
    stack = np.empty((128, 2), np.int64)   # depth <= log2(m) < 64: two entries per level
    stack[0, 0], stack[0, 1] = 0, m
    top, count = 1, 0
    while top > 0:
        top -= 1
        s, e = stack[top, 0], stack[top, 1]
        if e - s <= leaf:
            starts[count], ends[count] = s, e
            count += 1
            continue
        axis, widest = 0, np.float32(-1.0)
        for a in range(3):
            lo, hi = _INF, -_INF
            for i in range(s, e):
                lo, hi = min(lo, xyz[order[i], a]), max(hi, xyz[order[i], a])
            if hi - lo > widest:
                axis, widest = a, hi - lo
        segment = order[s:e].copy()
        keys = np.empty(e - s, np.float32)
        for i in range(e - s):
            keys[i] = xyz[segment[i], axis]
        perm = np.argsort(keys, kind="mergesort")
        for i in range(e - s):
            order[s + i] = segment[perm[i]]
        mid = s + (e - s) // 2
        stack[top, 0], stack[top, 1] = s, mid
        stack[top + 1, 0], stack[top + 1, 1] = mid, e
        top += 2
    return order, starts[:count], ends[:count]


@numba.njit(cache=True, nogil=True)
def fps_pruned(xyz: np.ndarray, n: int, leaf: int = 128) -> np.ndarray:
    """Indices (n,) int64 of the farthest point sampling of one cloud xyz (M, 3) float32, n <= M: the same
    indices as `fps` (start at point 0, ties to the lowest index, the same float32 distances).

    The points are grouped into kd leaves; a leaf is rescanned only when the new point lies closer to its
    bounding box than the leaf's largest current distance (with a 1e-5 relative margin, far above float32
    rounding), so a skipped leaf is one where no distance could have dropped.
    """
    m = xyz.shape[0]
    order, starts, ends = _kd_leaves(xyz, leaf)
    leaves = starts.shape[0]
    pts = np.empty((m, 3), np.float32)
    for i in range(m):
        pts[i] = xyz[order[i]]
    lo = np.full((leaves, 3), np.inf)
    hi = np.full((leaves, 3), -np.inf)
    for f in range(leaves):
        for i in range(starts[f], ends[f]):
            for a in range(3):
                lo[f, a] = min(lo[f, a], pts[i, a])
                hi[f, a] = max(hi[f, a], pts[i, a])
    mind = np.full(m, _INF, np.float32)
    leaf_max = np.full(leaves, _INF, np.float32)
    leaf_arg = np.zeros(leaves, np.int64)   # original index of the leaf's farthest point
    out = np.empty(n, np.int64)
    far = 0
    out[0] = 0
    for step in range(1, n):
        c = xyz[far]
        best = np.float32(-1.0)
        arg = m
        for f in range(leaves):
            gap = 0.0
            for a in range(3):
                if c[a] < lo[f, a]:
                    gap += (lo[f, a] - c[a]) ** 2
                elif c[a] > hi[f, a]:
                    gap += (c[a] - hi[f, a]) ** 2
            if gap * (1.0 - 1e-5) <= leaf_max[f]:
                top = np.float32(-1.0)
                top_arg = m
                for i in range(starts[f], ends[f]):
                    dx = pts[i, 0] - c[0]
                    dy = pts[i, 1] - c[1]
                    dz = pts[i, 2] - c[2]
                    d = dx * dx + dy * dy + dz * dz
                    if d < mind[i]:
                        mind[i] = d
                    if mind[i] > top or (mind[i] == top and order[i] < top_arg):
                        top, top_arg = mind[i], order[i]
                leaf_max[f], leaf_arg[f] = top, top_arg
            if leaf_max[f] > best or (leaf_max[f] == best and leaf_arg[f] < arg):
                best, arg = leaf_max[f], leaf_arg[f]
        far = arg
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
               exclude_self: bool, out_dist: np.ndarray, out_idx: np.ndarray) -> None:
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


@numba.njit(cache=True, nogil=True)
def knn(query: np.ndarray, ref: np.ndarray, k: int, margin: float, block: int, windowed: bool,
        exclude_self: bool) -> tuple[np.ndarray, np.ndarray]:
    """(squared distances, indices), each (B, Q, k), of the k nearest ref points of every query, ascending.

    `windowed`: only ref points whose x lies within `margin` of the x-range of the query's block of
    `block` x-sorted queries; else every ref point. `exclude_self` (query is ref): the point itself is
    skipped. Slots without a candidate hold distance inf and the ref point at the window's start.
    """
    b, q = query.shape[0], query.shape[1]
    out_dist = np.empty((b, q, k), np.float32)
    out_idx = np.empty((b, q, k), np.int64)
    m32 = np.float32(margin)
    for c in range(b):
        _knn_cloud(query[c], ref[c], k, m32, block, windowed, exclude_self, out_dist[c], out_idx[c])
    return out_dist, out_idx
