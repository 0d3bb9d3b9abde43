"""rosbags message objects built from the core's data: stamps, headers, PointCloud2, boxes, /tf_static."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from gd_completion.bags.typestore import (
    DETECTION3D_ARRAY,
    MARKER_ARRAY,
    POINTCLOUD2,
    TF_MESSAGE,
    message_class,
    require_type,
)
from gd_completion.box_messages import MARKER_ADD, MARKER_CUBE
from gd_completion.errors import BagError
from gd_completion.geometry import Box3D
from gd_completion.rotations import rotation_quaternion, yaw_quaternion

if TYPE_CHECKING:
    from gd_completion.pointcloud2 import CloudLayout

MARKER_DELETEALL = 3
LABEL_COLOURS = {"car": (0.1, 0.6, 1.0), "van": (0.2, 0.9, 0.4), "truck": (1.0, 0.6, 0.1)}


def stamp(ns: int) -> Any:
    """builtin_interfaces/Time from integer nanoseconds."""
    return message_class("builtin_interfaces/msg/Time")(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def header(frame_id: str, ns: int) -> Any:
    """std_msgs/Header."""
    return message_class("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=frame_id)


def pointcloud2_msg(layout: CloudLayout, frame_id: str, ns: int) -> Any:
    """sensor_msgs/PointCloud2 (rosbags object) from a CloudLayout (little-endian)."""
    point_field = message_class("sensor_msgs/msg/PointField")
    data = np.ascontiguousarray(np.asarray(layout.data, dtype=np.uint8).reshape(-1))
    width, height, step = int(layout.width), int(layout.height), int(layout.point_step)
    if step <= 0 or data.size != width * height * step:
        raise BagError(f"PointCloud2 for {frame_id}: {data.size} data bytes do not match "
                       f"{width}x{height} points of {step} bytes")
    fields = [point_field(name=f.name, offset=int(f.offset), datatype=int(f.datatype), count=int(f.count))
              for f in layout.fields]
    return message_class(POINTCLOUD2)(header=header(frame_id, ns), height=height, width=width, fields=fields,
                                      is_bigendian=False, point_step=step, row_step=step * width, data=data,
                                      is_dense=bool(layout.is_dense))


def _pose(box: Box3D) -> Any:
    qx, qy, qz, qw = yaw_quaternion(float(box.yaw))
    cx, cy, cz = (float(v) for v in box.center)
    return message_class("geometry_msgs/msg/Pose")(
        position=message_class("geometry_msgs/msg/Point")(x=cx, y=cy, z=cz),
        orientation=message_class("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
    )


def _vector3(values: Sequence[float] | np.ndarray) -> Any:
    return message_class("geometry_msgs/msg/Vector3")(x=float(values[0]), y=float(values[1]), z=float(values[2]))


def detection3d_array_msg(boxes: Sequence[Box3D], frame_id: str, ns: int, *,
                          ids: Sequence[str] | None = None, score: float = 1.0) -> Any:
    """vision_msgs/Detection3DArray: one detection per box (class_id = label, id = track id string)."""
    require_type(DETECTION3D_ARRAY)
    hdr = header(frame_id, ns)
    detections = []
    for k, box in enumerate(boxes):
        hypothesis = message_class("vision_msgs/msg/ObjectHypothesisWithPose")(
            hypothesis=message_class("vision_msgs/msg/ObjectHypothesis")(class_id=box.label, score=float(score)),
            pose=message_class("geometry_msgs/msg/PoseWithCovariance")(pose=_pose(box),
                                                                       covariance=np.zeros(36, np.float64)),
        )
        bbox = message_class("vision_msgs/msg/BoundingBox3D")(center=_pose(box), size=_vector3(box.size))
        det_id = ids[k] if ids is not None else str(box.instance_id)
        detections.append(message_class("vision_msgs/msg/Detection3D")(header=hdr, results=[hypothesis], bbox=bbox,
                                                                       id=det_id))
    return message_class(DETECTION3D_ARRAY)(header=hdr, detections=detections)


def marker_array_msg(boxes: Sequence[Box3D], frame_id: str, ns: int, *,
                     texts: Sequence[str] | None = None, delete_all: bool = True) -> Any:
    """visualization_msgs/MarkerArray of CUBE markers (ns = label, id = instance id, scale = l, w, h).

    With `delete_all` a leading DELETEALL marker clears the previous frame's boxes in RViz/Foxglove.
    """
    marker = message_class("visualization_msgs/msg/Marker")
    duration = message_class("builtin_interfaces/msg/Duration")
    colour = message_class("std_msgs/msg/ColorRGBA")
    hdr = header(frame_id, ns)
    empty = dict(points=[], colors=[], texture_resource="", texture=message_class("sensor_msgs/msg/CompressedImage")(
        header=header("", 0), format="", data=np.zeros(0, np.uint8)), uv_coordinates=[],
        mesh_file=message_class("visualization_msgs/msg/MeshFile")(filename="", data=np.zeros(0, np.uint8)),
        mesh_resource="", mesh_use_embedded_materials=False, frame_locked=False, lifetime=duration(sec=0, nanosec=0))
    markers = []
    if delete_all:
        markers.append(marker(header=hdr, ns="", id=0, type=0, action=MARKER_DELETEALL, pose=_pose(
            Box3D((0, 0, 0), (1, 1, 1), 0.0, "", 0)), scale=_vector3((1, 1, 1)), color=colour(r=0, g=0, b=0, a=0),
            text="", **empty))
    for k, box in enumerate(boxes):
        r, g, b = LABEL_COLOURS.get(box.label, (0.7, 0.7, 0.7))
        markers.append(marker(header=hdr, ns=box.label, id=int(box.instance_id), type=MARKER_CUBE, action=MARKER_ADD,
                              pose=_pose(box), scale=_vector3(box.size), color=colour(r=r, g=g, b=b, a=0.35),
                              text=texts[k] if texts is not None else box.label, **empty))
    return message_class(MARKER_ARRAY)(markers=markers)


def tf_static_msg(transforms: Sequence[tuple[str, str, np.ndarray]], ns: int) -> Any:
    """tf2_msgs/TFMessage from (parent, child, 4x4 child-to-parent matrix) triples."""
    stamped = []
    for parent, child, matrix in transforms:
        m = np.asarray(matrix, dtype=np.float64)
        qx, qy, qz, qw = rotation_quaternion(m[:3, :3])
        stamped.append(message_class("geometry_msgs/msg/TransformStamped")(
            header=header(parent, ns), child_frame_id=child,
            transform=message_class("geometry_msgs/msg/Transform")(
                translation=_vector3(m[:3, 3]),
                rotation=message_class("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw))))
    return message_class(TF_MESSAGE)(transforms=stamped)
