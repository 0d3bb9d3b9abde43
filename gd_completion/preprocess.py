"""The preprocessing contract: a vehicle's points in a cloud -> the network's input, and its parameters.

Crop the points inside the box grown by `crop_margin`, normalise them into the box frame (centre on the box, rotate
by -yaw, divide by the length), drop the ground (the lowest `ground_clearance` metres of the box), skip vehicles with
fewer than `min_points` points left, resample to the network's input size (FPS down, cyclic repetition up). The
dropped band's points inside the box's own footprint (tyres, wheel arches, the road under the body) are kept aside,
and so are the points above the ground within a wider `pool_margin` of the box but outside the crop (the ends of a
vehicle a detector's box cuts off): the measured merge publishes them, the network never sees them. The node, the
offline tools, training-data generation and evaluation all call these functions; the `Preprocessing` a model was
trained with is stored in its checkpoint.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from gd_completion.geometry import Box3D, crop_boxes, normalize
from gd_completion.sampling import resample_indices

# Metres around the box within which measured points above the ground are pooled by the measured merge (published with
# the completion) though not fed to the network, when wider than the crop margin: a detector's box error (centre
# sigma 0.15 m in the evaluation's box-noise run) cuts a vehicle's ends off its crop. Chosen on PandaSet-002's reduced
# protocol (docs/MODEL.md, "The pool margin").
POOL_MARGIN = 0.4


@dataclass(frozen=True)
class Preprocessing:
    """Parameters of the contract (defaults: the values every model so far was trained with)."""

    crop_margin: float = 0.1       # metres added to each side of the box when cropping
    ground_clearance: float = 0.1  # points this close to the box floor (metres) are ground, dropped
    min_points: int = 20           # vehicles with fewer points left are skipped (and never trained on)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.crop_margin) and 0.0 <= self.crop_margin <= 5.0):
            raise ValueError(f"crop_margin={self.crop_margin} must be in [0, 5] metres")
        if not (math.isfinite(self.ground_clearance) and 0.0 <= self.ground_clearance <= 2.0):
            raise ValueError(f"ground_clearance={self.ground_clearance} must be in [0, 2] metres")
        if int(self.min_points) != self.min_points or self.min_points < 1:
            raise ValueError(f"min_points={self.min_points} must be an integer >= 1")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for checkpoints and dataset metadata."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> Preprocessing:
        """Inverse of `to_dict`; None (a checkpoint from before the contract) gives the defaults.
        Raises ValueError on unknown keys or invalid values."""
        if data is None:
            return cls()
        if not isinstance(data, dict):
            raise ValueError(f"preprocessing must be a dict, got {type(data).__name__}")
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"unknown preprocessing keys: {unknown}")
        return cls(**data)


@dataclass(frozen=True)
class CroppedVehicle:
    """One vehicle of a cloud: its box, its measured points above the ground, the same in the box frame."""

    box: Box3D
    measured: np.ndarray    # (M, 3) float32, cloud frame
    normalized: np.ndarray  # (M, 3) float32, box frame divided by the length
    # track fusion: `normalized` is the track's fused partial; its last len(current_source) rows are this frame's
    # points `measured[current_source]` (as the track stored them: voxel-thinned, aligned, in its mean placement)
    current_source: np.ndarray | None = None
    # this frame's points of the ground band inside the box's footprint (`footprint_band`), normalised (K, 3): not
    # fed to the network, pooled by the measured merge (tyres, wheel arches, the road under the body)
    band: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    # this frame's points above the ground cut within the pool margin of the box but outside the crop margin,
    # normalised (S, 3): not fed to the network, pooled by the measured merge (the ends a loose box cuts off)
    surround: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))

    @property
    def aside(self) -> np.ndarray:
        """(K + S, 3) float32: the measured points kept aside for the merge, not fed to the network: the ground band,
        then the surround."""
        return with_aside(self.band, self.surround)

    @property
    def current_rows(self) -> int | None:
        """Track fusion: how many of the last rows of `normalized` are this frame's points (None: no fusion)."""
        return None if self.current_source is None else len(self.current_source)


def above_ground(normalized: np.ndarray, box: Box3D, ground_clearance: float) -> np.ndarray:
    """Bool (M,): normalised points higher than `ground_clearance` metres above the box floor."""
    return normalized[:, 2] * box.size[0] >= -box.size[2] / 2 + ground_clearance


def footprint_band(normalized: np.ndarray, box: Box3D, ground_clearance: float) -> np.ndarray:
    """Bool (M,): normalised points of the ground band (not `above_ground`, not below the box floor) inside the box's
    own footprint (the crop margin left out)."""
    length, width, _ = box.size
    return (above_ground(normalized, box, 0.0) & ~above_ground(normalized, box, ground_clearance)
            & (np.abs(normalized[:, 0]) <= 0.5) & (np.abs(normalized[:, 1]) * length <= width / 2))


