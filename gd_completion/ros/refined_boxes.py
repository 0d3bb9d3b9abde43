"""The completed vehicles' refined boxes as messages a planner consumes: vision_msgs/Detection3DArray, or
autoware_perception_msgs/DetectedObjects when the boxes came in as Autoware objects."""
from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any

from gd_completion.geometry import Box3D
from gd_completion.ros.params import ParameterError
from gd_completion.rotations import yaw_quaternion

# our labels -> autoware_perception_msgs/ObjectClassification labels (Autoware has no van: a van is a car there)
AUTOWARE_CLASSES = {"car": 1, "van": 1, "truck": 2}


def _pose(pose: Any, box: Box3D) -> None:
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in box.center)
    o = pose.orientation
    o.x, o.y, o.z, o.w = yaw_quaternion(box.yaw)


def _size(vector: Any, box: Box3D) -> None:
    vector.x, vector.y, vector.z = (float(v) for v in box.size)


def detection_array(msgs: Any, boxes: Sequence[Box3D], header: Any) -> Any:
    """Detection3DArray: per box its pose and size, `id` its instance id, one hypothesis (class_id = label, score 1)."""
    out = msgs.Detection3DArray(header=header)
    for box in boxes:
        det = msgs.Detection3D(header=header, id=str(box.instance_id))
        _pose(det.bbox.center, box)
        _size(det.bbox.size, box)
        hypothesis = msgs.ObjectHypothesisWithPose()
        hypothesis.hypothesis.class_id, hypothesis.hypothesis.score = box.label, 1.0
        _pose(hypothesis.pose.pose, box)
        det.results.append(hypothesis)
        out.detections.append(det)
    return out


def detected_objects(msgs: Any, boxes: Sequence[Box3D], header: Any) -> Any:
    """DetectedObjects: per box a BOUNDING_BOX object, its pose and size, its label's classification."""
    out = msgs.DetectedObjects(header=header)
    for box in boxes:
        obj = msgs.DetectedObject(existence_probability=1.0)
        obj.classification.append(msgs.ObjectClassification(label=AUTOWARE_CLASSES.get(box.label, 0),
                                                            probability=1.0))
        _pose(obj.kinematics.pose_with_covariance.pose, box)
        obj.kinematics.orientation_availability = msgs.DetectedObjectKinematics.AVAILABLE
        obj.shape.type = msgs.Shape.BOUNDING_BOX
        _size(obj.shape.dimensions, box)
        out.objects.append(obj)
    return out


def refined_boxes_output(boxes_type: str) -> tuple[type, Callable[[Sequence[Box3D], Any], Any], str]:
    """(message class, builder of a message from boxes and a header, type name) of the refined boxes output for
    the node's `boxes_type`: Autoware in, Autoware out; else Detection3DArray (ParameterError without vision_msgs)."""
    package, name, build = (("autoware_perception_msgs", "DetectedObjects", detected_objects)
                            if boxes_type.startswith("autoware") else
                            ("vision_msgs", "Detection3DArray", detection_array))
    try:
        msgs = importlib.import_module(f"{package}.msg")
    except ImportError as exc:
        raise ParameterError(f"parameter refined_boxes_topic: publishing {package}/msg/{name} needs {package} "
                             f"importable ({exc}); install ros-<distro>-{package.replace('_', '-')} or build it "
                             "with scripts/build_interfaces.sh") from exc
    return getattr(msgs, name), lambda boxes, header: build(msgs, boxes, header), f"{package}/msg/{name}"
