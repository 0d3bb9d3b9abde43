"""autoware_perception_msgs DetectedObjects / TrackedObjects -> BoxSet, duck-typed on the messages."""
from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from gd_completion.box_messages import INT32_MAX, BoxSet, _box
from gd_completion.class_maps import map_label
from gd_completion.stamp_sync import stamp_to_ns

# autoware_perception_msgs/msg/ObjectClassification label constants -> our class names (kept here so the pure
# logic needs no message import); a label not in the table reads as its number.
AUTOWARE_LABELS: dict[int, str] = {
    0: "unknown",
    1: "car",
    2: "truck",
    3: "bus",
    4: "trailer",
    5: "motorcycle",
    6: "bicycle",
    7: "pedestrian",
    8: "animal",
    9: "hazard",
    10: "over_drivable",
    11: "under_drivable",
}
# autoware_perception_msgs/msg/Shape type constants: only bounding boxes become boxes.
SHAPE_BOUNDING_BOX = 0
SHAPE_CYLINDER = 1
SHAPE_POLYGON = 2


def best_label(classification: Sequence[Any]) -> str:
    """AUTOWARE_LABELS name of the most probable classification ("" when there is none; NaN ranks last)."""
    if not len(classification):
        return ""

    def probability(c: Any) -> float:
        value = float(c.probability)
        return value if not math.isnan(value) else -math.inf

    label = int(max(classification, key=probability).label)
    return AUTOWARE_LABELS.get(label, str(label))


def uuid_instance_id(uuid: Any) -> int:
    """Stable 31-bit instance id of a unique_identifier_msgs/UUID (or its 16 bytes): crc32 of its lower-case hex
    text, so the same as box_messages gives a Detection3D whose `id` is that hex text (as Autoware writes UUIDs)."""
    value = getattr(uuid, "uuid", uuid)  # uint8[16]: a numpy array from rclpy and rosbags
    raw = bytes(value) if isinstance(value, bytes | bytearray) else np.asarray(value, dtype=np.uint8).tobytes()
    return zlib.crc32(raw.hex().encode()) & INT32_MAX


def _objects_to_boxes(msg: Any, class_map: Mapping[str, str], ids: Sequence[int]) -> BoxSet:
    """Bounding-box objects of `msg.objects` -> BoxSet (object i gets `ids[i]`); other shapes are only counted."""
    frame = str(msg.header.frame_id)
    boxes, unsupported = [], 0
    for obj, instance_id in zip(msg.objects, ids):
        if int(obj.shape.type) != SHAPE_BOUNDING_BOX:
            unsupported += 1
            continue
        label = map_label(best_label(obj.classification), class_map)
        boxes.append(_box(obj.kinematics.pose_with_covariance.pose, obj.shape.dimensions, label, instance_id))
    return BoxSet(stamp_to_ns(msg.header.stamp), tuple(boxes), (frame,) * len(boxes), unsupported_shapes=unsupported)


def detected_objects_to_boxes(msg: Any, class_map: Mapping[str, str] | None = None) -> BoxSet:
    """DetectedObjects -> BoxSet: pose of `kinematics.pose_with_covariance` (centre, yaw; an orientation of
    SIGN_UNKNOWN is taken as given, an all-zero one reads as yaw 0), `shape.dimensions` as length/width/height,
    the most probable class through AUTOWARE_LABELS then `class_map`, the array's frame and stamp. Detections carry
    no ids: instance id = index in the array. CYLINDER and POLYGON shapes are counted in `unsupported_shapes`."""
    return _objects_to_boxes(msg, class_map or {}, range(len(msg.objects)))


def tracked_objects_to_boxes(msg: Any, class_map: Mapping[str, str] | None = None) -> BoxSet:
    """TrackedObjects -> BoxSet as `detected_objects_to_boxes`, with instance id = `uuid_instance_id(object_id)`
    (the same for a track in every frame)."""
    return _objects_to_boxes(msg, class_map or {}, [uuid_instance_id(o.object_id) for o in msg.objects])
