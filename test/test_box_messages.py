"""MarkerArray / Detection3DArray -> Box3D with real rclpy message objects: yaw, labels, class_map, frames."""
from __future__ import annotations

import math
import zlib

import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, Quaternion
from visualization_msgs.msg import Marker, MarkerArray

from gd_completion.box_messages import detections_to_boxes, markers_to_boxes
from gd_completion.class_maps import map_label, parse_class_map
from gd_completion.errors import BoxError
from gd_completion.rotations import yaw_from_quaternion

CLASS_MAP = parse_class_map(["1:car", "2:van", "3:truck", "Car:car", "Pedestrian:ignore"])


def quat(yaw: float, scale: float = 1.0) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2) * scale, w=math.cos(yaw / 2) * scale)


def cube(mid: int, ns: str, yaw: float, frame: str = "velo", text: str = "", action: int = Marker.ADD,
         mtype: int = Marker.CUBE) -> Marker:
    m = Marker(ns=ns, id=mid, type=mtype, action=action, text=text)
    m.header.frame_id, m.header.stamp = frame, Time(sec=5, nanosec=250_000_000)
    m.pose.position.x, m.pose.position.y, m.pose.position.z = 10.0, -2.0, 0.8
    m.pose.orientation = quat(yaw)
    m.scale.x, m.scale.y, m.scale.z = 4.2, 1.8, 1.5
    return m


@pytest.mark.parametrize("yaw", [0.0, 0.3, -1.2, math.pi / 2, 3.0, -3.0])
@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_yaw_from_quaternion_round_trips(yaw, scale):
    q = quat(yaw, scale)
    assert yaw_from_quaternion(q.x, q.y, q.z, q.w) == pytest.approx(yaw, abs=1e-9)


def test_yaw_ignores_roll_and_pitch_free_parts_and_identity():
    assert yaw_from_quaternion(0.0, 0.0, 0.0, 0.0) == 0.0  # unset Pose orientation reads as identity
    assert math.isnan(yaw_from_quaternion(math.nan, 0.0, 0.0, 1.0))
    # pure pitch by 0.4 rad keeps yaw 0
    assert yaw_from_quaternion(0.0, math.sin(0.2), 0.0, math.cos(0.2)) == pytest.approx(0.0, abs=1e-12)


def test_parse_class_map_and_map_label():
    assert CLASS_MAP == {"1": "car", "2": "van", "3": "truck", "Car": "car", "Pedestrian": "ignore"}
    assert map_label("1", CLASS_MAP) == "car"
    assert map_label("Pedestrian", CLASS_MAP) == "ignore"
    assert map_label("Truck", CLASS_MAP) == "truck"  # unmapped: lower-cased
    assert parse_class_map(["a:b:Van"]) == {"a:b": "van"}
    for bad in (["car"], [":car"], ["1:"]):
        with pytest.raises(BoxError, match="class_map entry"):
            parse_class_map(bad)


def test_markers_to_boxes():
    msg = MarkerArray(markers=[
        cube(7, "Car", 0.5),
        cube(8, "ignored-ns", -1.0, text="2"),  # text wins over ns
        cube(9, "Pedestrian", 0.0),
        cube(10, "car", 0.0, action=Marker.DELETE),  # ignored
        cube(11, "car", 0.0, mtype=Marker.TEXT_VIEW_FACING),  # ignored
        cube(12, "truck", 1.0, frame="map"),
    ])
    bs = markers_to_boxes(msg, CLASS_MAP)
    assert bs.stamp_ns == 5_250_000_000
    assert [b.instance_id for b in bs.boxes] == [7, 8, 9, 12]
    assert [b.label for b in bs.boxes] == ["car", "van", "ignore", "truck"]
    assert bs.frame_ids == ("velo", "velo", "velo", "map")
    b = bs.boxes[0]
    assert b.center == pytest.approx((10.0, -2.0, 0.8))
    assert b.size == pytest.approx((4.2, 1.8, 1.5))
    assert b.yaw == pytest.approx(0.5)
    assert bs.boxes[1].yaw == pytest.approx(-1.0)
    kept, wrong = bs.split_by_frame("velo")
    assert [k.instance_id for k in kept] == [7, 8, 9] and wrong == 1


def test_markers_stamp_from_deleteall_and_empty_array():
    deleteall = cube(0, "", 0.0, action=Marker.DELETEALL)
    bs = markers_to_boxes(MarkerArray(markers=[deleteall]))
    assert bs.stamp_ns == 5_250_000_000 and bs.boxes == ()
    assert markers_to_boxes(MarkerArray()).stamp_ns is None


