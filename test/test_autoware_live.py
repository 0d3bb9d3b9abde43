"""Autoware boxes: the completer node with boxes_type autoware_detected / autoware_tracked against real rclpy pub/sub
(KITTI clouds, DetectedObjects / TrackedObjects built from the frame's boxes), and `complete_bag` on a recording with
a DetectedObjects topic completing the same vehicles. Plus the in-process pieces: boxes type resolution, the
track_ids warnings and the bag topic choice."""
from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("rclpy")
from kitti_frames import KittiFrame, cloud_msg, ros_time  # noqa: E402
from test_node_live import check_completion, frames, own_node, ros_context  # noqa: E402, F401  (fixtures)

from gd_completion.autoware_messages import (  # noqa: E402
    detected_objects_to_boxes,
    tracked_objects_to_boxes,
    uuid_instance_id,
)
from gd_completion.bags.typestore import (  # noqa: E402
    AUTOWARE_DETECTED_OBJECTS,
    AUTOWARE_TRACKED_OBJECTS,
    DETECTION3D_ARRAY,
    MARKER_ARRAY,
    POINTCLOUD2,
)
from gd_completion.class_maps import class_table  # noqa: E402
from gd_completion.geometry import Box3D  # noqa: E402
from gd_completion.labels import DEFAULT_LABELS, LABEL_IDS  # noqa: E402
from gd_completion.pointcloud2 import read_points  # noqa: E402
from gd_completion.ros.params import PARAMETERS, ParameterError, track_ids_problems, validate  # noqa: E402

LIDAR = "velodyne"
CLASSES = class_table("names")   # the node's default class_preset
UUID_A = bytes(range(16))
UUID_B = bytes(range(100, 116))
UUID_BIKE = bytes(range(200, 216))


@pytest.fixture(scope="module")
def apm():
    from built_msgs import import_built_msgs  # noqa: PLC0415 - builds the bindings on first use

    return import_built_msgs("autoware_perception_msgs")


@dataclass(frozen=True)
class Obj:
    """One Autoware object: its box (centre, size, yaw), ObjectClassification label, Shape type, UUID (tracked)."""

    box: Box3D
    label: int
    shape: int = 0          # Shape.BOUNDING_BOX
    uuid: bytes | None = None


def autoware_msg(apm, objects: list[Obj], stamp_ns: int, frame_id: str = LIDAR, tracked: bool = False):
    """DetectedObjects (TrackedObjects when `tracked`) of `objects`, as a perception stack publishes them."""
    from geometry_msgs.msg import Quaternion
    from unique_identifier_msgs.msg import UUID

    msg = apm.TrackedObjects() if tracked else apm.DetectedObjects()
    msg.header.stamp, msg.header.frame_id = ros_time(stamp_ns), frame_id
    for o in objects:
        obj = apm.TrackedObject() if tracked else apm.DetectedObject()
        kin = obj.kinematics
        pose = kin.pose_with_covariance.pose
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in o.box.center)
        pose.orientation = Quaternion(x=0.0, y=0.0, z=math.sin(o.box.yaw / 2), w=math.cos(o.box.yaw / 2))
        kin.orientation_availability = kin.AVAILABLE
        obj.shape.type = o.shape
        obj.shape.dimensions.x, obj.shape.dimensions.y, obj.shape.dimensions.z = (float(v) for v in o.box.size)
        obj.classification = [apm.ObjectClassification(label=o.label, probability=0.9)]
        obj.existence_probability = 0.9
        if tracked:
            assert o.uuid is not None
            obj.object_id = UUID(uuid=list(o.uuid))
        msg.objects.append(obj)
    return msg


def detected_sequence(apm, frame: KittiFrame) -> list[list[Obj]]:
    """Two DetectedObjects of KITTI frame 4 (cars b0, b1): [CAR b0, CAR b1, a CAR CYLINDER on b1], then
    [PEDESTRIAN on b1, CAR b0, the CYLINDER]: the pedestrian and the cylinder lie on a car that is completed as a
    CAR box, so only their class / shape keeps them out."""
    C, S = apm.ObjectClassification, apm.Shape
    b0, b1 = frame.boxes
    cylinder = Obj(b1, C.CAR, S.CYLINDER)
    return [[Obj(b0, C.CAR), Obj(b1, C.CAR), cylinder],
            [Obj(b1, C.PEDESTRIAN), Obj(b0, C.CAR), cylinder]]


