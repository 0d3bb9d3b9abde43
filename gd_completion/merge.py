"""Measured merge: a vehicle's completion thinned together with its measured points and their mirror image.

The network's N_o points cover the whole vehicle, but only its N_c control points are copies of measured
points; a densely seen side is better described by the measurements themselves. The merge takes the
union of the measured points fed to the network (at most its input size), their mirror image about the
box's longitudinal plane (y -> -y) and the completion, and keeps N_o of them by farthest point sampling
(deterministic, starting at a measured point): measured points replace network points where they lie
densely, the network fills what is unseen, and the spacing stays even. The box-only analogue (mirror and
a template instead of the network) is the "mirror + template" prior of the evaluation. A track's fused partial
(track fusion) holds far more measured points than the network's input: it is merged with one of its points per
`FUSED_POOL_VOXEL` voxel instead (`merge_with_pool`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gd_completion.kernels import fps_pruned
from gd_completion.sampling import resample_indices, voxel_first_indices

# A track's fused partial is merged with one of its points per voxel of this size (normalised: 2 % of the length),
# not with the network's input: measured on PandaSet-002 (docs/MODEL.md, "Track fusion: what more frames can give").
FUSED_POOL_VOXEL = 0.02


@dataclass(frozen=True)
class Merged:
    """A merged completion: its points and, per point, the row of the measured points it copies (-1: a
    network point or a mirrored one)."""

    points: np.ndarray        # (n, 3) float32, normalised box frame
    measured_row: np.ndarray  # (n,) int64

    @property
    def is_measured(self) -> np.ndarray:
        """Bool (n,): the points that are measured points."""
        return self.measured_row >= 0


def mirrored(points: np.ndarray) -> np.ndarray:
    """Points of the normalised box frame mirrored about its longitudinal vertical plane (y -> -y)."""
    return np.asarray(points, np.float32) * np.array([1.0, -1.0, 1.0], np.float32)


def merge_measured(completion: np.ndarray, measured: np.ndarray, n: int | None = None) -> Merged:
    """Farthest point sampling of the union of `measured` (M, 3), its mirror image and `completion` (N_o, 3),
    all finite and in the normalised box frame, to `n` points (default N_o). Pass the measured points the
    network saw (`merge_with_fed`) to bound the cost: about 0.8 ms for 512 measured and 2,048 completion
    points on one core. When the union holds fewer than `n` distinct points, all of them are kept and the
    completion's (else the mirror's) repeated."""
    completion = np.asarray(completion, np.float32).reshape(-1, 3)
    measured = np.asarray(measured, np.float32).reshape(-1, 3)
    n = len(completion) if n is None else int(n)
    union = np.ascontiguousarray(np.concatenate([measured, mirrored(measured), completion]))
    if not 0 < n <= len(union):
        raise ValueError(f"cannot keep {n} of {len(union)} points")
    if not np.isfinite(union).all():
        raise ValueError("merge_measured: non-finite points")
    keep = fps_pruned(union, n)
    if n > 1 and (keep[1:] == 0).any():
        # FPS took every distinct point and went back to point 0: exact repeats in the union (a sparse
        # input's cycled control points). All distinct points, then the completion's repeated cyclically.
        distinct = np.sort(np.unique(union, axis=0, return_index=True)[1])
        for first in (2 * len(measured), len(measured), 0):   # the completion, else the mirror, else all
            pool = distinct[distinct >= first]
            if len(pool):
                break
        keep = np.concatenate([distinct, pool[np.arange(n - len(distinct)) % len(pool)]])
    return Merged(union[keep], np.where(keep < len(measured), keep, -1))


def merge_with_pool(completion: np.ndarray, partial: np.ndarray, voxel: float = FUSED_POOL_VOXEL) -> Merged:
    """`merge_measured` with one point per `voxel` voxel of a track's fused `partial` (normalised; the first in its
    order, which lists the oldest frame first, so the pool changes little from frame to frame) instead of the
    points the network saw: a fused partial holds many more measured points than the network's input size.
    `Merged.measured_row` indexes `partial`."""
    partial = np.asarray(partial, np.float32).reshape(-1, 3)
    return _merge_rows(completion, partial, voxel_first_indices(partial, voxel))


def _merge_rows(completion: np.ndarray, partial: np.ndarray, rows: np.ndarray) -> Merged:
    """`merge_measured` with `partial[rows]`; `Merged.measured_row` indexes `partial`."""
    merged = merge_measured(completion, partial[rows])
    return Merged(merged.points, np.where(merged.is_measured, rows[np.maximum(merged.measured_row, 0)], -1))


def merge_with_fed(completion: np.ndarray, partial: np.ndarray, num_input: int, rows: np.ndarray | None = None
                   ) -> Merged:
    """`merge_measured` with the measured points the network was fed: the rows of `partial` that
    `preprocess.network_input(partial, num_input)` takes (`rows`, its `resample_indices`, computed when None;
    all rows of a smaller partial, without its cyclic repeats). `Merged.measured_row` indexes `partial`."""
    partial = np.asarray(partial, np.float32).reshape(-1, 3)
    if rows is None:
        rows = resample_indices(len(partial), partial, num_input)
    return _merge_rows(completion, partial, np.asarray(rows)[:min(len(partial), num_input)])
