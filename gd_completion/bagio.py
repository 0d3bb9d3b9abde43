"""rosbag2 helpers: type registration, atomic bag writing, PointCloud2 / box / tf message construction."""
from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gd_completion.box_messages import (
    MARKER_ADD,
    MARKER_CUBE,
    BoxSet,
    detections_to_boxes,
    markers_to_boxes,
    yaw_from_quaternion,
)
from gd_completion.errors import BagError, DataFormatError
from gd_completion.geometry import Box3D
from gd_completion.stamp_sync import stamp_to_ns

if TYPE_CHECKING:
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.typesys.store import Typestore

    from gd_completion.pointcloud2 import CloudLayout

MSG_DIR = Path(__file__).resolve().parent / "msg"
STORAGES = ("mcap", "sqlite3")
BAG_VERSION = 9

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DETECTION3D_ARRAY = "vision_msgs/msg/Detection3DArray"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

# pandar_msgs as published by the Hesai drivers (same text as the driver's msg/ folder).
PANDAR_MSGS = {
    "pandar_msgs/msg/PandarPacket": "builtin_interfaces/Time stamp\nuint8[1500] data\nuint32 size\n",
    "pandar_msgs/msg/PandarScan": "std_msgs/Header header\npandar_msgs/PandarPacket[] packets\n",
}

MARKER_DELETEALL = 3


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """ROS 2 Jazzy typestore plus the .msg types shipped in `gd_completion/msg/<package>/` and pandar_msgs."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in PANDAR_MSGS.items():
        types.update(get_types_from_msg(text, name))
    if MSG_DIR.is_dir():
        for path in sorted(MSG_DIR.glob("*/*.msg")) + sorted(MSG_DIR.glob("*/msg/*.msg")):
            package = path.parent.name if path.parent.name != "msg" else path.parent.parent.name
            try:
                types.update(get_types_from_msg(path.read_text(), f"{package}/msg/{path.stem}"))
            except Exception as error:  # rosbags raises several parser errors
                raise DataFormatError(f"{path}: cannot parse message definition: {error}") from error
    store.register(types)
    return store


def require_type(msgtype: str) -> None:
    """Raise BagError when `msgtype` is not registered (e.g. vision_msgs .msg files missing)."""
    if msgtype not in typestore().types:
        hint = f" (expected its definition under {MSG_DIR})" if msgtype.startswith("vision_msgs/") else ""
        raise BagError(f"message type {msgtype} is not registered{hint}")


def storage_plugin(storage: str):
    """rosbags StoragePlugin for 'mcap' or 'sqlite3'."""
    from rosbags.rosbag2 import StoragePlugin

    try:
        return {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    except KeyError:
        raise BagError(f"unknown storage {storage!r}; expected one of {', '.join(STORAGES)}") from None


@contextmanager
def atomic_bag_writer(path: str | Path, *, storage: str = "mcap", overwrite: bool = False) -> Iterator[Writer]:
    """Open a rosbag2 writer under a temporary name beside `path`; rename to `path` only on success.

    On any exception the temporary bag is deleted and nothing appears under `path`.
    """
    from rosbags.rosbag2 import Writer, WriterError

    final = Path(path)
    if final.exists() and not overwrite:
        raise BagError(f"{final}: output exists already (use --overwrite to replace it)")
    parent = final.parent if str(final.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=parent))
    tmp_bag = scratch / final.name
    writer = Writer(tmp_bag, version=BAG_VERSION, storage_plugin=storage_plugin(storage))
    try:
        writer.open()
        yield writer
        writer.close()
        # rosbags names the storage file after the directory; keep that name (same stem as the final bag).
        if final.exists():
            shutil.rmtree(final) if final.is_dir() else final.unlink()
        os.replace(tmp_bag, final)
    except BaseException as error:
        try:
            writer.abort()
        except Exception:
            pass
        if isinstance(error, WriterError):
            raise BagError(f"{final}: cannot write bag: {error}") from error
        raise
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


@contextmanager
def open_bag(path: str | Path) -> Iterator[Reader]:
    """Open a rosbag2 (directory, .mcap or .db3) for reading; problems raise BagError naming the file."""
    from rosbags.rosbag2 import Reader

    bag = Path(path)
    if not bag.exists():
        raise BagError(f"{bag}: no such bag")
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as error:
        raise BagError(f"{bag}: cannot open bag: {error}") from error
    try:
        yield reader
    finally:
        try:
            reader.close()
        except Exception:
            pass


def iter_raw(reader: Reader, connections=None) -> Iterator[tuple[Any, int, bytes]]:
    """Messages as (connection, bag timestamp ns, raw serialized bytes); corrupt storage raises BagError."""
    try:
        yield from reader.messages(connections=connections or ())
    except BagError:
        raise
    except Exception as error:
        raise BagError(f"{reader.path}: cannot read messages (truncated or corrupt bag?): {error}") from error


def deserialize(raw: bytes, msgtype: str, source: str = "bag") -> Any:
    """CDR bytes -> rosbags message object; BagError for unknown types or corrupt data."""
    require_type(msgtype)
    try:
        return typestore().deserialize_cdr(raw, msgtype)
    except Exception as error:
        raise BagError(f"{source}: cannot deserialize {msgtype}: {error}") from error


def serialize(msg: Any, msgtype: str) -> bytes:
    """rosbags message object -> CDR bytes."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def add_connection(writer: Writer, topic: str, msgtype: str, *, latched: bool = False):
    """Register `topic` with the definition from the typestore (transient-local QoS when latched)."""
    require_type(msgtype)
    qos = (latched_qos(),) if latched else ()
    return writer.add_connection(topic, msgtype, typestore=typestore(), offered_qos_profiles=qos)