def with_aside(partial: np.ndarray, aside: np.ndarray | None) -> np.ndarray:
    """(M + K, 3) float32: a vehicle's measured points, those fed to the network first, then those kept aside for the
    merge (`CroppedVehicle.aside`; None or empty: `partial` alone)."""
    partial = np.asarray(partial, np.float32).reshape(-1, 3)
    if aside is None or not len(aside):
        return partial
    return np.concatenate([partial, np.asarray(aside, np.float32).reshape(-1, 3)])


def crop_vehicles(points: np.ndarray, boxes: Sequence[Box3D], prep: Preprocessing, pool_margin: float = 0.0
                  ) -> tuple[list[CroppedVehicle], list[Box3D]]:
    """(vehicles with at least `min_points` points above the ground, boxes skipped for too few points); each
    vehicle also keeps its ground band's points in the footprint (`CroppedVehicle.band`) and, when `pool_margin`
    (metres) is wider than `prep.crop_margin`, the points above the ground in the box grown by `pool_margin` that no
    box's crop holds (`CroppedVehicle.surround`; a point near several boxes goes to the nearest: `crop_and_surround`).

    `points` (N, 3) finite, `boxes` valid (see `geometry.box_problem`); both in the same frame.
    """
    pool_margin = check_pool_margin(pool_margin)
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    vehicles: list[CroppedVehicle] = []
    too_few: list[Box3D] = []
    pools: Sequence[np.ndarray | None]
    if pool_margin > prep.crop_margin:
        crops, pools = crop_and_surround(points, boxes, prep.crop_margin, pool_margin)
    else:
        crops = crop_boxes(points, boxes, prep.crop_margin)
        pools = [None] * len(crops)
    for box, idx, pool in zip(boxes, crops, pools):
        measured = points[idx]
        normalized = normalize(measured, box).astype(np.float32, copy=False)
        keep = above_ground(normalized, box, prep.ground_clearance)
        if int(keep.sum()) < prep.min_points:
            too_few.append(box)
            continue
        band = normalized[footprint_band(normalized, box, prep.ground_clearance)]
        surround = np.zeros((0, 3), np.float32)
        if pool is not None:
            around = normalize(points[pool], box)
            surround = around[above_ground(around, box, prep.ground_clearance)]
        vehicles.append(CroppedVehicle(box, measured[keep], normalized[keep], band=band, surround=surround))
    return vehicles, too_few


def check_pool_margin(pool_margin: float) -> float:
    """`pool_margin` as a float; ValueError unless it is a finite margin in [0, 5] metres."""
    if not (math.isfinite(pool_margin) and 0.0 <= pool_margin <= 5.0):
        raise ValueError(f"pool_margin={pool_margin} must be in [0, 5] metres")
    return float(pool_margin)


def crop_and_surround(points: np.ndarray, boxes: Sequence[Box3D], crop_margin: float, pool_margin: float
                      ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per box, the indices of `points` in its crop (`geometry.crop_boxes` with `crop_margin`) and of its surround:
    the points within `pool_margin` (wider) metres of it that no box's crop holds, each given to the one box it lies
    nearest to (metres outside the box; the first box on a tie), so a neighbour's points are never published as this
    vehicle's and no point is kept aside twice. The crops are those of `crop_boxes` on all points (it tests each
    point on its own), searched among the points near some box only."""
    pools = crop_boxes(points, boxes, pool_margin)
    if not pools:
        return [], []
    near = np.zeros(len(points), bool)
    for pool in pools:
        near[pool] = True
    rows = np.flatnonzero(near)
    crops = [rows[inside] for inside in crop_boxes(points[rows], boxes, crop_margin)]
    taken = np.zeros(len(points), bool)
    for crop in crops:
        taken[crop] = True
    candidates = [pool[~taken[pool]] for pool in pools]
    claims = np.zeros(len(points), np.intp)
    for candidate in candidates:
        claims[candidate] += 1
    if not (claims > 1).any():
        return crops, candidates
    # a point near several boxes: the box it lies nearest to keeps it (the first on a tie)
    shared = np.flatnonzero(claims > 1)
    gaps = np.full((len(boxes), len(shared)), np.inf)
    for k, (candidate, box) in enumerate(zip(candidates, boxes)):
        mine = np.isin(shared, candidate, assume_unique=True)
        if mine.any():
            gaps[k, mine] = _outside_distance(points[shared[mine]], box)
    owner = np.full(len(points), -1, np.intp)
    owner[shared] = np.argmin(gaps, axis=0)
    return crops, [c[(owner[c] < 0) | (owner[c] == k)] for k, c in enumerate(candidates)]


def _outside_distance(points: np.ndarray, box: Box3D) -> np.ndarray:
    """(M,) metres from each point to `box` (0 inside it)."""
    local = normalize(points, box).astype(np.float64) * box.size[0]
    return np.linalg.norm(np.maximum(np.abs(local) - np.asarray(box.size, np.float64) / 2, 0.0), axis=1)


def network_input(normalized: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) float32: a vehicle's normalised points brought to the network's input size."""
    normalized = np.asarray(normalized, dtype=np.float32).reshape(-1, 3)
    return normalized[resample_indices(len(normalized), normalized, n)]
