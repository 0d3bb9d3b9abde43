"""Vectorised point-cloud operators (CPU and CUDA, no custom kernels): FPS, kNN, grouping, neighbour means."""
from __future__ import annotations

import warnings

import torch
import torch.nn.functional as F
from torch import Tensor


# Above this many distance entries FPS uses the low-memory path (one row of distances per step).
_FPS_DENSE_LIMIT = 1 << 22
# Distance entries per chunk in kNN / ball queries (keeps the matrix in cache).
_CHUNK_ENTRIES = 1 << 19


def _fps_dense(xyz: Tensor, n: int) -> Tensor:
    """FPS with a precomputed distance matrix: 3 small ops per step."""
    b, m, _ = xyz.shape
    sq = (xyz * xyz).sum(-1, keepdim=True)
    one = torch.ones_like(sq)
    d = torch.bmm(torch.cat([xyz, sq, one], -1), torch.cat([-2.0 * xyz, one, sq], -1).transpose(1, 2))
    d = d.clamp_min_(0.0).view(b * m, m)
    offset = torch.arange(b, device=xyz.device) * m
    far = torch.zeros(b, dtype=torch.long, device=xyz.device)
    picks = [far]
    mind = torch.full((b, m), float("inf"), dtype=xyz.dtype, device=xyz.device)
    for i in range(n - 1):
        mind = torch.minimum(mind, d.index_select(0, far + offset))
        far = mind.argmax(1)
        picks.append(far)
    return torch.stack(picks, 1)


def _fps_rows(xyz: Tensor, n: int) -> Tensor:
    """FPS computing one row of distances per step (large clouds)."""
    b, m, _ = xyz.shape
    flat = xyz.reshape(b * m, 3)
    offset = torch.arange(b, device=xyz.device) * m
    far = torch.zeros(b, dtype=torch.long, device=xyz.device)
    picks = [far]
    mind = torch.full((b, m), float("inf"), dtype=xyz.dtype, device=xyz.device)
    for i in range(n - 1):
        c = flat.index_select(0, far + offset).unsqueeze(1)
        mind = torch.minimum(mind, (xyz - c).pow(2).sum(-1))
        far = mind.argmax(1)
        picks.append(far)
    return torch.stack(picks, 1)


with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    _fps_dense = torch.jit.script(_fps_dense)
    _fps_rows = torch.jit.script(_fps_rows)