def latched_qos() -> Any:
    """Reliable, transient-local, keep-last-1 QoS (what /tf_static publishers offer)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL, deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


# --- message construction -------------------------------------------------------------------------------

def _msg(name: str) -> Any:
    return typestore().types[name]


def stamp(ns: int) -> Any:
    """builtin_interfaces/Time from integer nanoseconds."""
    return _msg("builtin_interfaces/msg/Time")(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


stamp_ns = stamp_to_ns  # integer nanoseconds of a builtin_interfaces/Time


def header(frame_id: str, ns: int) -> Any:
    """std_msgs/Header."""
    return _msg("std_msgs/msg/Header")(stamp=stamp(ns), frame_id=frame_id)


def pointcloud2_msg(layout: CloudLayout, frame_id: str, ns: int) -> Any:
    """sensor_msgs/PointCloud2 (rosbags object) from a CloudLayout (little-endian)."""
    point_field = _msg("sensor_msgs/msg/PointField")
    data = np.ascontiguousarray(np.asarray(layout.data, dtype=np.uint8).reshape(-1))
    width, height = int(getattr(layout, "width", 0)), int(getattr(layout, "height", 1))
    step = int(layout.point_step)
    if step <= 0 or data.size != width * height * step:
        raise BagError(f"PointCloud2 for {frame_id}: {data.size} data bytes do not match "
                       f"{width}x{height} points of {step} bytes")
    fields = [point_field(name=f.name, offset=int(f.offset), datatype=int(f.datatype), count=int(f.count))
              for f in layout.fields]
    return _msg(POINTCLOUD2)(header=header(frame_id, ns), height=height, width=width, fields=fields,
                             is_bigendian=False, point_step=step, row_step=step * width, data=data,
                             is_dense=bool(getattr(layout, "is_dense", False)))


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by `yaw` about +z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


quaternion_yaw = yaw_from_quaternion  # heading (rotation about +z) of a quaternion


def _pose(box: Box3D) -> Any:
    qx, qy, qz, qw = yaw_quaternion(float(box.yaw))
    cx, cy, cz = (float(v) for v in box.center)
    return _msg("geometry_msgs/msg/Pose")(
        position=_msg("geometry_msgs/msg/Point")(x=cx, y=cy, z=cz),
        orientation=_msg("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
    )


def _vector3(values: Sequence[float]) -> Any:
    return _msg("geometry_msgs/msg/Vector3")(x=float(values[0]), y=float(values[1]), z=float(values[2]))


def detection3d_array_msg(boxes: Sequence[Box3D], frame_id: str, ns: int, *,
                          ids: Sequence[str] | None = None, score: float = 1.0) -> Any:
    """vision_msgs/Detection3DArray: one detection per box (class_id = label, id = track id string)."""
    require_type(DETECTION3D_ARRAY)
    hdr = header(frame_id, ns)
    detections = []
    for k, box in enumerate(boxes):
        hypothesis = _msg("vision_msgs/msg/ObjectHypothesisWithPose")(
            hypothesis=_msg("vision_msgs/msg/ObjectHypothesis")(class_id=box.label, score=float(score)),
            pose=_msg("geometry_msgs/msg/PoseWithCovariance")(pose=_pose(box), covariance=np.zeros(36, np.float64)),
        )
        bbox = _msg("vision_msgs/msg/BoundingBox3D")(center=_pose(box), size=_vector3(box.size))
        det_id = ids[k] if ids is not None else str(box.instance_id)
        detections.append(_msg("vision_msgs/msg/Detection3D")(header=hdr, results=[hypothesis], bbox=bbox, id=det_id))
    return _msg(DETECTION3D_ARRAY)(header=hdr, detections=detections)


LABEL_COLOURS = {"car": (0.1, 0.6, 1.0), "van": (0.2, 0.9, 0.4), "truck": (1.0, 0.6, 0.1)}


def marker_array_msg(boxes: Sequence[Box3D], frame_id: str, ns: int, *,
                     texts: Sequence[str] | None = None, delete_all: bool = True) -> Any:
    """visualization_msgs/MarkerArray of CUBE markers (ns = label, id = instance id, scale = l, w, h).

    With `delete_all` a leading DELETEALL marker clears the previous frame's boxes in RViz/Foxglove.
    """
    marker = _msg("visualization_msgs/msg/Marker")
    duration = _msg("builtin_interfaces/msg/Duration")
    colour = _msg("std_msgs/msg/ColorRGBA")
    hdr = header(frame_id, ns)
    empty = dict(points=[], colors=[], texture_resource="", texture=_msg("sensor_msgs/msg/CompressedImage")(
        header=header("", 0), format="", data=np.zeros(0, np.uint8)), uv_coordinates=[],
        mesh_file=_msg("visualization_msgs/msg/MeshFile")(filename="", data=np.zeros(0, np.uint8)),
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
    return _msg(MARKER_ARRAY)(markers=markers)


def tf_static_msg(transforms: Sequence[tuple[str, str, np.ndarray]], ns: int) -> Any:
    """tf2_msgs/TFMessage from (parent, child, 4x4 child-to-parent matrix) triples."""
    stamped = []
    for parent, child, matrix in transforms:
        m = np.asarray(matrix, dtype=np.float64)
        qx, qy, qz, qw = rotation_quaternion(m[:3, :3])
        stamped.append(_msg("geometry_msgs/msg/TransformStamped")(
            header=header(parent, ns), child_frame_id=child,
            transform=_msg("geometry_msgs/msg/Transform")(
                translation=_vector3(m[:3, 3]),
                rotation=_msg("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw))))
    return _msg(TF_MESSAGE)(transforms=stamped)


def rotation_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix (orthonormalised first)."""
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=np.float64))
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    trace = np.trace(r)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0, 0.0, 0.0]
        q[i] = 0.25 * s
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
        w = (r[k, j] - r[j, k]) / s
        x, y, z = q
    return float(x), float(y), float(z), float(w)


# --- boxes back from messages ---------------------------------------------------------------------------

def boxes_from_detections(msg: Any) -> list[Box3D]:
    """Box3D list from a Detection3DArray (see `gd_completion.box_messages.detections_to_boxes`)."""
    return list(detections_to_boxes(msg).boxes)


def boxes_from_markers(msg: Any) -> list[Box3D]:
    """Box3D list from the ADD CUBE markers of a MarkerArray (see `gd_completion.box_messages`)."""
    return list(markers_to_boxes(msg).boxes)


def box_set_from_message(msg: Any, msgtype: str) -> BoxSet:
    """The BoxSet (stamp, boxes, per-box frame) of a Detection3DArray or MarkerArray message, as the node reads it."""
    if msgtype == DETECTION3D_ARRAY:
        return detections_to_boxes(msg)
    if msgtype == MARKER_ARRAY:
        return markers_to_boxes(msg)
    raise BagError(f"boxes topic has type {msgtype}; expected {DETECTION3D_ARRAY} or {MARKER_ARRAY}")


def boxes_from_message(msg: Any, msgtype: str) -> list[Box3D]:
    """Boxes from a Detection3DArray or MarkerArray message."""
    return list(box_set_from_message(msg, msgtype).boxes)
