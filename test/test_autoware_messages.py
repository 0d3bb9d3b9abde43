"""Autoware DetectedObjects / TrackedObjects -> BoxSet with real messages from the locally built
autoware_perception_msgs bindings, and tf2_msgs/TFMessage from the same build through rclpy serialization."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import zlib

import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, TransformStamped
from rclpy.serialization import deserialize_message, serialize_message
from unique_identifier_msgs.msg import UUID

from gd_completion.autoware_messages import (
    AUTOWARE_LABELS,
    best_label,
    detected_objects_to_boxes,
    tracked_objects_to_boxes,
    uuid_instance_id,
)
from gd_completion.bags.typestore import TF_MESSAGE, typestore
from gd_completion.box_messages import _instance_id, box_count
from gd_completion.class_maps import parse_class_map

STAMP = Time(sec=1_700_000_000, nanosec=250_000_000)
STAMP_NS = 1_700_000_000_250_000_000
UUID_A = bytes(range(16))
UUID_B = bytes(range(100, 116))
# Upstream tf2_msgs/msg/TFMessage (Jazzy) type hash; identical .msg text gives identical hashes.
TFMESSAGE_TYPE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


@pytest.fixture(scope="module")
def apm():
    from built_msgs import import_built_msgs  # noqa: PLC0415 - builds the bindings on first use

    return import_built_msgs("autoware_perception_msgs")


def quat(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def make_object(apm, cls, xyz, yaw, dims, classes, shape=0, uuid: bytes | None = None):
    """A DetectedObject (TrackedObject when `uuid` is given) with the pose, shape and (label, probability) list."""
    obj = cls()
    kin = obj.kinematics
    kin.pose_with_covariance.pose.position.x, kin.pose_with_covariance.pose.position.y, \
        kin.pose_with_covariance.pose.position.z = xyz
    kin.pose_with_covariance.pose.orientation = quat(yaw)
    kin.orientation_availability = kin.AVAILABLE
    obj.shape.type = shape
    obj.shape.dimensions.x, obj.shape.dimensions.y, obj.shape.dimensions.z = dims
    obj.classification = [apm.ObjectClassification(label=label, probability=p) for label, p in classes]
    obj.existence_probability = 0.9
    if uuid is not None:
        obj.object_id = UUID(uuid=list(uuid))
    return obj


def detected(apm):
    C, S = apm.ObjectClassification, apm.Shape
    msg = apm.DetectedObjects()
    msg.header.frame_id, msg.header.stamp = "base_link", STAMP
    D = apm.DetectedObject
    msg.objects = [
        make_object(apm, D, (12.0, -3.0, 0.9), 0.5, (4.6, 1.9, 1.5), [(C.PEDESTRIAN, 0.2), (C.CAR, 0.8)]),
        make_object(apm, D, (25.0, 4.0, 1.6), -2.5, (9.0, 2.5, 3.2), [(C.TRUCK, 0.9)]),
        make_object(apm, D, (6.0, 2.0, 0.85), 0.0, (0.6, 0.6, 1.7), [(C.PEDESTRIAN, 0.95)]),
        make_object(apm, D, (8.0, -6.0, 0.5), 0.0, (1.0, 1.0, 1.0), [(C.UNKNOWN, 0.5)], shape=S.CYLINDER),
        make_object(apm, D, (40.0, 0.0, 1.8), math.pi / 2, (12.0, 2.6, 3.4), [(C.CAR, 0.4), (C.BUS, 0.6)]),
    ]
    return msg


def tracked(apm, uuids: list[bytes], shapes: list[int] | None = None):
    C = apm.ObjectClassification
    msg = apm.TrackedObjects()
    msg.header.frame_id, msg.header.stamp = "map", STAMP
    shapes = shapes or [apm.Shape.BOUNDING_BOX] * len(uuids)
    msg.objects = [make_object(apm, apm.TrackedObject, (10.0 * i, 1.0, 0.8), 0.25 * i, (4.5, 1.8, 1.5),
                               [(C.CAR, 0.7)], shape, uuid) for i, (uuid, shape) in enumerate(zip(uuids, shapes))]
    return msg


def test_autoware_labels_match_the_message_constants(apm):
    C = apm.ObjectClassification
    assert AUTOWARE_LABELS[C.CAR] == "car" and AUTOWARE_LABELS[C.TRUCK] == "truck"
    assert AUTOWARE_LABELS[C.BUS] == "bus" and AUTOWARE_LABELS[C.TRAILER] == "trailer"
    for name in ("UNKNOWN", "MOTORCYCLE", "BICYCLE", "PEDESTRIAN", "ANIMAL", "HAZARD", "OVER_DRIVABLE",
                 "UNDER_DRIVABLE"):
        assert AUTOWARE_LABELS[getattr(C, name)] == name.lower()


def test_detected_objects_to_boxes(apm):
    msg = detected(apm)
    bs = detected_objects_to_boxes(msg, parse_class_map(["bus:truck"]))
    assert box_count(msg) == 5 and bs.unsupported_shapes == 1   # the cylinder is counted, not converted
    assert [b.label for b in bs.boxes] == ["car", "truck", "pedestrian", "truck"]  # bus -> truck by class_map
    assert [b.instance_id for b in bs.boxes] == [0, 1, 2, 4]    # index in the array (no ids on detections)
    assert bs.frame_ids == ("base_link",) * 4 and bs.stamp_ns == STAMP_NS
    car, truck, ped, bus = bs.boxes
    assert car.center == pytest.approx((12.0, -3.0, 0.9)) and car.size == pytest.approx((4.6, 1.9, 1.5))
    assert car.yaw == pytest.approx(0.5) and truck.yaw == pytest.approx(-2.5) and bus.yaw == pytest.approx(math.pi / 2)
    assert truck.size == pytest.approx((9.0, 2.5, 3.2)) and ped.size == pytest.approx((0.6, 0.6, 1.7))
    assert bus.center == pytest.approx((40.0, 0.0, 1.8))
    assert detected_objects_to_boxes(msg).boxes[3].label == "bus"  # without a class_map: the Autoware name


def test_tracked_ids_are_stable_per_uuid(apm):
    first = tracked_objects_to_boxes(tracked(apm, [UUID_A, UUID_B]))
    second = tracked_objects_to_boxes(tracked(apm, [UUID_B, UUID_A]))
    id_a, id_b = (b.instance_id for b in first.boxes)
    assert [b.instance_id for b in second.boxes] == [id_b, id_a] and id_a != id_b
    assert all(0 <= i < 2**31 for i in (id_a, id_b))
    # Documented value: crc32 of the hex text, i.e. what a Detection3D with that hex `id` gets.
    assert id_a == zlib.crc32(UUID_A.hex().encode()) & 0x7FFFFFFF == _instance_id(UUID_A.hex(), 7)
    assert uuid_instance_id(UUID(uuid=list(UUID_B))) == uuid_instance_id(UUID_B) == id_b
    assert first.frame_ids == ("map", "map") and first.stamp_ns == STAMP_NS and first.unsupported_shapes == 0
    assert [b.label for b in first.boxes] == ["car", "car"]
    assert first.boxes[1].center == pytest.approx((10.0, 1.0, 0.8)) and first.boxes[1].yaw == pytest.approx(0.25)


def test_tracked_polygon_and_cylinder_are_counted(apm):
    S = apm.Shape
    msg = tracked(apm, [UUID_A, UUID_B, bytes(16)], [S.POLYGON, S.BOUNDING_BOX, S.CYLINDER])
    bs = tracked_objects_to_boxes(msg)
    assert box_count(msg) == 3 and bs.unsupported_shapes == 2
    assert [b.instance_id for b in bs.boxes] == [uuid_instance_id(UUID_B)] and bs.frame_ids == ("map",)


def test_best_label_edge_cases(apm):
    C = apm.ObjectClassification
    assert best_label([]) == ""
    assert best_label([C(label=C.CAR, probability=math.nan), C(label=C.BICYCLE, probability=0.1)]) == "bicycle"
    assert best_label([C(label=42, probability=1.0)]) == "42"   # a label newer than the table: its number
    assert best_label([C(label=C.TRAILER, probability=0.5), C(label=C.CAR, probability=0.5)]) == "trailer"  # tie: 1st
    empty = tracked(apm, [UUID_A])
    empty.objects[0].classification = []
    assert tracked_objects_to_boxes(empty).boxes[0].label == ""


def test_rosbags_messages_convert_the_same(apm):
    """The bag side (rosbags objects from gd_completion/msg) gives the same boxes as the rclpy objects."""
    for msg, convert in ((detected(apm), detected_objects_to_boxes), (tracked(apm, [UUID_A, UUID_B]),
                                                                       tracked_objects_to_boxes)):
        name = f"autoware_perception_msgs/msg/{type(msg).__name__}"
        from_bag = typestore().deserialize_cdr(serialize_message(msg), name)
        assert convert(from_bag, {"bus": "truck"}) == convert(msg, {"bus": "truck"})


def test_autoware_type_hashes_match_the_bag_typestore(apm):
    from built_msgs import built_type_hash  # noqa: PLC0415

    for name in ("DetectedObjects", "TrackedObjects"):
        assert built_type_hash("autoware_perception_msgs", name) == typestore().hash_rihs01(
            f"autoware_perception_msgs/msg/{name}")


def test_tf_message_roundtrip():
    from built_msgs import built_type_hash, import_built_msgs  # noqa: PLC0415

    tf2 = import_built_msgs("tf2_msgs")
    transforms = []
    for i, (parent, child) in enumerate([("map", "odom"), ("odom", "base_link")]):
        t = TransformStamped(child_frame_id=child)
        t.header.frame_id, t.header.stamp = parent, STAMP
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = 1.5 * (i + 1), -2.0, 0.25
        t.transform.rotation = quat(0.3 * (i + 1))
        transforms.append(t)
    msg = tf2.TFMessage(transforms=transforms)
    raw = serialize_message(msg)
    back = deserialize_message(raw, tf2.TFMessage)
    assert back == msg and [t.child_frame_id for t in back.transforms] == ["odom", "base_link"]
    assert back.transforms[1].transform.translation.x == 3.0
    assert back.transforms[1].transform.rotation.z == pytest.approx(math.sin(0.3))
    from_bag = typestore().deserialize_cdr(raw, TF_MESSAGE)   # the same bytes as a bag would hold them
    first = from_bag.transforms[0]
    assert first.header.frame_id == "map" and first.header.stamp.nanosec == 250_000_000
    assert first.transform.translation.x == 1.5 and first.child_frame_id == "odom"
    assert built_type_hash("tf2_msgs", "TFMessage") == TFMESSAGE_TYPE_HASH


@pytest.mark.integration  # starts a process
def test_built_packages_import_with_the_subprocess_environment():
    """`interfaces.vision_msgs_env()` (the one install prefix on PYTHONPATH, LD_LIBRARY_PATH, AMENT_PREFIX_PATH),
    as a node or `play` gets it, serves all three packages with their type support."""
    from interfaces import vision_msgs_env  # noqa: PLC0415

    code = ("from rclpy.serialization import serialize_message as s\n"
            "import tf2_msgs.msg as t, autoware_perception_msgs.msg as a, vision_msgs.msg as v\n"
            "print(len(s(t.TFMessage())), len(s(a.TrackedObjects())), len(s(v.Detection3DArray())), a.__file__)")
    env = {**os.environ, **vision_msgs_env()}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=True)
    sizes, path = out.stdout.split()[:3], out.stdout.split()[3]
    assert sizes == ["8", "24", "24"]   # CDR: 4-byte encapsulation, [header,] empty sequence
    assert path.startswith(env["PYTHONPATH"].split(os.pathsep)[0])