def farthest_point_sample(xyz: Tensor, n: int) -> Tensor:
    """Indices (B, n) long of a farthest point sampling of `xyz` (B, N, 3), starting at point 0.

    Deterministic. Repeated points are harmless (distance 0, never NaN). When n > N, or when fewer
    than n distinct points exist, indices repeat: after N picks the FPS order is cycled.
    Prefixes are nested: fps(x, n)[:, :m] == fps(x, m).
    """
    if xyz.dim() != 3 or xyz.shape[-1] != 3:
        raise ValueError(f"farthest_point_sample expects (B, N, 3), got {tuple(xyz.shape)}")
    b, m, _ = xyz.shape
    if n <= 0 or m == 0:
        return torch.zeros(b, max(n, 0), dtype=torch.long, device=xyz.device)
    k = min(n, m)
    with torch.no_grad():
        x = xyz.detach().float()
        idx = _fps_dense(x, k) if b * m * m <= _FPS_DENSE_LIMIT else _fps_rows(x, k)
    if n > m:
        reps = -(-n // m)
        idx = idx.repeat(1, reps)[:, :n]
    return idx


def square_distance(a: Tensor, b: Tensor) -> Tensor:
    """Squared Euclidean distances (B, Na, Nb) between a (B, Na, 3) and b (B, Nb, 3), >= 0."""
    aa = (a * a).sum(-1, keepdim=True)
    bb = (b * b).sum(-1, keepdim=True)
    # one GEMM on augmented coordinates [a, |a|^2, 1] . [-2b, 1, |b|^2]: no broadcast copy of the output
    lhs = torch.cat([a, aa, torch.ones_like(aa)], -1)
    rhs = torch.cat([-2.0 * b, torch.ones_like(bb), bb], -1)
    return torch.bmm(lhs, rhs.transpose(1, 2)).clamp_min_(0.0)


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
    with torch.no_grad():
        if margin is not None:
            return window_knn(points, points, k, margin, block=32, exclude_self=True)[1]
        d = square_distance(points, points)
        d.diagonal(dim1=1, dim2=2).fill_(float("inf"))
        return d.topk(k, dim=-1, largest=False, sorted=False).indices


def neighbour_mean(x: Tensor, nbr_flat: Tensor, k: int) -> Tensor:
    """A x for the umbrella adjacency A = adjacency / k; x (B, N, C), nbr_flat from `flat_index(knn, N)`."""
    b, n, c = x.shape
    # embedding_bag(mean) gathers and averages in one pass without the (B, N, k, C) intermediate
    return F.embedding_bag(nbr_flat.view(b * n, k), x.reshape(b * n, c), mode="mean").view(b, n, c)


def ball_group(centers: Tensor, points: Tensor, radius: float, m: int, window: bool = False) -> Tensor:
    """Indices (B, Q, m) of the m nearest `points` of each center, those farther than `radius` replaced by
    the nearest one (PointNet++ ball-query padding). `window`: x-sorted window search with margin
    `radius` (`window_knn`; exact inside the ball); else brute force in row chunks that stay in cache."""
    with torch.no_grad():
        b, q, _ = centers.shape
        n = points.shape[1]
        mm = min(m, n)
        if window:
            dist, nn = window_knn(centers, points, mm, radius, block=32)
            idx = torch.where(dist > radius * radius, nn[..., :1], nn)
            return idx if mm == m else torch.cat([idx, idx[..., :1].expand(b, q, m - mm)], -1)
        rows = max(16, _CHUNK_ENTRIES // max(b * n, 1))
        out = []
        for s in range(0, q, rows):
            dist, nn = square_distance(centers[:, s:s + rows], points).topk(mm, dim=-1, largest=False, sorted=True)
            out.append(torch.where(dist > radius * radius, nn[..., :1], nn))
        idx = torch.cat(out, 1) if len(out) > 1 else out[0]
        if mm < m:
            idx = torch.cat([idx, idx[..., :1].expand(b, q, m - mm)], -1)
        return idx


def smallest_k(d: Tensor, k: int, group: int = 8) -> tuple[Tensor, Tensor]:
    """(values, indices) of the k smallest entries of each row of d (..., W), sorted ascending.

    Exact two-stage selection: the k groups of `group` columns with the smallest minima contain the
    k smallest entries; topk then runs on k*group candidates instead of W (topk is the CPU hot spot).
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
    return val, cand.gather(-1, j)


def window_knn(query: Tensor, ref: Tensor, k: int, margin: float, block: int = 64,
               exclude_self: bool = False) -> tuple[Tensor, Tensor]:
    """k nearest `ref` points of every `query` point: (squared distances, indices), each (B, Q, k), sorted.

    Both clouds are sorted along x (the vehicle's long axis); each block of `block` consecutive sorted
    queries searches only the ref points whose x lies within `margin` of the block's x-range (window
    width = the largest such count in the batch, computed per call). Exact for every query whose k-th
    neighbour is within `margin` (so exact for ball queries of radius <= margin); otherwise the
    neighbours are the nearest inside the window. `exclude_self` (query is ref) drops the point itself.
    """
    with torch.no_grad():
        b, q, _ = query.shape
        n = ref.shape[1]
        kk = min(k, n - 1 if exclude_self else n)
        if q * n <= 4 * block * block or n <= 2 * block:   # tiny clouds: brute force
            d = square_distance(query, ref)
            if exclude_self:
                d.diagonal(dim1=1, dim2=2).fill_(float("inf"))
            return d.topk(kk, dim=-1, largest=False, sorted=True)
        rx, rperm = ref[..., 0].sort(dim=1)
        if exclude_self:
            qx, qperm = rx, rperm
        else:
            qx, qperm = query[..., 0].sort(dim=1)
        nb = -(-q // block)
        pad = nb * block - q
        if pad:
            qperm = torch.cat([qperm, qperm[:, -1:].expand(b, pad)], 1)
            qx = torch.cat([qx, qx[:, -1:].expand(b, pad)], 1)
        qs = gather_points(query, qperm)                                   # (B, nb*block, 3) sorted by x
        rs = gather_points(ref, rperm)
        lo = torch.searchsorted(rx, (qx[:, ::block] - margin).contiguous())
        hi = torch.searchsorted(rx, (qx[:, block - 1::block] + margin).contiguous(), right=True)
        w = int(min(max(int((hi - lo).max()), kk + (1 if exclude_self else 0)), n))
        start = lo.clamp(max=n - w)                                        # (B, nb)
        cand = start.unsqueeze(-1) + torch.arange(w, device=ref.device)    # (B, nb, w) sorted-ref positions
        cpts = gather_points(rs, cand).view(b * nb, w, 3)
        d = square_distance(qs.view(b * nb, block, 3), cpts)               # (B*nb, block, w)
        # only [lo, hi) counts: the result of a cloud must not depend on the other clouds of the batch
        outside = (cand < lo.unsqueeze(-1)) | (cand >= hi.unsqueeze(-1))
        d.masked_fill_(outside.view(b * nb, 1, w), float("inf"))
        if exclude_self:
            col = torch.arange(nb * block, device=ref.device).clamp(max=q - 1).view(1, nb, block) - start.unsqueeze(-1)
            d.view(-1, w).scatter_(1, col.reshape(-1, 1), float("inf"))
        dist, j = smallest_k(d, kk)                                        # (B*nb, block, kk)
        pos = torch.gather(cand.view(b * nb, 1, w).expand(-1, block, -1), 2, j).view(b, nb * block, kk)
        # fewer than k candidates in the window: fall back to the ref point nearest in x to the block
        fallback = lo.clamp(max=n - 1).view(b, nb, 1, 1).expand(b, nb, block, kk).reshape(b, nb * block, kk)
        pos = torch.where(torch.isinf(dist).view(b, nb * block, kk), fallback, pos)
        idx = torch.gather(rperm, 1, pos.view(b, -1)).view(b, nb * block, kk)
        dist = dist.view(b, nb * block, kk)
        # undo the query sort (padding rows are duplicates of the last query and are dropped)
        inv = torch.empty(b, q, dtype=torch.long, device=ref.device)
        inv.scatter_(1, qperm[:, :q], torch.arange(q, device=ref.device).expand(b, q))
        return gather_points(dist, inv), gather_points(idx, inv)
