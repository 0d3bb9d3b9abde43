"""visualization_msgs/MarkerArray and vision_msgs/Detection3DArray -> Box3D, duck-typed on the messages."""
from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from gd_completion.class_maps import map_label
from gd_completion.geometry import Box3D
from gd_completion.rotations import yaw_from_quaternion
from gd_completion.stamp_sync import stamp_to_ns

# visualization_msgs/msg/Marker constants (kept here so the pure logic needs no message import).
MARKER_CUBE = 1
MARKER_ADD = 0  # MODIFY has the same value


@dataclass(frozen=True)
class BoxSet:
    """The boxes of one boxes message: its stamp and, per box, the frame its pose is given in."""

    stamp_ns: int | None  # None when the message carries no header (an empty MarkerArray)
    boxes: tuple[Box3D, ...]
    frame_ids: tuple[str, ...]
    decode_s: float = 0.0  # seconds its conversion from the message took (counted in the frame's processing time)
    unsupported_shapes: int = 0  # objects not converted because their shape is no box (Autoware CYLINDER, POLYGON)

    def split_by_frame(self, frame_id: str) -> tuple[list[Box3D], int]:
        """Boxes given in `frame_id`, and how many were in another frame (no tf here: those are skipped)."""
        kept = [b for b, f in zip(self.boxes, self.frame_ids) if f == frame_id]
        return kept, len(self.boxes) - len(kept)


def _box(pose: Any, size: Any, label: str, instance_id: int) -> Box3D:
    p, q = pose.position, pose.orientation
    return Box3D(center=(p.x, p.y, p.z), size=(size.x, size.y, size.z),
                 yaw=yaw_from_quaternion(q.x, q.y, q.z, q.w), label=label, instance_id=instance_id)


def box_count(msg: Any) -> int:
    """Boxes (markers, detections or Autoware objects) in a boxes message, read before converting it."""
    if hasattr(msg, "markers"):
        return len(msg.markers)
    return len(msg.objects) if hasattr(msg, "objects") else len(msg.detections)


def markers_to_boxes(msg: Any, class_map: Mapping[str, str] | None = None) -> BoxSet:
    """CUBE markers (pose = centre and heading, scale = length/width/height, `text` or else `ns` = class,
    `id` = instance) -> BoxSet. Other marker types and DELETE/DELETEALL are ignored, but any marker's
    header gives the stamp (so a lone DELETEALL marks a frame without vehicles)."""
    class_map = class_map or {}
    markers: Sequence[Any] = msg.markers
    stamp = stamp_to_ns(markers[0].header.stamp) if len(markers) else None
    boxes, frames = [], []
    for m in markers:
        if int(m.type) != MARKER_CUBE or int(m.action) != MARKER_ADD:
            continue
        boxes.append(_box(m.pose, m.scale, map_label(m.text or m.ns, class_map), int(m.id)))
        frames.append(str(m.header.frame_id))
    return BoxSet(stamp, tuple(boxes), tuple(frames))


def _best_class(results: Sequence[Any]) -> str:
    """class_id of the best-scoring hypothesis ("" when there is none; NaN scores rank last)."""
    def score(r: Any) -> float:
        value = float(r.hypothesis.score)
        return value if not math.isnan(value) else -math.inf
    return str(max(results, key=score).hypothesis.class_id) if len(results) else ""


INT32_MAX = 2**31 - 1


def _instance_id(raw: str, index: int) -> int:
    """int32 instance id of a detection: its `id` when that is an integer in int32 range; otherwise (a
    tracker's UUID, an id beyond int32) a stable 31-bit hash of the text, the same in every frame; the
    detection's index in the array when the id is empty."""
    text = str(raw).strip()
    if not text:
        return index
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is not None and -INT32_MAX - 1 <= value <= INT32_MAX:
        return value
    return zlib.crc32(text.encode()) & INT32_MAX


def detections_to_boxes(msg: Any, class_map: Mapping[str, str] | None = None) -> BoxSet:
    """Detection3DArray -> BoxSet: bbox centre/size (x = length), class of the best-scoring hypothesis,
    `id` as int32 instance id (`_instance_id`: stable for non-integer or out-of-range ids). A detection whose own header
    names a frame uses it; otherwise the array's frame."""
    class_map = class_map or {}
    array_frame = str(msg.header.frame_id)
    boxes, frames = [], []
    for i, det in enumerate(msg.detections):
        label = map_label(_best_class(det.results), class_map)
        boxes.append(_box(det.bbox.center, det.bbox.size, label, _instance_id(det.id, i)))
        own = getattr(getattr(det, "header", None), "frame_id", "")
        frames.append(str(own) or array_frame)
    return BoxSet(stamp_to_ns(msg.header.stamp), tuple(boxes), tuple(frames))
