"""Point-cloud operators: FPS, kNN and ball queries, grouping, neighbour means.

The neighbour searches (FPS, `window_knn`, `knn_graph`, `ball_group`) have one definition and two
implementations: compiled kernels (`kernels`, numba) for CPU tensors, and torch ops for CUDA tensors or
when `use_compiled_kernels(False)`. Both compute squared distances as ((dx*dx + dy*dy) + dz*dz) in
float32 (never through a GEMM, whose rounding depends on the matrix shapes), so their indices are
identical except the order of exact distance ties, and no result depends on the rest of the batch.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

# Distance entries per chunk in brute-force ball queries (keeps the matrix in cache).
_CHUNK_ENTRIES = 1 << 19
# Above this many distance entries the torch FPS computes one row of distances per step.
_FPS_DENSE_LIMIT = 1 << 22
_COMPILED = {"enabled": True}
# Grid cell of the kNN graph's grid search, in units of its margin (measured: 0.9 fastest on P_g, 0.75-1.0 within 3 %).
GRID_CELL = 0.9
# Queries per x-window of the windowed ball queries.
BALL_BLOCK = 32


def use_compiled_kernels(enabled: bool) -> bool:
    """Route CPU neighbour searches to the compiled kernels (default) or to the torch ops; returns the old value."""
    old = _COMPILED["enabled"]
    _COMPILED["enabled"] = bool(enabled)
    return old


@contextmanager
def torch_kernels() -> Iterator[None]:
    """Context in which CPU neighbour searches run the torch ops (the reference the kernels are tested against)."""
    old = use_compiled_kernels(False)
    try:
        yield
    finally:
        use_compiled_kernels(old)


def _compiled(t: Tensor) -> bool:
    return _COMPILED["enabled"] and t.device.type == "cpu"


def _as_numpy(t: Tensor) -> np.ndarray:
    return t.detach().to(torch.float32).contiguous().numpy()


def neighbour_distance(a: Tensor, b: Tensor) -> Tensor:
    """Squared distances (B, Na, Nb) computed as ((dx*dx + dy*dy) + dz*dz): the neighbour searches' arithmetic."""
    first = a[..., 0].unsqueeze(-1) - b[..., 0].unsqueeze(-2)
    d = first * first
    for c in (1, 2):
        diff = a[..., c].unsqueeze(-1) - b[..., c].unsqueeze(-2)
        d = d.add_(diff * diff)
    return d


def _fps_torch(xyz: Tensor, n: int) -> Tensor:
    """FPS with torch ops, 3 small ops per step: rows of a precomputed distance matrix, or (large clouds)
    one row computed per step; the same values either way (the kernels' elementwise arithmetic)."""
    b, m, _ = xyz.shape
    offset = torch.arange(b, device=xyz.device) * m
    dense = neighbour_distance(xyz, xyz).view(b * m, m) if b * m * m <= _FPS_DENSE_LIMIT else None
    flat = xyz.reshape(b * m, 3)
    far = torch.zeros(b, dtype=torch.long, device=xyz.device)
    picks = [far]
    mind = torch.full((b, m), float("inf"), dtype=xyz.dtype, device=xyz.device)
    for _ in range(n - 1):
        if dense is not None:
            row = dense.index_select(0, far + offset)
        else:
            row = neighbour_distance(xyz, flat.index_select(0, far + offset).unsqueeze(1)).squeeze(-1)
        mind = torch.minimum(mind, row)
        far = mind.argmax(1)
        picks.append(far)
    return torch.stack(picks, 1)


