"""Message types of the bags: the ROS 2 Jazzy typestore plus the shipped .msg files, and CDR (de)serialisation."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gd_completion.errors import BagError, DataFormatError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

MSG_DIR = Path(__file__).resolve().parents[1] / "msg"

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DETECTION3D_ARRAY = "vision_msgs/msg/Detection3DArray"
AUTOWARE_DETECTED_OBJECTS = "autoware_perception_msgs/msg/DetectedObjects"
AUTOWARE_TRACKED_OBJECTS = "autoware_perception_msgs/msg/TrackedObjects"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

# pandar_msgs as published by the Hesai drivers (same text as the driver's msg/ folder).
PANDAR_MSGS = {
    "pandar_msgs/msg/PandarPacket": "builtin_interfaces/Time stamp\nuint8[1500] data\nuint32 size\n",
    "pandar_msgs/msg/PandarScan": "std_msgs/Header header\npandar_msgs/PandarPacket[] packets\n",
}


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
        shipped = ("vision_msgs/", "autoware_perception_msgs/")
        hint = f" (expected its definition under {MSG_DIR})" if msgtype.startswith(shipped) else ""
        raise BagError(f"message type {msgtype} is not registered{hint}")


def message_class(msgtype: str) -> Any:
    """The rosbags message class of a registered type ('sensor_msgs/msg/PointCloud2')."""
    return typestore().types[msgtype]


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
