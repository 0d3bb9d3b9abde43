"""Which topics of a bag hold the clouds and the boxes, and where completions go (shared by `complete` and `render`)."""
from __future__ import annotations

from typing import Any

from gd_completion.bags.typestore import (
    AUTOWARE_DETECTED_OBJECTS,
    AUTOWARE_TRACKED_OBJECTS,
    DETECTION3D_ARRAY,
    MARKER_ARRAY,
    POINTCLOUD2,
)
from gd_completion.errors import BagError

DEFAULT_CLOUD_TOPICS = ("/kitti/points", "/pandar64/points", "/points")
# The boxes types `complete` and `render` read, in the order a boxes topic is picked when none is given.
BOXES_TYPES = (DETECTION3D_ARRAY, AUTOWARE_DETECTED_OBJECTS, AUTOWARE_TRACKED_OBJECTS, MARKER_ARRAY)


def _one_of() -> str:
    """'A, B, C or D' of BOXES_TYPES."""
    return ", ".join(BOXES_TYPES[:-1]) + f" or {BOXES_TYPES[-1]}"


def default_output_topic(cloud_topic: str) -> str:
    """'/kitti/points' -> '/kitti/completed'; '/points' -> '/completed'."""
    parent = cloud_topic.rstrip("/").rpartition("/")[0]
    return f"{parent}/completed"


def pick_topics(reader: Any, cloud_topic: str | None, boxes_topic: str | None) -> tuple[str, str, str]:
    """(cloud topic, boxes topic, boxes type) of a bag; BagError naming the bag when ambiguous or absent."""
    types = {c.topic: c.msgtype for c in reader.connections}
    clouds = sorted(t for t, ty in types.items() if ty == POINTCLOUD2)
    if cloud_topic is None:
        preferred = [t for t in DEFAULT_CLOUD_TOPICS if t in clouds]
        if len(clouds) == 1 or preferred:
            cloud_topic = clouds[0] if len(clouds) == 1 else preferred[0]
        elif not clouds:
            raise BagError(f"{reader.path}: no {POINTCLOUD2} topic")
        else:
            raise BagError(f"{reader.path}: several PointCloud2 topics ({', '.join(clouds)}); choose --cloud-topic")
    elif cloud_topic not in types:
        raise BagError(f"{reader.path}: no topic {cloud_topic}")
    elif types[cloud_topic] != POINTCLOUD2:
        raise BagError(f"{reader.path}: {cloud_topic} has type {types[cloud_topic]}, not {POINTCLOUD2}")
    if boxes_topic is None:
        candidates = [t for kind in BOXES_TYPES for t in sorted(t for t, ty in types.items() if ty == kind)]
        if not candidates:
            raise BagError(f"{reader.path}: clouds without boxes: no {_one_of()} topic (give --boxes-topic)")
        boxes_topic = candidates[0]
    elif boxes_topic not in types:
        raise BagError(f"{reader.path}: no topic {boxes_topic}")
    if types[boxes_topic] not in BOXES_TYPES:
        raise BagError(f"{reader.path}: {boxes_topic} has type {types[boxes_topic]}; expected {_one_of()}")
    return cloud_topic, boxes_topic, types[boxes_topic]