# instance id (= index in the array) -> the KITTI box completed, per message of `detected_sequence`
DETECTED_EXPECTED = [{0: 0, 1: 1}, {1: 0}]


def expected_frame(frame: KittiFrame, expected: dict[int, int]) -> KittiFrame:
    """`frame` with its boxes renumbered to the instance ids the converter gives them (for check_completion)."""
    return KittiFrame(frame.index, frame.points, [replace(frame.boxes[k], instance_id=i) for i, k in expected.items()])


def vehicle_ids(boxes) -> set[int]:
    """Instance ids of a BoxSet's boxes whose label is completed by default."""
    return {b.instance_id for b in boxes.boxes if b.label in DEFAULT_LABELS}


def built_env(ros_env: dict[str, str]) -> dict[str, str]:
    """The node's environment additions for the locally built bindings (autoware_perception_msgs among them)."""
    import interfaces

    return interfaces.vision_msgs_env({**os.environ, **ros_env})


# -- in process --------------------------------------------------------------------------------------

def test_resolve_autoware_boxes_types(apm, monkeypatch):
    from gd_completion.ros.completer_node import resolve_boxes_type

    cls, convert, name = resolve_boxes_type("autoware_detected")
    assert (cls, convert, name) == (apm.DetectedObjects, detected_objects_to_boxes, AUTOWARE_DETECTED_OBJECTS)
    cls, convert, name = resolve_boxes_type("autoware_tracked")
    assert (cls, convert, name) == (apm.TrackedObjects, tracked_objects_to_boxes, AUTOWARE_TRACKED_OBJECTS)
    monkeypatch.setitem(sys.modules, "autoware_perception_msgs.msg", None)   # as if not installed
    with pytest.raises(ParameterError, match=r"boxes_type='autoware_tracked' but autoware_perception_msgs is not "
                                             r"importable .*scripts/build_interfaces.sh"):
        resolve_boxes_type("autoware_tracked")


def params(**values):
    return validate({**{name: default for name, (default, _, _) in PARAMETERS.items()}, **values})


def test_track_ids_problems():
    """Warned: a tracker's UUIDs unused while tracks are used, or array indices taken for track ids."""
    tracked = track_ids_problems(params(boxes_type="autoware_tracked"))   # defaults: associate, reuse on
    assert len(tracked) == 1 and "set track_ids:=message" in tracked[0]
    assert track_ids_problems(params(boxes_type="autoware_tracked", track_ids="message")) == []
    assert track_ids_problems(params(boxes_type="autoware_tracked", reuse=False)) == []   # no tracks used
    assert len(track_ids_problems(params(boxes_type="autoware_tracked", reuse=False, track_fusion=True))) == 1
    detected = track_ids_problems(params(boxes_type="autoware_detected", track_ids="message"))
    assert len(detected) == 1 and "no track id" in detected[0]
    assert track_ids_problems(params(boxes_type="autoware_detected")) == []
    assert track_ids_problems(params(boxes_type="detection3d", track_ids="message")) == []
    with pytest.raises(ParameterError, match="boxes_type='autoware'"):
        params(boxes_type="autoware")