def test_degenerate_marker_values_are_kept_for_the_pipeline_to_skip():
    m = cube(1, "car", 0.0)
    m.scale.x = 0.0
    m.pose.orientation = Quaternion(x=math.nan, y=0.0, z=0.0, w=1.0)
    b = markers_to_boxes(MarkerArray(markers=[m])).boxes[0]
    assert b.size[0] == 0.0 and math.isnan(b.yaw)


def _detection_array():
    from interfaces import import_vision_msgs  # noqa: PLC0415 - another engineer's helper

    import_vision_msgs()
    from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose  # noqa: PLC0415

    arr = Detection3DArray()
    arr.header.frame_id, arr.header.stamp = "velo", Time(sec=3, nanosec=7)
    dets = []
    for i, (ident, classes, yaw) in enumerate([("41", [("1", 0.9), ("2", 0.3)], 0.7),
                                               ("track-b", [("Car", 0.2), ("3", 0.6)], -2.0),
                                               ("", [], 0.0)]):
        d = Detection3D(id=ident)
        d.bbox.center = Pose()
        d.bbox.center.position.x = 5.0 + i
        d.bbox.center.orientation = quat(yaw)
        d.bbox.size.x, d.bbox.size.y, d.bbox.size.z = 4.5, 1.9, 1.6
        for cid, score in classes:
            h = ObjectHypothesisWithPose()
            h.hypothesis.class_id, h.hypothesis.score = cid, score
            d.results.append(h)
        dets.append(d)
    dets[2].header.frame_id = "map"
    arr.detections = dets
    return arr


def test_detections_to_boxes():
    import interfaces  # noqa: F401  (vision_msgs bindings on the path)
    bs = detections_to_boxes(_detection_array(), CLASS_MAP)
    assert bs.stamp_ns == 3_000_000_007
    assert [b.label for b in bs.boxes] == ["car", "truck", ""]  # best score wins; no result -> no label
    ids = [b.instance_id for b in bs.boxes]
    assert ids[0] == 41 and ids[2] == 2        # integer id kept; an empty id -> the detection's index
    assert ids[1] == zlib.crc32(b"track-b") & 0x7FFFFFFF and 0 <= ids[1] < 2**31   # text id -> stable hash
    assert bs.boxes[0].yaw == pytest.approx(0.7) and bs.boxes[1].yaw == pytest.approx(-2.0)
    assert bs.boxes[0].size == pytest.approx((4.5, 1.9, 1.6)) and bs.boxes[1].center[0] == pytest.approx(6.0)
    assert bs.frame_ids == ("velo", "velo", "map")


def test_detections_to_boxes_duck_typed():
    """The same conversion on plain objects shaped like vision_msgs (runs without the bindings)."""
    from types import SimpleNamespace as NS

    def det(ident, classes, x, yaw, frame=""):
        q = quat(yaw)
        return NS(id=ident, header=NS(frame_id=frame),
                  bbox=NS(center=NS(position=NS(x=x, y=1.0, z=0.5), orientation=q), size=NS(x=4.0, y=1.7, z=1.4)),
                  results=[NS(hypothesis=NS(class_id=c, score=s)) for c, s in classes])

    arr = NS(header=NS(frame_id="velo", stamp=Time(sec=1, nanosec=2)),
             detections=[det("3", [("2", float("nan")), ("Pedestrian", 0.1)], 2.0, 1.0),
                         det("x", [("Car", 0.8)], 9.0, 0.0, frame="base_link")])
    bs = detections_to_boxes(arr, CLASS_MAP)
    assert bs.stamp_ns == 1_000_000_002
    assert [b.label for b in bs.boxes] == ["ignore", "car"]  # a NaN score ranks last
    assert [b.instance_id for b in bs.boxes] == [3, zlib.crc32(b"x") & 0x7FFFFFFF]
    assert bs.boxes[0].yaw == pytest.approx(1.0) and bs.boxes[0].center == pytest.approx((2.0, 1.0, 0.5))
    assert bs.split_by_frame("velo") == ([bs.boxes[0]], 1)


def test_detection_ids_map_to_stable_int32():
    from gd_completion.box_messages import _instance_id

    assert _instance_id("7", 0) == 7 and _instance_id("-3", 0) == -3 and _instance_id(" 12 ", 0) == 12
    assert _instance_id("2147483647", 0) == 2**31 - 1
    big = _instance_id("99999999999", 4)          # beyond int32: hashed, not an OverflowError
    assert 0 <= big < 2**31 and big == _instance_id("99999999999", 9)
    uuid = "0b6c6e2c-5f0e-4c1e-9d8a-3f1e2d4c5b6a"
    assert _instance_id(uuid, 1) == _instance_id(uuid, 5) != _instance_id(uuid + "x", 1)
    assert _instance_id("", 6) == 6
