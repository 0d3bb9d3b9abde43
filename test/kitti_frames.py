"""Test helper: KITTI object frames (points + Car/Van/Truck boxes in the lidar frame) and their ROS messages."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.geometry import Box3D
from gd_completion.pointcloud2 import xyz_array_to_structured

VEHICLE_TYPES = {"Car": "car", "Van": "van", "Truck": "truck"}


@dataclass(frozen=True)
class KittiFrame:
    """One frame: (N, 4) float32 x, y, z, reflectance in the lidar frame, and its vehicle boxes (lidar frame)."""

    index: str
    points: np.ndarray
    boxes: list[Box3D]


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """`key: numbers` lines -> arrays (R0_rect 3x3, Tr_velo_to_cam 3x4, P0..P3 3x4)."""
    out = {}
    for line in path.read_text().splitlines():
        key, sep, rest = line.partition(":")
        if sep and rest.strip():
            out[key.strip()] = np.array(rest.split(), dtype=np.float64)
    return out


def _homogeneous(m: np.ndarray, rows: int, cols: int) -> np.ndarray:
    h = np.eye(4)
    h[:rows, :cols] = m.reshape(rows, cols)
    return h


def cam_to_velo_matrix(calib: dict[str, np.ndarray]) -> np.ndarray:
    """4x4 transform from rectified camera coordinates to the lidar frame."""
    velo_to_rect = _homogeneous(calib["R0_rect"], 3, 3) @ _homogeneous(calib["Tr_velo_to_cam"], 3, 4)
    return np.linalg.inv(velo_to_rect)


def read_boxes(label_path: Path, calib: dict[str, np.ndarray]) -> list[Box3D]:
    """Car/Van/Truck rows of a label_2 file as lidar-frame boxes; instance_id = row number in the file."""
    cam_to_velo = cam_to_velo_matrix(calib)
    boxes = []
    for row, line in enumerate(label_path.read_text().splitlines()):
        f = line.split()
        if not f or f[0] not in VEHICLE_TYPES:
            continue
        h, w, l, x, y, z, ry = (float(v) for v in f[8:15])
        # KITTI's location is the bottom centre in camera coordinates (y down): the box centre is h/2 above.
        centre = cam_to_velo @ np.array([x, y - h / 2.0, z, 1.0])
        yaw = math.remainder(-ry - math.pi / 2.0, 2.0 * math.pi)
        boxes.append(Box3D(tuple(centre[:3]), (l, w, h), yaw, VEHICLE_TYPES[f[0]], row))
    return boxes


def read_frame(training: Path, index: str) -> KittiFrame:
    """Frame `index` ("000001") of a KITTI `training` folder."""
    points = np.fromfile(training / "velodyne" / f"{index}.bin", dtype=np.float32).reshape(-1, 4)
    calib = read_calib(training / "calib" / f"{index}.txt")
    return KittiFrame(index, points, read_boxes(training / "label_2" / f"{index}.txt", calib))


# -- ROS messages (rclpy message classes are imported lazily: the reader itself needs no ROS) ----------

def ros_time(stamp_ns: int):
    from builtin_interfaces.msg import Time
    return Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def cloud_msg(points: np.ndarray, stamp_ns: int, frame_id: str = "velodyne"):
    """PointCloud2 with x, y, z (and intensity when `points` has 4 columns), float32."""
    from std_msgs.msg import Header

    from gd_completion.ros.cloud_messages import structured_to_msg

    extra = {"intensity": points[:, 3].astype(np.float32)} if points.shape[1] > 3 else {}
    array = xyz_array_to_structured(points[:, :3].astype(np.float32), **extra)
    return structured_to_msg(array, Header(stamp=ros_time(stamp_ns), frame_id=frame_id),
                             is_dense=bool(np.isfinite(points[:, :3]).all()))


def _quaternion(yaw: float):
    from geometry_msgs.msg import Quaternion
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def marker_array(boxes: list[Box3D], stamp_ns: int, frame_id: str = "velodyne", class_names: bool = True):
    """CUBE markers (ns = KITTI class name) after a DELETEALL marker that carries the header."""
    from visualization_msgs.msg import Marker, MarkerArray

    header_marker = Marker(action=Marker.DELETEALL)
    header_marker.header.stamp, header_marker.header.frame_id = ros_time(stamp_ns), frame_id
    markers = [header_marker]
    for b in boxes:
        m = Marker(ns=b.label.capitalize() if class_names else b.label, id=b.instance_id, type=Marker.CUBE,
                   action=Marker.ADD)
        m.header = header_marker.header
        m.pose.position.x, m.pose.position.y, m.pose.position.z = b.center
        m.pose.orientation = _quaternion(b.yaw)
        m.scale.x, m.scale.y, m.scale.z = b.size
        markers.append(m)
    return MarkerArray(markers=markers)


def detection_array(boxes: list[Box3D], stamp_ns: int, frame_id: str = "velodyne"):
    """vision_msgs/Detection3DArray (needs the bindings importable), class ids 1/2/3, id = instance id."""
    from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose

    ids = {"car": "1", "van": "2", "truck": "3"}
    msg = Detection3DArray()
    msg.header.stamp, msg.header.frame_id = ros_time(stamp_ns), frame_id
    for b in boxes:
        d = Detection3D(id=str(b.instance_id))
        d.header = msg.header
        d.bbox.center.position.x, d.bbox.center.position.y, d.bbox.center.position.z = b.center
        d.bbox.center.orientation = _quaternion(b.yaw)
        d.bbox.size.x, d.bbox.size.y, d.bbox.size.z = b.size
        h = ObjectHypothesisWithPose()
        h.hypothesis.class_id, h.hypothesis.score = ids.get(b.label, b.label), 0.9
        d.results.append(h)
        msg.detections.append(d)
    return msg
