"""Measured merge: a vehicle's completion thinned together with its measured points and their mirror image.

The network's N_o points cover the whole vehicle, but only its N_c control points are copies of measured
points; a densely seen side is better described by the measurements themselves. The merge pools every measured
point of the vehicle (one per `POOL_VOXEL` voxel: a single frame's crop or a track's fused partial alike, and the
points the crop kept aside, which the network is not fed: the ground band in the box's footprint, tyres and wheel
arches, and the surround within the pool margin, the ends a loose box cuts off), adds
their mirror image about the box's longitudinal plane (y -> -y; moved across the box to where a clearly seen
side and the box's width place the vehicle, `mirror_plane_offset`, where the box is off by at least 2 % of the
length, as a detector's box often is) and the completion, and keeps N_o of the union by
a weighted farthest point sampling (`kernels.fps_pruned` with weights; deterministic, starting at a measured point):
a measured point is taken where nothing chosen lies within its distance, a mirrored point only
1/sqrt(MIRROR_WEIGHT) times and a network point 1/sqrt(NETWORK_WEIGHT) times farther out. Measured points therefore
replace network points wherever the vehicle was seen, at half the network points' spacing (four times their density
per area), so a densely seen vehicle keeps its measurements and fidelity does not worsen with density; the network
fills what is unseen and the spacing stays even within each kind. The box-only analogue (mirror and a template
instead of the network, unweighted, about the box's own plane) is the "mirror + template" prior of the evaluation.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gd_completion.kernels import fps_pruned
from gd_completion.preprocess import with_aside
from gd_completion.sampling import voxel_first_indices

# The measured points are pooled one per voxel of this size (normalised: 1 % of the length), bounding the merge's cost
# for dense vehicles and fused tracks; the weights are those of the squared distances in the weighted FPS. Chosen on
# PandaSet-002's reduced protocol (docs/MODEL.md, "Measured merge").
POOL_VOXEL = 0.01
MIRROR_WEIGHT = 0.5
NETWORK_WEIGHT = 0.25
# The mirror's plane (`mirror_plane_offset`): a box's plane is off by the box's error across the vehicle, so the
# plane is moved by a share of the offset that the seen side and the box's width give: PLANE_SHARE (1 by default;
# read at call time), only where that offset is at least PLANE_MIN_MOVE (smaller ones are within the estimate's own
# error, and are what a box tighter than PandaSet's annotations, such as the synthetic sets', gives).
# SIDE_GAP: where the seen side's 90th percentile lies against the box's side (normalised; the median over
# PandaSet-002's moving vehicles, which the evaluation does not score); the side is read in the middle of the
# vehicle (|x| < SIDE_SPAN) at body height (SIDE_BAND), needs SIDE_MIN_POINTS points and SIDE_RATIO times the
# other side's; the move is capped at PLANE_LIMIT. Measured on PandaSet-002 and the synthetic sets (docs/MODEL.md,
# "Model v3.2", the mirror's plane).
PLANE_SHARE = 1.0
PLANE_MIN_MOVE = 0.02
SIDE_GAP = -0.0154
SIDE_SPAN = 0.3
SIDE_BAND = (-0.3, 0.2)   # body height: from 0.3 below to 0.2 above the box's centre, in box heights
SIDE_MIN_POINTS = 20
SIDE_RATIO = 3.0
PLANE_LIMIT = 0.08


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


def mirrored(points: np.ndarray, offset: float = 0.0) -> np.ndarray:
    """Points of the normalised box frame mirrored about the vertical plane y = `offset` along the box (y -> 2 offset
    - y; the box's own longitudinal plane by default)."""
    out = np.asarray(points, np.float32) * np.array([1.0, -1.0, 1.0], np.float32)
    if offset:
        out[:, 1] += np.float32(2.0 * offset)
    return out


def check_plane_share(share: float) -> float:
    """`share` as a float; ValueError unless it is in [0, 1]."""
    share = float(share)
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"mirror plane share {share} must be in [0, 1]")
    return share


