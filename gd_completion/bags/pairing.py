"""A bag's clouds paired with its boxes as the completer node pairs them live (RecordingSync over bag time)."""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from gd_completion.autoware_messages import detected_objects_to_boxes, tracked_objects_to_boxes
from gd_completion.bags.typestore import (
    AUTOWARE_DETECTED_OBJECTS,
    AUTOWARE_TRACKED_OBJECTS,
    DETECTION3D_ARRAY,
    MARKER_ARRAY,
    POINTCLOUD2,
    TF_MESSAGE,
    deserialize,
)
from gd_completion.box_messages import BoxSet, detections_to_boxes, markers_to_boxes
from gd_completion.errors import BagError
from gd_completion.geometry import Box3D
from gd_completion.stamp_sync import SYNC_TOLERANCE_S, RecordingSync, SyncCounters, stamp_to_ns
from gd_completion.transforms import TransformBuffer, boxes_in_frame

TF_TOPICS = {"/tf": False, "/tf_static": True}   # topic -> static


@dataclass(frozen=True)
class RecordedCloud:
    """One message of the cloud topic."""

    index: int  # position among the cloud topic's messages
    bag_ns: int  # bag timestamp
    msg: Any  # the sensor_msgs/PointCloud2 (rosbags object)

    @property
    def stamp_ns(self) -> int:
        """Header stamp (ns)."""
        return stamp_to_ns(self.msg.header.stamp)

    def boxes_in_frame(self, boxes: BoxSet | None, transforms: TransformBuffer | None = None
                       ) -> tuple[list[Box3D], int]:
        """The paired boxes in this cloud's frame at its stamp (boxes in another frame moved by `transforms`), and
        how many were left out (no transform known, or none given)."""
        if boxes is None:
            return [], 0
        return boxes_in_frame(boxes, self.msg.header.frame_id, self.stamp_ns, transforms)


# boxes message type -> its converter (the node's boxes_type: detection3d, marker, autoware_detected, _tracked)
BOX_CONVERTERS: dict[str, Callable[..., BoxSet]] = {
    DETECTION3D_ARRAY: detections_to_boxes,
    MARKER_ARRAY: markers_to_boxes,
    AUTOWARE_DETECTED_OBJECTS: detected_objects_to_boxes,
    AUTOWARE_TRACKED_OBJECTS: tracked_objects_to_boxes,
}


def box_set_from_message(msg: Any, msgtype: str, class_map: Mapping[str, str] | None = None) -> BoxSet:
    """The BoxSet (stamp, boxes, per-box frame) of a Detection3DArray, MarkerArray or Autoware DetectedObjects /
    TrackedObjects message, as the node reads it (detector classes mapped by `class_map`, as the node's
    class_preset and class_map)."""
    convert = BOX_CONVERTERS.get(msgtype)
    if convert is None:
        raise BagError(f"boxes topic has type {msgtype}; expected one of {', '.join(BOX_CONVERTERS)}")
    return convert(msg, class_map)


class BagPairing:
    """Feed a bag's messages in recorded order; the clouds of `cloud_topic` come out with the boxes of
    `boxes_topic` that the node would pair them with (stamps within `tolerance_s`), or with None. /tf and
    /tf_static feed `transforms` (when given) as the node's subscriptions feed its buffer."""

    def __init__(self, cloud_topic: str, boxes_topic: str, boxes_type: str, *,
                 tolerance_s: float = SYNC_TOLERANCE_S, class_map: Mapping[str, str] | None = None,
                 transforms: TransformBuffer | None = None, source: str = "bag") -> None:
        self.class_map = class_map
        self.transforms = transforms
        self.cloud_topic, self.boxes_topic, self.boxes_type, self.source = cloud_topic, boxes_topic, boxes_type, source
        self.sync: RecordingSync[RecordedCloud, BoxSet] = RecordingSync(int(tolerance_s * 1e9))
        self.boxes_without_header = 0  # empty MarkerArrays: no header to pair by (the node skips them too)
        self.unsupported_shapes = 0  # Autoware objects whose shape is no box (counted as the node counts them)
        self._clouds = 0

    @property
    def counters(self) -> SyncCounters:
        """The synchroniser's counters (paired, cloud_no_boxes, ...), as the node reports them."""
        return self.sync.sync.counters

    def feed(self, topic: str, bag_ns: int, raw: bytes) -> tuple[RecordedCloud | None,
                                                                 list[tuple[RecordedCloud, BoxSet | None]]]:
        """One message: (the cloud when it is one, the clouds whose pairing it decided)."""
        if topic == self.cloud_topic:
            cloud = RecordedCloud(self._clouds, bag_ns, deserialize(raw, POINTCLOUD2, f"{self.source} {topic}"))
            self._clouds += 1
            return cloud, self.sync.add_cloud(cloud.stamp_ns, cloud, bag_ns)
        if topic in TF_TOPICS and self.transforms is not None:   # in recorded order, as the node receives them
            self.transforms.add_message(deserialize(raw, TF_MESSAGE, f"{self.source} {topic}"), TF_TOPICS[topic])
            return None, []
        if topic == self.boxes_topic:
            boxes = box_set_from_message(deserialize(raw, self.boxes_type, f"{self.source} {topic}"), self.boxes_type,
                                         self.class_map)
            self.unsupported_shapes += boxes.unsupported_shapes
            if boxes.stamp_ns is None:
                self.boxes_without_header += 1
                return None, []
            return None, self.sync.add_boxes(boxes.stamp_ns, boxes, bag_ns)
        return None, []

    def close(self) -> list[tuple[RecordedCloud, BoxSet | None]]:
        """The bag ended: the clouds still waiting get no boxes."""
        return self.sync.close()
