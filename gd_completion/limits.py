"""Per-frame work limits: what one cloud and its boxes may cost, whatever a detector sends.

Boxes are screened before any point is touched: implausible vehicle sizes (a box in millimetres, a
10 km box), duplicates of a box already kept, and boxes beyond `max_boxes` are skipped and counted.
The kept boxes are completed nearest first, so when the frame's time budget or output-point limit
runs out, the vehicles that matter most to a planner are the ones done.
"""
from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from gd_completion.geometry import Box3D, boxes_to_array


def check_positive_fields(settings: Any, skip: Collection[str] = ()) -> None:
    """ValueError naming the field unless every dataclass field of `settings` (but those in `skip`) is
    positive and finite, and every field annotated `int` an integer (not a bool)."""
    name = type(settings).__name__
    for f in fields(settings):
        if f.name in skip:
            continue
        value = getattr(settings, f.name)
        if f.type == "int" and (isinstance(value, bool) or int(value) != value):
            raise ValueError(f"{name}.{f.name}={value!r} must be an integer")
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name}.{f.name}={value!r} must be positive and finite")


@dataclass(frozen=True)
class FrameLimits:
    """Limits of one frame's work (defaults: generous for real traffic, tight for hostile input)."""

    max_boxes: int = 256                 # boxes completed per frame at most (nearest first)
    max_box_length: float = 30.0         # metres; longer boxes are not vehicles (articulated trucks are ~25 m)
    max_box_width: float = 5.0           # metres
    max_box_height: float = 6.0          # metres
    min_box_length: float = 0.5          # metres; shorter boxes are not vehicles either
    duplicate_distance: float = 0.3      # metres: a box whose centre is this close to a kept box is a duplicate
    max_points_per_vehicle: int = 200_000  # more points in one box: skipped (no vehicle returns that many)
    max_output_points: int = 2_000_000   # points published per frame at most (whole vehicles, nearest first)
    time_budget_s: float = 2.0           # seconds of completion per frame; vehicles not started by then are skipped
                                         # (math.inf: none, as offline, where output must not depend on load)

    def __post_init__(self) -> None:
        values = asdict(self)
        if values["time_budget_s"] == math.inf:
            values.pop("time_budget_s")
        bad = [k for k, v in values.items() if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0)]
        if bad:
            raise ValueError(f"frame limits must be positive and finite: {', '.join(bad)}")
        if self.min_box_length >= self.max_box_length:
            raise ValueError("min_box_length must be below max_box_length")


# The offline tools' limits: no time budget, so what they write never depends on the machine's load.
OFFLINE_LIMITS = FrameLimits(time_budget_s=math.inf)


def implausible(box: Box3D, limits: FrameLimits) -> bool:
    """True when the box cannot be a vehicle (size outside the limits)."""
    length, width, height = box.size
    return not (limits.min_box_length <= length <= limits.max_box_length
                and width <= limits.max_box_width and height <= limits.max_box_height)


def screen_boxes(boxes: Sequence[Box3D], limits: FrameLimits) -> tuple[list[int], list[tuple[int, str]]]:
    """(indices of the boxes to complete, nearest to the origin first; (index, reason) of each box skipped).

    Reasons: `implausible_box`; `duplicate_box` (centre within `duplicate_distance` of a nearer box
    already kept); `too_many_boxes` (after `max_boxes` were kept). Cost: O(boxes * max_boxes).
    """
    plausible = [i for i, b in enumerate(boxes) if not implausible(b, limits)]
    skipped = [(i, "implausible_box") for i in sorted(set(range(len(boxes))) - set(plausible))]
    if not plausible:
        return [], skipped
    centres = boxes_to_array([boxes[i] for i in plausible])[:, :3]
    order = np.argsort(np.hypot(centres[:, 0], centres[:, 1]), kind="stable")
    kept_centres = np.empty((limits.max_boxes, 3))
    kept: list[int] = []
    for rank, j in enumerate(order):
        if len(kept) == limits.max_boxes:
            skipped += [(plausible[k], "too_many_boxes") for k in order[rank:]]
            break
        near = ((kept_centres[:len(kept)] - centres[j]) ** 2).sum(-1) < limits.duplicate_distance ** 2
        if near.any():
            skipped.append((plausible[j], "duplicate_box"))
        else:
            kept_centres[len(kept)] = centres[j]
            kept.append(plausible[j])
    return kept, skipped