def test_pick_topics_takes_autoware_objects():
    from gd_completion.bags.topics import pick_topics
    from gd_completion.errors import BagError

    def reader(**topics: str) -> SimpleNamespace:
        conns = [SimpleNamespace(topic=f"/{t}", msgtype=ty) for t, ty in {"points": POINTCLOUD2, **topics}.items()]
        return SimpleNamespace(path="bag", connections=conns)

    assert pick_topics(reader(tracks=AUTOWARE_TRACKED_OBJECTS), None, None) == (
        "/points", "/tracks", AUTOWARE_TRACKED_OBJECTS)
    both = reader(markers=MARKER_ARRAY, tracks=AUTOWARE_TRACKED_OBJECTS, objects=AUTOWARE_DETECTED_OBJECTS)
    assert pick_topics(both, None, None)[1:] == ("/objects", AUTOWARE_DETECTED_OBJECTS)   # detections first
    assert pick_topics(both, None, "/tracks")[1:] == ("/tracks", AUTOWARE_TRACKED_OBJECTS)
    assert pick_topics(reader(d=DETECTION3D_ARRAY, o=AUTOWARE_DETECTED_OBJECTS), None, None)[2] == DETECTION3D_ARRAY
    with pytest.raises(BagError, match=f"{AUTOWARE_DETECTED_OBJECTS}, {AUTOWARE_TRACKED_OBJECTS} or {MARKER_ARRAY}"):
        pick_topics(reader(), None, None)


# -- live --------------------------------------------------------------------------------------------

@pytest.mark.integration
def test_detected_objects_live(apm, ros_context, frames, tmp_path):  # noqa: F811
    """boxes_type autoware_detected: CAR objects completed with instance id = index in the array (the converter's);
    a PEDESTRIAN on a car's points is ignored (counted), a CYLINDER is skipped and counted in /diagnostics."""
    frame = frames[4]
    C = apm.ObjectClassification

    def boxes_msg(items, stamp_ns, frame_id):   # the client's warm-up sends the frame's Box3Ds: CAR objects
        return autoware_msg(apm, [o if isinstance(o, Obj) else Obj(o, C.CAR) for o in items], stamp_ns, frame_id)

    with own_node(ros_context, tmp_path, "aw_detected", params={"boxes_type": "autoware_detected"},
                  env=built_env(ros_context[0]), boxes_cls=apm.DetectedObjects) as (node, client):
        assert f"({AUTOWARE_DETECTED_OBJECTS})" in node.stderr
        client.boxes_msg = boxes_msg
        client.warm_up(frame)
        base = client.settled_diagnostics()
        for objects, expected in zip(detected_sequence(apm, frame), DETECTED_EXPECTED):
            stamp = client.send(frame, boxes=objects)
            msg = client.wait_reply(stamp)
            assert msg is not None, node.stderr[-2000:]
            assert vehicle_ids(detected_objects_to_boxes(boxes_msg(objects, stamp, LIDAR), CLASSES)) == set(expected)
            check_completion(msg, expected_frame(frame, expected), stamp, set(expected))
        wanted = {"frames_published": 2, "vehicles_completed": 3, "ignored_labels": 1, "skipped_unsupported_shape": 2}
        assert client.wait_diagnostics(base, wanted) == wanted
        assert "whose shape is no BOUNDING_BOX" in node.stderr
        assert "track_ids" not in node.stderr   # defaults (associate) with detections: no warning