def farthest_point_sample(xyz: Tensor, n: int) -> Tensor:
    """Indices (B, n) long of a farthest point sampling of `xyz` (B, N, 3), starting at point 0.

    Deterministic (ties: the lowest index). Repeated points are harmless (distance 0, never NaN).
    When n > N, or when fewer than n distinct points exist, indices repeat: after N picks the FPS
    order is cycled. Prefixes are nested: fps(x, n)[:, :m] == fps(x, m).
    """
    if xyz.dim() != 3 or xyz.shape[-1] != 3:
        raise ValueError(f"farthest_point_sample expects (B, N, 3), got {tuple(xyz.shape)}")
    b, m, _ = xyz.shape
    if n <= 0 or m == 0:
        return torch.zeros(b, max(n, 0), dtype=torch.long, device=xyz.device)
    k = min(n, m)
    with torch.no_grad():
        if _compiled(xyz):
            from gd_completion import kernels
            idx = torch.from_numpy(kernels.fps(_as_numpy(xyz), k))
        else:
            idx = _fps_torch(xyz.detach().float(), k)
    if n > m:
        reps = -(-n // m)
        idx = idx.repeat(1, reps)[:, :n]
    return idx


def nearest_index(query: Tensor, target: Tensor, chunk_entries: int = 1 << 22) -> Tensor:
    """Index (B, Nq) long of the nearest `target` point of every `query` point (B, Nq, 3) / (B, Nt, 3), Nt > 0.

    One cloud at a time, in query chunks of at most `chunk_entries` distance entries: the argmin of
    |t|^2 - 2 q.t (one GEMM) on clouds centred on the target's mean (small coordinates, little
    cancellation). No gradient; callers recompute the distances to these points exactly (Chamfer loss
    and metrics).
    """
    b, nq, nt = query.shape[0], query.shape[1], target.shape[1]
    out = torch.empty(b, nq, dtype=torch.long, device=query.device)
    step = max(1, chunk_entries // max(nt, 1))
    with torch.no_grad():
        for i in range(b):
            centre = target[i].mean(0, keepdim=True)
            tc = target[i] - centre
            tt = (tc * tc).sum(-1)
            tc_t = tc.t().contiguous()
            for start in range(0, nq, step):
                approx = torch.addmm(tt, query[i, start:start + step] - centre, tc_t, alpha=-2.0)
                out[i, start:start + step] = approx.argmin(-1)
    return out


def flat_index(idx: Tensor, n: int) -> Tensor:
    """Turn per-batch indices (B, ...) into indices of the flattened (B*n, C) tensor, flattened."""
    b = idx.shape[0]
    offset = (torch.arange(b, device=idx.device) * n).view((b,) + (1,) * (idx.dim() - 1))
    return (idx + offset).reshape(-1)


def gather_points(x: Tensor, idx: Tensor) -> Tensor:
    """x (B, N, C) indexed by idx (B, ...) -> (B, ..., C), via index_select on the flattened tensor."""
    b, n, c = x.shape
    out = x.reshape(b * n, c).index_select(0, flat_index(idx, n))
    return out.view(idx.shape + (c,))


def knn_graph(points: Tensor, k: int, margin: float | None = None) -> Tensor:
    """Indices (B, N, k) of the k nearest other points of every point (one-way edges, self excluded).

    With `margin`, the x-sorted window search of `window_knn` (exact for points whose k-th neighbour
    is within `margin`); without, brute force over all pairs.
    """
    if margin is not None:
        return window_knn(points, points, k, margin, block=32, exclude_self=True, grid=True)[1]
    return _nearest_k(points, points, min(k, points.shape[1] - 1), None, 0, exclude_self=True)[1]


def neighbour_mean(x: Tensor, nbr_flat: Tensor, k: int) -> Tensor:
    """A x for the umbrella adjacency A = adjacency / k; x (B, N, C), nbr_flat from `flat_index(knn, N)`."""
    b, n, c = x.shape
    # embedding_bag(mean) gathers and averages in one pass without the (B, N, k, C) intermediate
    return F.embedding_bag(nbr_flat.view(b * n, k), x.reshape(b * n, c), mode="mean").view(b, n, c)


def ball_group(centers: Tensor, points: Tensor, radius: float, m: int, window: bool = False) -> Tensor:
    """Indices (B, Q, m) of the m nearest `points` of each center, those farther than `radius` replaced by
    the nearest one (PointNet++ ball-query padding). `window`: x-sorted window search with margin
    `radius` (`window_knn`; exact inside the ball); else over all points. CPU tensors take the compiled
    `kernels.ball_query` (a grid for the balls, the scan only for the nearest point of an empty one)."""
    b, q, _ = centers.shape
    mm = min(m, points.shape[1])
    if _compiled(centers):   # the same indices up to the order of exact ties, faster
        from gd_completion import kernels
        windowed = window and not _tiny(q, points.shape[1], BALL_BLOCK)
        idx = torch.from_numpy(kernels.ball_query(_as_numpy(centers), _as_numpy(points), mm, float(radius),
                                                  BALL_BLOCK, windowed))
    else:
        if window:
            dist, nn = window_knn(centers, points, mm, radius, block=BALL_BLOCK)
        else:
            dist, nn = _nearest_k(centers, points, mm, None, 0, exclude_self=False)
        idx = torch.where(dist > radius * radius, nn[..., :1], nn)
    if mm < m:
        idx = torch.cat([idx, idx[..., :1].expand(b, q, m - mm)], -1)
    return idx


def smallest_k(d: Tensor, k: int, group: int = 8) -> tuple[Tensor, Tensor]:
    """(values, indices) of the k smallest entries of each row of d (..., W), sorted ascending.

    Exact two-stage selection: the k groups of `group` columns with the smallest minima contain the
    k smallest entries; topk then runs on k*group candidates instead of W (topk is the CPU hot spot).
    A row with fewer than k finite entries fills its last slots with inf, at indices within [0, W).
    """
    w = d.shape[-1]
    if w < 4 * k * group:
        return d.topk(k, dim=-1, largest=False, sorted=True)
    pad = (-w) % group
    if pad:
        d = F.pad(d, (0, pad), value=float("inf"))
    mins = d.view(d.shape[:-1] + (-1, group)).amin(-1)
    blk = mins.topk(k, dim=-1, largest=False, sorted=False).indices
    cand = (blk.unsqueeze(-1) * group + torch.arange(group, device=d.device)).flatten(-2)
    val, j = d.gather(-1, cand).topk(k, dim=-1, largest=False, sorted=True)
    return val, cand.gather(-1, j).clamp_(max=w - 1)   # an inf slot may have picked a padding column


def window_knn(query: Tensor, ref: Tensor, k: int, margin: float, block: int = 64,
               exclude_self: bool = False, grid: bool = False) -> tuple[Tensor, Tensor]:
    """k nearest `ref` points of every `query` point: (squared distances, indices), each (B, Q, k), sorted.

    Both clouds are sorted along x (the vehicle's long axis); each block of `block` consecutive sorted
    queries searches only the ref points whose x lies within `margin` of the block's x-range [lo, hi).
    Exact for every query whose k-th neighbour is within `margin` (so exact for ball queries of radius
    <= margin); otherwise the neighbours are the nearest inside the window, and slots the window cannot
    fill hold distance inf and the ref point at its start. `exclude_self` (query is ref) drops the point
    itself. Tiny clouds (Q*N <= 4 block^2 or N <= 2 block) are searched whole. `grid`: the compiled kernel
    tries a grid search first (same result up to exact ties; faster where most queries have their k
    neighbours within `margin`, as in the kNN graph over P_g).
    """
    q, n = query.shape[1], ref.shape[1]
    kk = min(k, n - 1 if exclude_self else n)
    return _nearest_k(query, ref, kk, None if _tiny(q, n, block) else margin, block, exclude_self,
                      cell=GRID_CELL * margin if grid else 0.0)


def _tiny(q: int, n: int, block: int) -> bool:
    """Whether `window_knn` searches q queries over n ref points whole instead of by windows."""
    return q * n <= 4 * block * block or n <= 2 * block


def _nearest_k(query: Tensor, ref: Tensor, k: int, margin: float | None, block: int,
               exclude_self: bool, cell: float = 0.0) -> tuple[Tensor, Tensor]:
    """k nearest ref points per query over the whole ref cloud (margin None) or the x-windows of `window_knn`."""
    with torch.no_grad():
        if _compiled(query):
            from gd_completion import kernels
            dist, idx = kernels.knn(_as_numpy(query), _as_numpy(ref), k, float(margin or 0.0), max(block, 1),
                                    margin is not None, exclude_self, float(cell))
            return torch.from_numpy(dist), torch.from_numpy(idx)
        if margin is None:
            return _brute_knn_torch(query, ref, k, exclude_self)
        return _window_knn_torch(query, ref, k, margin, block, exclude_self)


def _brute_knn_torch(query: Tensor, ref: Tensor, k: int, exclude_self: bool) -> tuple[Tensor, Tensor]:
    b, q, _ = query.shape
    rows = max(16, _CHUNK_ENTRIES // max(b * ref.shape[1], 1))
    dists, idxs = [], []
    for s in range(0, q, rows):    # row chunks keep the distance matrix in cache (elementwise: same values)
        d = neighbour_distance(query[:, s:s + rows], ref)
        if exclude_self:
            rows_here = torch.arange(s, s + d.shape[1], device=d.device)
            d[:, torch.arange(d.shape[1], device=d.device), rows_here] = float("inf")
        dist, nn = d.topk(k, dim=-1, largest=False, sorted=True)
        dists.append(dist)
        idxs.append(nn)
    return torch.cat(dists, 1), torch.cat(idxs, 1)


def _window_knn_torch(query: Tensor, ref: Tensor, k: int, margin: float, block: int,
                      exclude_self: bool) -> tuple[Tensor, Tensor]:
    b, q, _ = query.shape
    n = ref.shape[1]
    rx, rperm = ref[..., 0].sort(dim=1, stable=True)
    if exclude_self:
        qx, qperm = rx, rperm
    else:
        qx, qperm = query[..., 0].sort(dim=1, stable=True)
    nb = -(-q // block)
    pad = nb * block - q
    if pad:
        qperm = torch.cat([qperm, qperm[:, -1:].expand(b, pad)], 1)
        qx = torch.cat([qx, qx[:, -1:].expand(b, pad)], 1)
    qs = gather_points(query, qperm)                                   # (B, nb*block, 3) sorted by x
    rs = gather_points(ref, rperm)
    lo = torch.searchsorted(rx, (qx[:, ::block] - margin).contiguous())
    hi = torch.searchsorted(rx, (qx[:, block - 1::block] + margin).contiguous(), right=True)
    w = int(min(max(int((hi - lo).max()), k + (1 if exclude_self else 0)), n))
    start = lo.clamp(max=n - w)                                        # (B, nb)
    cand = start.unsqueeze(-1) + torch.arange(w, device=ref.device)    # (B, nb, w) sorted-ref positions
    cpts = gather_points(rs, cand).view(b * nb, w, 3)
    d = neighbour_distance(qs.view(b * nb, block, 3), cpts)            # (B*nb, block, w)
    # only [lo, hi) counts: the result of a cloud must not depend on the other clouds of the batch
    outside = (cand < lo.unsqueeze(-1)) | (cand >= hi.unsqueeze(-1))
    d.masked_fill_(outside.view(b * nb, 1, w), float("inf"))
    if exclude_self:   # a query's own sorted position, wherever it falls (never an index out of range)
        own = torch.arange(nb * block, device=ref.device).clamp(max=q - 1).view(1, nb, block, 1)
        d.masked_fill_((cand.unsqueeze(2) == own).view(b * nb, block, w), float("inf"))
    dist, j = smallest_k(d, k)                                         # (B*nb, block, k)
    pos = torch.gather(cand.view(b * nb, 1, w).expand(-1, block, -1), 2, j).view(b, nb * block, k)
    # fewer than k candidates in the window: the ref point at the window's start
    fallback = lo.clamp(max=n - 1).view(b, nb, 1, 1).expand(b, nb, block, k).reshape(b, nb * block, k)
    pos = torch.where(torch.isinf(dist).view(b, nb * block, k), fallback, pos)
    idx = torch.gather(rperm, 1, pos.view(b, -1)).view(b, nb * block, k)
    dist = dist.view(b, nb * block, k)
    # undo the query sort (padding rows are duplicates of the last query and are dropped)
    inv = torch.empty(b, q, dtype=torch.long, device=ref.device)
    inv.scatter_(1, qperm[:, :q], torch.arange(q, device=ref.device).expand(b, q))
    return gather_points(dist, inv), gather_points(idx, inv)
