"""Detector classes -> the labels completed: named presets for common detectors, and the user's own entries.

Names are unambiguous across detectors, so the default preset `names` takes the class names of KITTI, nuScenes
and Autoware at once. Numeric ids are not: OpenPCDet's KITTI models number 1 Car, 2 Pedestrian, 3 Cyclist, other
detectors otherwise, so a numeric id is mapped only by a preset that says so (`openpcdet_kitti`) or by an explicit
`class_map` entry; an unmapped numeric id is never guessed (the box is skipped and counted).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping

from gd_completion.errors import BoxError

IGNORE = "ignore"   # a class_map label that drops the box (not counted as a vehicle label)

KITTI = {"Car": "car", "Van": "van", "Truck": "truck", "Pedestrian": IGNORE, "Person_sitting": IGNORE,
         "Cyclist": IGNORE, "Tram": IGNORE, "Misc": IGNORE, "DontCare": IGNORE}
NUSCENES = {"car": "car", "truck": "truck", "bus": "truck", "trailer": "truck", "construction_vehicle": "truck",
            "pedestrian": IGNORE, "motorcycle": IGNORE, "bicycle": IGNORE, "traffic_cone": IGNORE, "barrier": IGNORE,
            "vehicle.car": "car", "vehicle.truck": "truck", "vehicle.bus.bendy": "truck", "vehicle.bus.rigid": "truck",
            "vehicle.trailer": "truck", "vehicle.construction": "truck", "vehicle.emergency.ambulance": "van",
            "vehicle.emergency.police": "car"}
# autoware_perception_msgs/ObjectClassification labels, by the names `autoware_messages` gives them
AUTOWARE = {"car": "car", "truck": "truck", "bus": "truck", "trailer": "truck", "motorcycle": IGNORE,
            "bicycle": IGNORE, "pedestrian": IGNORE, "unknown": IGNORE}
OPENPCDET_KITTI = {"1": "car", "2": IGNORE, "3": IGNORE, **KITTI}

CLASS_PRESETS: dict[str, dict[str, str]] = {
    "names": {**AUTOWARE, **NUSCENES, **KITTI},
    "kitti": KITTI,
    "nuscenes": NUSCENES,
    "autoware": AUTOWARE,
    "openpcdet_kitti": OPENPCDET_KITTI,
}
DEFAULT_PRESET = "names"


def parse_class_map(entries: Iterable[str]) -> dict[str, str]:
    """["1:car", "Car:car", "Pedestrian:ignore"] -> {"1": "car", "Car": "car", "Pedestrian": "ignore"}; blank entries
    are skipped (`[""]` is how a ROS parameter says "no entries": an empty list has no type)."""
    table: dict[str, str] = {}
    for entry in entries:
        if not str(entry).strip():
            continue
        key, sep, label = str(entry).rpartition(":")
        key, label = key.strip(), label.strip().lower()
        if not sep or not key or not label:
            raise BoxError(f"class_map entry {entry!r} is not of the form 'class_id:label'")
        table[key] = label
    return table


def class_table(preset: str, entries: Iterable[str] = ()) -> dict[str, str]:
    """The preset's table with the user's `class_map` entries on top; BoxError for an unknown preset."""
    if preset not in CLASS_PRESETS:
        raise BoxError(f"class preset {preset!r} is not one of {sorted(CLASS_PRESETS)}")
    return {**CLASS_PRESETS[preset], **parse_class_map(entries)}


def is_numeric_id(raw: str) -> bool:
    """True for a class given as an integer ("3", "-1"): its meaning depends on the detector."""
    text = raw.strip().lstrip("+-")
    return text.isdigit()


UNMAPPED = "unmapped:"   # label prefix of a box whose numeric class id no map names ("unmapped:3")


def map_label(raw: str, class_map: Mapping[str, str]) -> str:
    """Detector class name/id -> our label: the class_map entry; else a name in lower case; else (a numeric id
    nothing maps) `UNMAPPED` + the id, which no vehicle label matches."""
    raw = str(raw).strip()
    if raw in class_map:
        return class_map[raw]
    return f"{UNMAPPED}{raw}" if is_numeric_id(raw) else raw.lower()


def unmapped_ids(labels: Iterable[str]) -> list[str]:
    """The numeric class ids among box labels that no map named, sorted, each once."""
    return sorted({label.removeprefix(UNMAPPED) for label in labels if label.startswith(UNMAPPED)})