@pytest.mark.integration
def test_tracked_objects_live_with_fusion(apm, ros_context, frames, tmp_path):  # noqa: F811
    """boxes_type autoware_tracked, track_fusion, track_ids message: two frames with the same UUIDs are answered with
    the converter's UUID-derived instance ids both times, the fused tracks are those two (keyed by the UUIDs: their
    measured points grow, no built-in association runs), a BICYCLE object is ignored."""
    frame = frames[4]
    C = apm.ObjectClassification
    uuids = {0: UUID_A, 1: UUID_B}   # KITTI box (row) -> the tracker's UUID

    def boxes_msg(boxes, stamp_ns, frame_id):
        objects = [Obj(b, C.CAR, uuid=uuids[b.instance_id]) for b in boxes]
        objects.append(Obj(boxes[1], C.BICYCLE, uuid=UUID_BIKE))   # on a car: not completed, not a duplicate
        return autoware_msg(apm, objects, stamp_ns, frame_id, tracked=True)

    expected = {uuid_instance_id(UUID_A): 0, uuid_instance_id(UUID_B): 1}
    converted = tracked_objects_to_boxes(boxes_msg(frame.boxes, 0, LIDAR), CLASSES)
    assert vehicle_ids(converted) == set(expected) and len(converted.boxes) == 3
    parameters = {"boxes_type": "autoware_tracked", "track_fusion": "true", "track_ids": "message",
                  "publish_fused_points": "true", "fusion_expiry": "30.0"}
    with own_node(ros_context, tmp_path, "aw_tracked", params=parameters, env=built_env(ros_context[0]),
                  boxes_cls=apm.TrackedObjects) as (node, client):
        assert f"({AUTOWARE_TRACKED_OBJECTS})" in node.stderr
        client.boxes_msg = boxes_msg
        first = client.send_until_reply(frame)          # the first frame answered (resent until one is)
        assert first is not None, node.stderr[-2000:]
        base = client.settled_diagnostics()
        second = client.send_until_reply(frame)         # a later frame of the same tracks
        assert second is not None, node.stderr[-2000:]
        measured = []
        for msg in (first, second):
            pts = read_points(msg)
            assert set(np.unique(pts["instance_id"]).tolist()) == set(expected)
            assert (pts["label"] == LABEL_IDS["car"]).all()
            measured.append({i: int(((pts["instance_id"] == i) & (pts["generated"] == 0)).sum()) for i in expected})
        assert all(measured[1][i] > measured[0][i] > 0 for i in expected), measured   # fused by UUID track
        wanted = {"frames_published": 1, "vehicles_completed": 2, "ignored_labels": 1}
        grown = client.wait_diagnostics(base, wanted)   # per frame: the two cars completed, the bicycle ignored
        assert grown["frames_published"] >= 1 and grown["vehicles_completed"] == 2 * grown["frames_published"]
        assert grown["ignored_labels"] == grown["frames_published"]
        diag = client.diag
        assert diag["tracks_alive"] == 2 and diag["tracks_reset"] == 0
        assert "association_tracks" not in diag   # track_ids message: the UUIDs are the tracks, no association
        assert "track_ids" not in node.stderr     # no track_ids warning with track_ids:=message


# -- offline -----------------------------------------------------------------------------------------

@pytest.mark.integration
def test_complete_bag_with_detected_objects(apm, frames, tmp_path):  # noqa: F811
    """A recording of clouds and a DetectedObjects topic (the messages of the live test, as rclpy serialises them):
    `complete_bag` picks the Autoware topic and completes the same vehicles (instance ids, labels) as the node, with
    the same counts."""
    from rclpy.serialization import serialize_message

    from gd_completion.bags.completion import complete_bag
    from gd_completion.bags.reader import iter_raw, open_bag
    from gd_completion.bags.typestore import deserialize
    from gd_completion.bags.writer import add_connection, atomic_bag_writer
    from gd_completion.settings import CompletionSettings

    frame = frames[4]
    bag, out = tmp_path / "drive", tmp_path / "done"
    stamps = [1_000_000_000_000 + k * 100_000_000 for k in range(2)]
    with atomic_bag_writer(bag) as writer:
        clouds = add_connection(writer, "/points", POINTCLOUD2)
        objects = add_connection(writer, "/perception/object_recognition/detection/objects", AUTOWARE_DETECTED_OBJECTS)
        for stamp, objs in zip(stamps, detected_sequence(apm, frame)):
            writer.write(clouds, stamp, serialize_message(cloud_msg(frame.points, stamp, LIDAR)))
            writer.write(objects, stamp + 1, serialize_message(autoware_msg(apm, objs, stamp)))
    summary = complete_bag(bag, out, CompletionSettings.offline(num_threads=1), progress=False)
    counters = summary.counters()
    assert summary.frames == 2 and counters["frames_paired"] == 2
    assert (summary.vehicles_completed, summary.ignored_labels, counters["skipped_unsupported_shape"]) == (3, 1, 2)
    assert "skipped_unsupported_shape 2" in summary.text()
    with open_bag(out) as reader:
        conns = [c for c in reader.connections if c.topic == summary.output_topic]
        completed = [deserialize(raw, POINTCLOUD2) for _, _, raw in iter_raw(reader, conns)]
    assert len(completed) == 2
    for msg, stamp, expected in zip(completed, stamps, DETECTED_EXPECTED):
        check_completion(msg, expected_frame(frame, expected), stamp, set(expected))
