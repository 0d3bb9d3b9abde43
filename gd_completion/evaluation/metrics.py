"""Completion metrics (normalised box frame): Chamfer-L2 and its two directions, Fidelity, Coverage error,
F-score. The one place these are defined; the training loss (`model.losses.chamfer_l2`) is their
differentiable twin, tested against them."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from gd_completion.model.ops import gather_points, nearest_index

# Report units: Chamfer (and its directions) x1e4 at 2048 points, Fidelity and Coverage error x1e3.
CD_SCALE = 1e4
FIDELITY_SCALE = 1e3
COVERAGE_SCALE = 1e3
# Largest number of (query, target) distance entries held at once.
CHUNK_ENTRIES = 1 << 22


def _batched(points: np.ndarray | Tensor) -> tuple[Tensor, bool]:
    t = torch.as_tensor(np.asarray(points, dtype=np.float32) if not isinstance(points, Tensor) else points)
    t = t.float()
    if t.dim() == 2:
        return t.unsqueeze(0), True
    if t.dim() != 3 or t.shape[-1] != 3:
        raise ValueError(f"point clouds must be (N, 3) or (B, N, 3), got {tuple(t.shape)}")
    return t, False


def nearest_sq_distance(query: np.ndarray | Tensor, target: np.ndarray | Tensor,
                        chunk_entries: int = CHUNK_ENTRIES) -> Tensor:
    """Squared distance from each query point to its nearest target point: (B, Nq) (or (Nq,) unbatched).

    The nearest neighbour is the one the training loss uses (`model.ops.nearest_index`); its distance is
    recomputed exactly from the coordinate differences, so coincident points give exactly 0. An empty
    target gives +inf.
    """
    q, single = _batched(query)
    t, _ = _batched(target)
    if q.shape[0] != t.shape[0]:
        raise ValueError(f"batch sizes differ: {tuple(q.shape)} vs {tuple(t.shape)}")
    if t.shape[1] == 0:
        out = torch.full(q.shape[:2], float("inf"))
    else:
        with torch.no_grad():
            out = (q - gather_points(t, nearest_index(q, t, chunk_entries))).pow(2).sum(-1)
    return out[0] if single else out


def _mean(d: Tensor) -> Tensor:
    return d.mean(-1) if d.shape[-1] else torch.full(d.shape[:-1], float("nan"))


def chamfer_directional(output: np.ndarray | Tensor, gt: np.ndarray | Tensor) -> tuple[Tensor, Tensor]:
    """(CD(D,G), CD(G,D)): mean squared distance output->GT (fidelity-like) and GT->output (completeness).

    Unscaled; (B,) for batched input, 0-d for single clouds.
    """
    return _mean(nearest_sq_distance(output, gt)), _mean(nearest_sq_distance(gt, output))


def chamfer(output: np.ndarray | Tensor, gt: np.ndarray | Tensor) -> Tensor:
    """Chamfer-L2: squared distances, each direction averaged over its points, the two summed (unscaled)."""
    dg, gd = chamfer_directional(output, gt)
    return dg + gd


def fidelity(partial: np.ndarray | Tensor, output: np.ndarray | Tensor) -> Tensor:
    """Fidelity: mean squared distance from each input point to its nearest output point (unscaled)."""
    return _mean(nearest_sq_distance(partial, output))


def coverage_error(reference: np.ndarray | Tensor, output: np.ndarray | Tensor) -> Tensor:
    """Coverage error: mean squared distance from each reference point to its nearest output point (unscaled)."""
    return _mean(nearest_sq_distance(reference, output))


# F-score threshold (normalised frame: 1 % of the vehicle length), as in the completion literature (F-Score@1%).
F_SCORE_THRESHOLD = 0.01


def f_score(output: np.ndarray | Tensor, gt: np.ndarray | Tensor, threshold: float = F_SCORE_THRESHOLD) -> Tensor:
    """F-score at `threshold`: harmonic mean of precision (output points within `threshold` of the ground
    truth) and recall (ground-truth points within `threshold` of the output); 0 when both are 0."""
    return f_score_of(nearest_sq_distance(output, gt), nearest_sq_distance(gt, output), threshold)


def f_score_of(output_to_gt: Tensor, gt_to_output: Tensor, threshold: float = F_SCORE_THRESHOLD) -> Tensor:
    """`f_score` from the two directions' squared nearest distances (as `nearest_sq_distance` gives them)."""
    t2 = threshold * threshold
    precision = (output_to_gt <= t2).float().mean(-1)
    recall = (gt_to_output <= t2).float().mean(-1)
    total = precision + recall
    return torch.where(total > 0, 2 * precision * recall / total.clamp_min(1e-12), torch.zeros_like(total))


# Ground-truth points within this distance of an input point count as observed (normalised frame).
OBSERVED_RADIUS = 0.05


def observed_mask(gt: np.ndarray | Tensor, partial: np.ndarray | Tensor, radius: float = OBSERVED_RADIUS) -> Tensor:
    """True for each ground-truth point with an input point within `radius` (same shape as the distances)."""
    return nearest_sq_distance(gt, partial) <= radius * radius


def region_means(gt_to_output: Tensor, observed: Tensor) -> tuple[float, float, float]:
    """(observed mean, unobserved mean, observed fraction) of per-ground-truth-point distances, pooled."""
    d, seen = gt_to_output.flatten(), observed.flatten()
    mean = lambda x: float(x.mean()) if x.numel() else float("nan")  # noqa: E731
    return mean(d[seen]), mean(d[~seen]), float(seen.float().mean())


def completeness_by_region(gt: np.ndarray | Tensor, output: np.ndarray | Tensor, partial: np.ndarray | Tensor,
                           radius: float = OBSERVED_RADIUS) -> tuple[float, float, float]:
    """CD(G,D) split by region: (observed, unobserved, observed fraction), unscaled.

    A ground-truth point is observed when an input point lies within `radius` of it; each region's
    value is the mean squared distance from its ground-truth points (pooled over the batch) to the output.
    """
    return region_means(nearest_sq_distance(gt, output), observed_mask(gt, partial, radius))
