"""One cloud completed without a bag: boxes from text, JSON or KITTI labels, and `complete_cloud` (cached model)."""
from __future__ import annotations

import json
import math
import threading
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion.datasets.kitti import labels_to_boxes, read_calib, read_labels
from gd_completion.errors import BoxError, DataFormatError
from gd_completion.geometry import Box3D, box_problem, crop_boxes, finite_mask
from gd_completion.settings import CompletionSettings

BOX_FORMAT = "cx,cy,cz,length,width,height,yaw[,label]"
VEHICLES = ("car", "van", "truck")  # the labels completed (pipeline.LABEL_IDS; not imported: it imports torch)

_completers: dict[str, Any] = {}
_completers_lock = threading.Lock()


@dataclass
class CloudCompletion:
    """A completed cloud (`pipeline.COMPLETION_DTYPE` rows), the boxes skipped with a reason, the frame's stats."""

    points: np.ndarray
    skipped: list[tuple[Box3D, str]] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)  # skip reason -> vehicles (the node's skipped_<reason>)
    completed: int = 0


def parse_box(text: str, instance_id: int) -> Box3D:
    """`cx,cy,cz,length,width,height,yaw[,label]` (metres, radians; label default car) -> Box3D."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (7, 8):
        raise BoxError(f"--box {text!r}: expected {BOX_FORMAT} (7 numbers and an optional label), "
                       f"got {len(parts)} values")
    try:
        values = [float(p) for p in parts[:7]]
    except ValueError as error:
        raise BoxError(f"--box {text!r}: expected {BOX_FORMAT}: {error}") from None
    label = parts[7].lower() if len(parts) == 8 and parts[7] else "car"
    return _checked(Box3D(tuple(values[:3]), tuple(values[3:6]), values[6], label, instance_id), f"--box {text!r}")


def as_box(item: Box3D | Sequence[Any], instance_id: int) -> Box3D:
    """A Box3D as it is, or a (cx, cy, cz, l, w, h, yaw[, label]) sequence as a Box3D with `instance_id`."""
    if isinstance(item, Box3D):
        return item
    if isinstance(item, str) or len(item) not in (7, 8):
        raise BoxError(f"box {item!r}: expected a Box3D or ({BOX_FORMAT.replace(',', ', ')})")
    label = str(item[7]).lower() if len(item) == 8 else "car"
    try:
        return Box3D(tuple(item[:3]), tuple(item[3:6]), float(item[6]), label, instance_id)
    except (TypeError, ValueError) as error:
        raise BoxError(f"box {item!r}: {error}") from None


def read_boxes_json(path: str | Path) -> list[Box3D]:
    """A JSON list of boxes: {"center": [x, y, z], "size": [length, width, height], "yaw": rad (default 0),
    "label": "car"|"van"|"truck" (default car), "id": int (default the 1-based position)}, in the cloud's frame."""
    path = Path(path)
    try:
        items = json.loads(path.read_text())
    except OSError as error:
        raise DataFormatError(f"{path}: cannot read boxes file ({error.strerror})") from None
    except ValueError as error:
        raise DataFormatError(f"{path}: not JSON ({error})") from None
    if not isinstance(items, list):
        raise DataFormatError(f"{path}: expected a JSON list of boxes, got {type(items).__name__}")
    boxes = []
    for k, item in enumerate(items):
        where = f"{path}: box {k}"
        if not isinstance(item, dict) or "center" not in item or "size" not in item:
            raise DataFormatError(f"{where}: expected an object with center and size (yaw, label, id optional)")
        try:
            box = Box3D(item["center"], item["size"], float(item.get("yaw", 0.0)),
                        str(item.get("label", "car")).lower(), int(item.get("id", k + 1)))
        except (BoxError, TypeError, ValueError) as error:
            raise DataFormatError(f"{where}: {error}") from None
        boxes.append(_checked(box, where))
    return boxes


def kitti_boxes(label_path: str | Path, calib_path: str | Path) -> list[Box3D]:
    """The Car/Van/Truck rows of a KITTI object label_2 file as lidar-frame boxes (`datasets.kitti` readers);
    instance id = the row's 1-based position among the file's non-DontCare rows (`labels_to_boxes`)."""
    boxes, _ = labels_to_boxes(read_labels(label_path), read_calib(calib_path))
    return [box for box in boxes if box.label in VEHICLES]


def _checked(box: Box3D, where: str) -> Box3D:
    problem = box_problem(box)
    if problem is not None:
        raise BoxError(f"{where}: unusable box: {problem}")
    return box


