"""Dataset readers (KITTI, PandaSet) yielding lidar frames with boxes in the lidar frame."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gd_completion.geometry import Box3D

# Dataset class names -> the completion pipeline's vehicle labels; anything else is lower-cased.
VEHICLE_LABELS = {
    "car": "car", "van": "van", "truck": "truck",
    "pickup truck": "car", "medium-sized truck": "truck", "semi-truck": "truck",
}


def normalise_label(name: str) -> str:
    """Pipeline label of a dataset class ('Car' -> 'car', 'Pickup Truck' -> 'car', 'Semi-truck' -> 'truck')."""
    key = name.strip().lower()
    return VEHICLE_LABELS.get(key, key.replace(" ", "_"))


@dataclass
class DatasetFrame:
    """One lidar frame: points (N, 3) float32 in `frame_id`, per-point columns, boxes in the same frame."""

    name: str
    stamp_ns: int
    frame_id: str
    xyz: np.ndarray
    intensity: np.ndarray
    boxes: list[Box3D]
    source_labels: list[str]
    track_ids: list[str]
    calib: Any = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    labelled: bool = True  # False: the frame had no label file, so its boxes are unknown (converted without any)
