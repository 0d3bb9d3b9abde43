"""One frame of a bag as the node sees it: a cloud message, the boxes it pairs it with (moved into its frame with the
bag's /tf) and the completion written for it."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from gd_completion.bags.pairing import BagPairing, RecordedCloud
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.topics import default_output_topic, pick_topics
from gd_completion.bags.typestore import POINTCLOUD2, deserialize
from gd_completion.box_messages import BoxSet
from gd_completion.errors import BagError
from gd_completion.geometry import Box3D
from gd_completion.stamp_sync import SYNC_TOLERANCE_S, stamp_to_ns
from gd_completion.transforms import TransformBuffer


def _paired_frame(reader: Any, pairing: BagPairing, frame: int) -> tuple[RecordedCloud, BoxSet | None] | None:
    """Cloud message number `frame` and the boxes the node pairs it with (None when there is no such frame)."""
    conns = [c for c in reader.connections if c.topic in (pairing.cloud_topic, pairing.boxes_topic)]
    for conn, bag_ns, raw in iter_raw(reader, conns):
        for cloud, boxes in pairing.feed(conn.topic, bag_ns, raw)[1]:
            if cloud.index == frame:
                return cloud, boxes
    return next(((c, b) for c, b in pairing.close() if c.index == frame), None)


def _cloud_at(reader: Any, topic: str, stamp: int) -> Any | None:
    conns = [c for c in reader.connections if c.topic == topic]
    for _c, _t, raw in iter_raw(reader, conns):
        msg = deserialize(raw, POINTCLOUD2, f"{reader.path} {topic}")
        if stamp_to_ns(msg.header.stamp) == stamp:
            return msg
    return None


def read_frame(bag: str | Path, frame: int = 0, *, cloud_topic: str | None = None, boxes_topic: str | None = None,
               completed_topic: str | None = None, sync_tolerance: float = SYNC_TOLERANCE_S
               ) -> tuple[str, Any, list[Box3D], Any | None]:
    """(cloud topic, cloud message number `frame`, its boxes in its frame as the node pairs them (moved with the
    transforms read up to the pairing: no `transform_wait`, so boxes whose transform was recorded later are left out),
    its completion on `completed_topic` (same stamp) or None)."""
    with open_bag(bag) as reader:
        cloud_topic, boxes_topic, boxes_type = pick_topics(reader, cloud_topic, boxes_topic)
        completed_topic = completed_topic or default_output_topic(cloud_topic)
        transforms = TransformBuffer()
        pairing = BagPairing(cloud_topic, boxes_topic, boxes_type, tolerance_s=sync_tolerance, transforms=transforms,
                             source=str(bag))
        found = _paired_frame(reader, pairing, frame)
        if found is None:
            raise BagError(f"{bag}: {cloud_topic} has no frame {frame}")
        cloud, box_set = found
        boxes = cloud.boxes_in_frame(box_set, transforms)[0]
        completed = None
        if completed_topic in {c.topic for c in reader.connections}:
            completed = _cloud_at(reader, completed_topic, cloud.stamp_ns)
    return cloud_topic, cloud.msg, boxes, completed