def cloud_xyz(points: np.ndarray) -> np.ndarray:
    """(N, 3) float32 of an (N, 3+) array or a structured array with x, y, z."""
    points = np.asarray(points)
    if points.dtype.names is not None:
        if not {"x", "y", "z"} <= set(points.dtype.names):
            raise DataFormatError(f"points: structured array without x, y, z (fields {points.dtype.names})")
        return np.stack([points["x"], points["y"], points["z"]], axis=1).astype(np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise DataFormatError(f"points: expected an (N, 3) array, got shape {points.shape}")
    return np.ascontiguousarray(points[:, :3], dtype=np.float32)


def points_in_boxes(points: np.ndarray, boxes: Sequence[Box3D]) -> list[int]:
    """Finite points inside each box (no margin, ground included): 0 means the box misses the cloud."""
    points = cloud_xyz(points)
    return [len(idx) for idx in crop_boxes(points[finite_mask(points)], boxes, 0.0)] if boxes else []


def completer(settings: CompletionSettings) -> Any:
    """The `VehicleCompleter` of `settings`, made once per process (later calls with equal settings reuse it)."""
    key = repr(replace(settings, model_path=str(Path(settings.model_path).resolve()) if settings.model_path else ""))
    with _completers_lock:
        if key not in _completers:
            from gd_completion.pipeline import VehicleCompleter
            _completers[key] = VehicleCompleter.from_settings(settings)
        return _completers[key]


def cloud_settings(model: str | Path | None = None, *, device: str = "cpu", threads: int = 0,
                   min_points: int | None = None, include_input_points: bool = True) -> CompletionSettings:
    """The offline settings (no time budget: every box completed) of `complete_cloud`'s keyword arguments."""
    return CompletionSettings.offline(model_path=str(model or ""), device=device, num_threads=int(threads),
                                      min_points=int(min_points or 0), include_input_points=include_input_points)


# What the pipeline's skip reasons mean, for messages (gd_completion.limits.FrameLimits).
SKIP_REASONS = {
    "implausible_box": "implausible size for a vehicle",
    "duplicate_box": "duplicate of a nearer box",
    "too_many_boxes": "beyond the boxes completed per frame",
    "too_many_points": "more points in the box than any vehicle returns",
    "output_limit": "output point limit reached",
    "time_budget": "time budget spent",
}


def complete_cloud_report(points: np.ndarray, boxes: Sequence[Box3D | Sequence[Any]],
                          settings: CompletionSettings | None = None, **options: Any) -> CloudCompletion:
    """`complete_cloud`, with the boxes skipped and why; `settings` (default: `cloud_settings(**options)`)."""
    from gd_completion.pipeline import completion_to_structured

    xyz = cloud_xyz(points)
    parsed = [as_box(item, k + 1) for k, item in enumerate(boxes)]
    ids = [box.instance_id for box in parsed]
    if len(set(ids)) != len(ids):
        raise BoxError(f"boxes: instance ids are not unique ({sorted(i for i in set(ids) if ids.count(i) > 1)})")
    engine = completer(settings or cloud_settings(**options))
    result = engine.complete_frame(xyz, parsed)
    table = completion_to_structured(result)
    finite = xyz[finite_mask(xyz)]
    skipped = [(box, f"label {box.label!r} is not completed (only {', '.join(VEHICLES)})")
               for box in parsed if box.label not in engine.labels]
    for box, reason in result.stats.skipped_boxes:
        if reason == "degenerate_box":
            text = f"unusable box: {box_problem(box)}"
        elif reason == "too_few_points":
            count = len(crop_boxes(finite, [box], engine.preprocessing.crop_margin)[0])
            text = (f"too few points: {count} in the box, {engine.preprocessing.min_points} needed above the "
                    "ground (--min-points)")
        else:
            text = SKIP_REASONS.get(reason, reason)
        skipped.append((box, text))
    return CloudCompletion(table, skipped, Counter(result.stats.skipped), int(result.stats.completed))


def complete_cloud(points: np.ndarray, boxes: Sequence[Box3D | Sequence[Any]],
                   settings: CompletionSettings | None = None, *, model: str | Path | None = None,
                   device: str = "cpu", threads: int = 0, min_points: int | None = None,
                   include_input_points: bool = True) -> np.ndarray:
    """Complete the vehicles of one cloud: a structured array (`pipeline.COMPLETION_DTYPE`: x, y, z float32,
    instance_id int32, label uint8 1 car 2 van 3 truck, generated uint8) in the frame of `points`.

    `points`: (N, 3+) array (or structured with x, y, z); `boxes`: Box3D, or (cx, cy, cz, length, width, height,
    yaw[, label]) tuples (instance id = 1-based position). `model`: checkpoint (None: the shipped weights), loaded
    once per process and options; `threads`: vehicles completed in parallel (0: one per core); `min_points`:
    the checkpoint's when None. `settings` (`settings.CompletionSettings`), when given, replaces those keyword
    arguments. Boxes with too few points are left out (see `complete_cloud_report`).
    """
    return complete_cloud_report(points, boxes, settings or cloud_settings(
        model, device=device, threads=threads, min_points=min_points, include_input_points=include_input_points)
    ).points


def describe(box: Box3D) -> str:
    """'box 3 (car at 12.1, -3.0, -0.8)' for messages."""
    x, y, z = (0.0 if math.isnan(v) else v for v in box.center)
    return f"box {box.instance_id} ({box.label} at {x:.1f}, {y:.1f}, {z:.1f})"
