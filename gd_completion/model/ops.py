"""Vectorised point-cloud operators (CPU and CUDA, no custom kernels): FPS, kNN, grouping, neighbour means."""
from __future__ import annotations

import warnings

import torch
from torch import Tensor


# Above this many distance entries FPS uses the low-memory path (one row of distances per step).
_FPS_DENSE_LIMIT = 1 << 22
# Distance entries per chunk in kNN / ball queries (keeps the matrix in cache).
_CHUNK_ENTRIES = 1 << 19


def _fps_dense(xyz: Tensor, n: int) -> Tensor:
    """FPS with a precomputed distance matrix: 3 small ops per step."""
    b, m, _ = xyz.shape
    sq = (xyz * xyz).sum(-1)
    d = torch.baddbmm(sq.unsqueeze(2) + sq.unsqueeze(1), xyz, xyz.transpose(1, 2), alpha=-2.0)
    d = d.clamp_min_(0.0).view(b * m, m)
    offset = torch.arange(b, device=xyz.device) * m
    idx = torch.zeros(n, b, dtype=torch.long, device=xyz.device)
    far = torch.zeros(b, dtype=torch.long, device=xyz.device)
    mind = torch.full((b, m), float("inf"), dtype=xyz.dtype, device=xyz.device)
    for i in range(n):
        idx[i] = far
        mind = torch.minimum(mind, d.index_select(0, far + offset))
        far = mind.argmax(1)
    return idx.t().contiguous()


def _fps_rows(xyz: Tensor, n: int) -> Tensor:
    """FPS computing one row of distances per step (large clouds)."""
    b, m, _ = xyz.shape
    flat = xyz.reshape(b * m, 3)
    offset = torch.arange(b, device=xyz.device) * m
    idx = torch.zeros(n, b, dtype=torch.long, device=xyz.device)
    far = torch.zeros(b, dtype=torch.long, device=xyz.device)
    mind = torch.full((b, m), float("inf"), dtype=xyz.dtype, device=xyz.device)
    for i in range(n):
        idx[i] = far
        c = flat.index_select(0, far + offset).unsqueeze(1)
        mind = torch.minimum(mind, (xyz - c).pow(2).sum(-1))
        far = mind.argmax(1)
    return idx.t().contiguous()


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
    bb = (b * b).sum(-1).unsqueeze(1)
    return torch.baddbmm(aa + bb, a, b.transpose(1, 2), alpha=-2.0).clamp_min_(0.0)


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


def knn_graph(points: Tensor, k: int) -> Tensor:
    """Indices (B, N, k) of the k nearest other points of every point (one-way edges, self excluded)."""
    with torch.no_grad():
        b, n, _ = points.shape
        rows = max(16, _CHUNK_ENTRIES // max(b * n, 1))
        out = []
        for s in range(0, n, rows):
            d = square_distance(points[:, s:s + rows], points)
            d.diagonal(offset=s, dim1=1, dim2=2).fill_(float("inf"))
            out.append(d.topk(k, dim=-1, largest=False, sorted=False).indices)
        return torch.cat(out, 1) if len(out) > 1 else out[0]


def neighbour_mean(x: Tensor, nbr_flat: Tensor, k: int) -> Tensor:
    """A x for the umbrella adjacency A = adjacency / k; x (B, N, C), nbr_flat from `flat_index(knn, N)`."""
    b, n, c = x.shape
    return x.reshape(b * n, c).index_select(0, nbr_flat).view(b, n, k, c).mean(2)


def ball_group(centers: Tensor, points: Tensor, radius: float, m: int) -> Tensor:
    """Indices (B, Q, m) of the m nearest `points` of each center, those farther than `radius` replaced by
    the nearest one (PointNet++ ball-query padding); computed in row chunks so the distances stay in cache."""
    with torch.no_grad():
        b, q, _ = centers.shape
        n = points.shape[1]
        mm = min(m, n)
        rows = max(16, _CHUNK_ENTRIES // max(b * n, 1))
        out = []
        for s in range(0, q, rows):
            dist, nn = square_distance(centers[:, s:s + rows], points).topk(mm, dim=-1, largest=False, sorted=True)
            out.append(torch.where(dist > radius * radius, nn[..., :1], nn))
        idx = torch.cat(out, 1) if len(out) > 1 else out[0]
        if mm < m:
            idx = torch.cat([idx, idx[..., :1].expand(b, q, m - mm)], -1)
        return idx