def mirror_plane_offset(partial: np.ndarray, size: Sequence[float] | None, share: float | None = None) -> float:
    """Where the vehicle's plane of symmetry lies across its box (y, normalised frame), times `share`: from the seen
    side (the 90th percentile of its points' distance from the box's plane, in the middle of the vehicle at body
    height) and the box's width (`size` = length, width, height), the side's gap `SIDE_GAP` removed. 0 when no side
    is seen clearly (fewer than `SIDE_MIN_POINTS` points, or less than `SIDE_RATIO` times the other side's), when the
    offset is under `PLANE_MIN_MOVE`, without a finite positive size, or with `share` 0 (None: `PLANE_SHARE`); at
    most `PLANE_LIMIT` x `share`."""
    share = PLANE_SHARE if share is None else share
    dims = np.asarray(size if size is not None else (), np.float64).ravel()
    if not share or len(dims) != 3 or not (np.isfinite(dims).all() and (dims > 0).all()):
        return 0.0
    length, width, height = dims
    p = np.asarray(partial, np.float32).reshape(-1, 3)
    low, high = SIDE_BAND[0] * height / length, SIDE_BAND[1] * height / length
    body = (np.abs(p[:, 0]) < SIDE_SPAN) & (p[:, 2] > low) & (p[:, 2] < high)
    y = p[body, 1]
    left, right = y[y > 0], -y[y < 0]
    sign, seen, other = (1.0, left, right) if len(left) >= len(right) else (-1.0, right, left)
    if len(seen) < SIDE_MIN_POINTS or len(seen) < SIDE_RATIO * max(len(other), 1):
        return 0.0
    offset = sign * (float(np.percentile(seen, 90)) - width / length / 2 - SIDE_GAP)
    if abs(offset) < PLANE_MIN_MOVE:
        return 0.0
    return float(np.clip(offset, -PLANE_LIMIT, PLANE_LIMIT)) * share


def check_weights(network_weight: float, mirror_weight: float) -> None:
    """ValueError unless both weights of the merge's FPS are in (0, 1] (the measured points weigh 1)."""
    if not (0.0 < network_weight <= 1.0 and 0.0 < mirror_weight <= 1.0):
        raise ValueError(f"merge weights must be in (0, 1]: network {network_weight}, mirror {mirror_weight}")


def merge_measured(completion: np.ndarray, measured: np.ndarray, n: int | None = None, *,
                   network_weight: float = NETWORK_WEIGHT, mirror_weight: float = MIRROR_WEIGHT,
                   mirror_offset: float = 0.0) -> Merged:
    """Weighted farthest point sampling (see the module; the measured points weigh 1) of the union of `measured`
    (M, 3), its mirror image about y = `mirror_offset` and `completion` (N_o, 3), all finite and in the normalised
    box frame, to `n` points
    (default N_o). Pass a pool of the measured points (`merge_with_pool`) to bound the cost: about 1 ms for 2,000
    measured and 2,048 completion points on one core. When the union holds fewer than `n` distinct points, all of
    them are kept and the completion's (else the mirror's) repeated."""
    completion = np.asarray(completion, np.float32).reshape(-1, 3)
    measured = np.asarray(measured, np.float32).reshape(-1, 3)
    n = len(completion) if n is None else int(n)
    union = np.ascontiguousarray(np.concatenate([measured, mirrored(measured, mirror_offset), completion]))
    if not 0 < n <= len(union):
        raise ValueError(f"cannot keep {n} of {len(union)} points")
    if not np.isfinite(union).all():
        raise ValueError("merge_measured: non-finite points")
    check_weights(network_weight, mirror_weight)
    weights = np.full(len(union), network_weight, np.float32)
    weights[:len(measured)] = 1.0
    weights[len(measured):2 * len(measured)] = mirror_weight
    keep = fps_pruned(union, n, weights=weights)
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


def merge_with_pool(completion: np.ndarray, partial: np.ndarray, voxel: float = POOL_VOXEL,
                    aside: np.ndarray | None = None, *, network_weight: float = NETWORK_WEIGHT,
                    mirror_weight: float = MIRROR_WEIGHT, size: Sequence[float] | None = None,
                    plane_share: float | None = None) -> Merged:
    """`merge_measured` with one point per `voxel` voxel of a vehicle's measured `partial` (normalised; the first in
    its order: a track's fused partial lists the oldest frame first, so the pool changes little from frame to
    frame) and of the points its crop kept aside, `aside` (`preprocess.CroppedVehicle.aside`: the ground band and the
    surround, which the network is not fed). With the box's `size`, the mirror's plane is moved by `plane_share`
    (None: `PLANE_SHARE`) of what the seen side gives (`mirror_plane_offset` of `partial`). `Merged.measured_row`
    indexes `partial` followed by `aside`."""
    measured = with_aside(partial, aside)
    rows = voxel_first_indices(measured, voxel)
    merged = merge_measured(completion, measured[rows], network_weight=network_weight, mirror_weight=mirror_weight,
                            mirror_offset=mirror_plane_offset(partial, size, plane_share))
    return Merged(merged.points, np.where(merged.is_measured, rows[np.maximum(merged.measured_row, 0)], -1))
