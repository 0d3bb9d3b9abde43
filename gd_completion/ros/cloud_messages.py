"""CloudLayout / structured numpy arrays <-> sensor_msgs/PointCloud2 (rclpy messages)."""
from __future__ import annotations

import array
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from gd_completion.pointcloud2 import CloudLayout, write_points


def layout_to_msg(layout: CloudLayout, header: Any) -> PointCloud2:
    """A PointCloud2 carrying `layout` under `header` (one copy of the bytes, no per-byte checks)."""
    data = array.array("B")
    data.frombytes(memoryview(np.ascontiguousarray(layout.data, dtype=np.uint8)))
    return PointCloud2(
        header=header,
        height=int(layout.height),
        width=int(layout.width),
        fields=[PointField(name=f.name, offset=int(f.offset), datatype=int(f.datatype), count=int(f.count))
                for f in layout.fields],
        is_bigendian=bool(layout.is_bigendian),
        point_step=int(layout.point_step),
        row_step=int(layout.row_step),
        data=data,
        is_dense=bool(layout.is_dense),
    )


def structured_to_msg(points: np.ndarray, header: Any, *, is_dense: bool = True) -> PointCloud2:
    """Encode a structured array (e.g. `completion_to_structured` output) as a PointCloud2."""
    layout = write_points(points)
    layout.is_dense = is_dense
    return layout_to_msg(layout, header)
