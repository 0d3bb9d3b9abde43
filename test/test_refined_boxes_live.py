"""The node's refined boxes output (`refined_boxes_topic`): each completed vehicle's refined box, with the cloud's
header and the vehicle's id and label, as vision_msgs/Detection3DArray, or as Autoware DetectedObjects when the
boxes came in as Autoware objects."""
from __future__ import annotations

import math
import os
import sys
import threading

import numpy as np
import pytest

pytest.importorskip("rclpy")
from test_autoware_live import LIDAR, Obj, apm, autoware_msg  # noqa: E402, F401  (fixture)
from test_node_live import frames, own_node, ros_context  # noqa: E402, F401  (fixtures)

from gd_completion.pointcloud2 import read_points  # noqa: E402

pytestmark = pytest.mark.integration
SHIFT = 0.3   # metres along the heading: the boxes sent are off, the refined ones should be nearer the true ones


def shifted(frame):
    from dataclasses import replace

    return [replace(b, center=(b.center[0] + SHIFT * math.cos(b.yaw), b.center[1] + SHIFT * math.sin(b.yaw),
                               b.center[2])) for b in frame.boxes]


class Collector:
    """Messages of one topic, by header stamp."""

    def __init__(self, client, cls, topic: str) -> None:
        from rclpy.qos import QoSProfile

        self.messages: dict[int, object] = {}
        self._cond = threading.Condition()
        client.node.create_subscription(cls, topic, self._on, QoSProfile(depth=10))

    def _on(self, msg) -> None:
        with self._cond:
            self.messages[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = msg
            self._cond.notify_all()

    def wait(self, stamp: int, timeout: float = 20.0):
        with self._cond:
            self._cond.wait_for(lambda: stamp in self.messages, timeout)
            return self.messages.get(stamp)


def answered(client, frame, boxes, refined: Collector):
    """Send `frame` with `boxes` (fresh stamps: clouds go out best effort) until both outputs of one stamp arrive."""
    for _ in range(5):
        stamp = client.send(frame, boxes=boxes)
        cloud, boxes_msg = client.wait_reply(stamp, timeout=10.0), refined.wait(stamp, timeout=10.0)
        if cloud is not None and boxes_msg is not None:
            return read_points(cloud), boxes_msg
    raise AssertionError("no frame answered on both outputs")


def centre_errors(centres: dict[int, tuple[float, float, float]], frame) -> list[float]:
    truth = {b.instance_id: b.center for b in frame.boxes}
    return [math.dist(c, truth[i]) for i, c in centres.items()]


def test_refined_boxes_as_detection3d(ros_context, frames, tmp_path):  # noqa: F811
    import interfaces

    msgs = interfaces.import_vision_msgs()
    env = interfaces.vision_msgs_env({**os.environ, **ros_context[0]})
    frame = frames[4]
    with own_node(ros_context, tmp_path, "refined", params={"refined_boxes_topic": "refined_boxes"}, env=env) \
            as (node, client):
        refined = Collector(client, msgs.Detection3DArray, "refined_boxes")
        client.warm_up(frame)
        points, msg = answered(client, frame, shifted(frame), refined)
        assert msg.header.frame_id == LIDAR
        ids = {int(d.id) for d in msg.detections}
        assert ids == set(np.unique(points["instance_id"]).tolist()) == {b.instance_id for b in frame.boxes}
        assert all(d.results[0].hypothesis.class_id == "car" for d in msg.detections)
        centres = {int(d.id): (d.bbox.center.position.x, d.bbox.center.position.y, d.bbox.center.position.z)
                   for d in msg.detections}
        assert np.mean(centre_errors(centres, frame)) < SHIFT   # nearer the annotated boxes than the ones sent
        assert all(d.bbox.size.x > 2.0 and d.bbox.size.y > 1.0 for d in msg.detections)


def test_refined_boxes_as_autoware_objects(apm, ros_context, frames, tmp_path):  # noqa: F811
    import interfaces

    env = interfaces.vision_msgs_env({**os.environ, **ros_context[0]})
    frame = frames[4]
    car = apm.ObjectClassification.CAR
    with own_node(ros_context, tmp_path, "aw_refined", env=env, boxes_cls=apm.DetectedObjects,
                  params={"boxes_type": "autoware_detected", "refined_boxes_topic": "refined_objects"}) \
            as (node, client):
        client.boxes_msg = lambda boxes, stamp, frame_id: autoware_msg(apm, [Obj(b, car) for b in boxes], stamp,
                                                                       frame_id)
        refined = Collector(client, apm.DetectedObjects, "refined_objects")
        client.warm_up(frame)
        boxes = shifted(frame)
        points, msg = answered(client, frame, boxes, refined)
        assert len(msg.objects) == len(boxes) == len(np.unique(points["instance_id"]))
        assert all(o.classification[0].label == car and o.shape.type == apm.Shape.BOUNDING_BOX for o in msg.objects)
        # DetectedObjects carry no ids: the objects come in the order of the completed vehicles (array index)
        centres = {i: (o.kinematics.pose_with_covariance.pose.position.x,
                       o.kinematics.pose_with_covariance.pose.position.y,
                       o.kinematics.pose_with_covariance.pose.position.z) for i, o in enumerate(msg.objects)}
        assert np.mean(centre_errors(centres, frame)) < SHIFT


@pytest.mark.parametrize("boxes_type, package", [("marker", "vision_msgs"),
                                                  ("autoware_tracked", "autoware_perception_msgs")])
def test_refined_boxes_without_their_messages_are_a_clear_error(boxes_type, package, monkeypatch):
    from gd_completion.ros.params import ParameterError
    from gd_completion.ros.refined_boxes import refined_boxes_output

    monkeypatch.setitem(sys.modules, f"{package}.msg", None)   # not importable
    with pytest.raises(ParameterError, match=f"refined_boxes_topic: publishing {package}/msg/"):
        refined_boxes_output(boxes_type)
