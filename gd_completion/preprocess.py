"""The preprocessing contract: a vehicle's points in a cloud -> the network's input, and its parameters.

Crop the points inside the box grown by `crop_margin`, normalise them into the box frame (centre on the box, rotate
by -yaw, divide by the length), drop the ground (the lowest `ground_clearance` metres of the box), skip vehicles with
fewer than `min_points` points left, resample to the network's input size (FPS down, cyclic repetition up). The
dropped band's points inside the box's own footprint (tyres, wheel arches, the road under the body) are kept aside:
the measured merge publishes them, the network never sees them. The node, the offline tools, training-data
generation and evaluation all call these functions; the `Preprocessing` a model was trained with is stored in its
checkpoint.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from gd_completion.geometry import Box3D, crop_boxes, normalize
from gd_completion.sampling import resample_indices


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


def with_band(partial: np.ndarray, band: np.ndarray | None) -> np.ndarray:
    """(M + K, 3) float32: a vehicle's measured points, those above the ground cut first, then its ground band's
    (`CroppedVehicle.band`; None or empty: `partial` alone)."""
    partial = np.asarray(partial, np.float32).reshape(-1, 3)
    if band is None or not len(band):
        return partial
    return np.concatenate([partial, np.asarray(band, np.float32).reshape(-1, 3)])


def crop_vehicles(points: np.ndarray, boxes: Sequence[Box3D], prep: Preprocessing
                  ) -> tuple[list[CroppedVehicle], list[Box3D]]:
    """(vehicles with at least `min_points` points above the ground, boxes skipped for too few points); each
    vehicle also keeps its ground band's points in the footprint (`CroppedVehicle.band`).

    `points` (N, 3) finite, `boxes` valid (see `geometry.box_problem`); both in the same frame.
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    vehicles: list[CroppedVehicle] = []
    too_few: list[Box3D] = []
    for box, idx in zip(boxes, crop_boxes(points, boxes, prep.crop_margin)):
        measured = points[idx]
        normalized = normalize(measured, box).astype(np.float32, copy=False)
        keep = above_ground(normalized, box, prep.ground_clearance)
        if int(keep.sum()) < prep.min_points:
            too_few.append(box)
        else:
            band = normalized[footprint_band(normalized, box, prep.ground_clearance)]
            vehicles.append(CroppedVehicle(box, measured[keep], normalized[keep], band=band))
    return vehicles, too_few


def network_input(normalized: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) float32: a vehicle's normalised points brought to the network's input size."""
    normalized = np.asarray(normalized, dtype=np.float32).reshape(-1, 3)
    return normalized[resample_indices(len(normalized), normalized, n)]
