"""Parameters of the completer node: declarations with descriptions and ranges, read and validated once."""
from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from gd_completion.association import TRACK_ID_MODES, AssociationSettings
from gd_completion.box_messages import parse_class_map
from gd_completion.errors import BoxError, GDCompletionError
from gd_completion.fusion import FusionLimits
from gd_completion.labels import LABEL_IDS
from gd_completion.limits import FrameLimits
from gd_completion.reuse import ReuseSettings
from gd_completion.stamp_sync import FRESH_FRAME_AGE_S, SYNC_MAX_WAIT_S, SYNC_QUEUE_SIZE, SYNC_TOLERANCE_S

BOXES_TYPES = ("auto", "detection3d", "marker")


class ParameterError(GDCompletionError):
    """A completer parameter with an unusable value."""


@dataclass(frozen=True)
class CompleterParams:
    """Validated parameter values of one completer node."""

    cloud_topic: str
    boxes_topic: str
    output_topic: str
    boxes_type: str
    model_path: str
    device: str
    num_threads: int
    num_input_points: int
    num_output_points: int
    min_points: int
    crop_margin: float
    labels: tuple[str, ...]
    class_map: dict[str, str]
    sync_tolerance: float
    sync_max_wait: float
    queue_size: int
    fresh_frame_age: float
    include_input_points: bool
    measured_merge: bool
    limits: FrameLimits
    track_fusion: bool
    publish_fused_points: bool
    fusion_max_tracks: int
    fusion_max_points: int
    fusion_expiry: float
    fusion_align: bool
    track_ids: str
    association_max_distance: float
    reuse: ReuseSettings | None
    max_boxes_per_message: int


def _int(lo: int, hi: int) -> dict[str, Any]:
    return {"integer_range": [IntegerRange(from_value=lo, to_value=hi, step=1)]}


def _float(lo: float, hi: float) -> dict[str, Any]:
    return {"floating_point_range": [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]}


_LIMITS = FrameLimits()
_FUSION = FusionLimits()
_REUSE = ReuseSettings()
_ASSOCIATION = AssociationSettings()
# The node's frame budget of network work when reusing completions (offline: none, so output never depends on load).
COMPLETION_BUDGET_S = 0.03
# name -> (default, description, range keyword arguments of ParameterDescriptor)
PARAMETERS: dict[str, tuple[Any, str, dict[str, Any]]] = {
    "cloud_topic": ("points", "Input sensor_msgs/PointCloud2 topic (sensor-data QoS).", {}),
    "boxes_topic": ("detections", "Input 3D boxes topic (vision_msgs/Detection3DArray or "
                                  "visualization_msgs/MarkerArray).", {}),
    "output_topic": ("completed_vehicles", "Output PointCloud2: x, y, z, instance_id, label, generated; "
                                           "input header.", {}),
    "boxes_type": ("auto", "Boxes message type: auto (Detection3DArray when vision_msgs is installed, else "
                           "MarkerArray), detection3d or marker.", {}),
    "model_path": ("", "GGD-Net checkpoint (.pt); empty = the weights shipped with the package.", {}),
    "device": ("cpu", "Torch device: cpu, cuda or cuda:N.", {}),
    "num_threads": (0, "CPU threads completing a frame's vehicles in parallel, one torch thread each; "
                       "0 = 1 with reuse (a frame's network work is small: a second thread only contends with the "
                       "node's other threads), else one per core.", _int(0, 256)),
    "num_input_points": (0, "Points per vehicle fed to the network; must match the checkpoint (0 = take it "
                            "from the checkpoint).", _int(0, 65536)),
    "num_output_points": (0, "Points the network generates per vehicle; must match the checkpoint (0 = take it "
                             "from the checkpoint).", _int(0, 65536)),
    "min_points": (0, "Vehicles with fewer measured points above the ground in their box are skipped; 0 = the "
                      "checkpoint's preprocessing (20 for the shipped weights).", _int(0, 1000000)),
    "crop_margin": (-1.0, "Metres added to each side of a box when cropping its points; -1 = the checkpoint's "
                          "preprocessing (0.1 for the shipped weights).", _float(-1.0, 5.0)),
    "labels": (["car", "van", "truck"], f"Labels to complete (of {sorted(LABEL_IDS)}).", {}),
    "class_map": (["1:car", "2:van", "3:truck", "Car:car", "Van:van", "Truck:truck",
                   "Pedestrian:ignore", "Cyclist:ignore"],
                  "Detector class id or name -> label, as 'id:label' strings; unmapped names are lower-cased; "
                  "'ignore' drops the box.", {}),
    "sync_tolerance": (SYNC_TOLERANCE_S, "Largest stamp difference (s) between a cloud and its boxes.",
                       _float(0.0, 10.0)),
    "sync_max_wait": (SYNC_MAX_WAIT_S, "Seconds a cloud (or boxes message) waits for its partner before it is dropped.",
                      _float(0.01, 60.0)),
    "queue_size": (SYNC_QUEUE_SIZE, "Clouds and boxes messages buffered per stream while waiting for their partner.",
                   _int(1, 1000)),
    "fresh_frame_age": (FRESH_FRAME_AGE_S, "Seconds; when the node is slower than its input, a paired frame that "
                                           "has waited longer than this for the worker is held back for the next "
                                           "frame if that is due within this time too, and replaced by it "
                                           "(drop_stale); else it is completed as is. Lower latency; may answer "
                                           "fewer frames. 0 = complete the newest pending frame whatever its age.",
                        _float(0.0, 10.0)),
    "include_input_points": (True, "Also publish the measured points of each completed vehicle (generated=0); "
                                   "without them, a merged completion's own measured points still carry "
                                   "generated=0.", {}),
    "measured_merge": (True, "Thin each completion together with the measured points fed to the network (a track's "
                             "fused partial: one point per 2 % voxel) and their mirror image (measured points "
                             "replace network points where they lie densely).", {}),
    # per-frame work limits (gd_completion.limits.FrameLimits); every skip is a counter in /diagnostics
    "max_boxes": (_LIMITS.max_boxes, "Boxes completed per frame at most, nearest first; the rest are skipped "
                                     "(too_many_boxes).", _int(1, 100000)),
    "max_box_length": (_LIMITS.max_box_length, "Metres; longer boxes are not vehicles and are skipped "
                                               "(implausible_box).", _float(1.0, 1000.0)),
    "max_box_width": (_LIMITS.max_box_width, "Metres; wider boxes are skipped (implausible_box).", _float(0.5, 1000.0)),
    "max_box_height": (_LIMITS.max_box_height, "Metres; taller boxes are skipped (implausible_box).",
                       _float(0.5, 1000.0)),
    "min_box_length": (_LIMITS.min_box_length, "Metres; shorter boxes are skipped (implausible_box).",
                       _float(0.01, 100.0)),
    "duplicate_distance": (_LIMITS.duplicate_distance, "Metres; a box whose centre is this close to a nearer kept "
                                                       "box is a duplicate, skipped (duplicate_box).",
                           _float(0.001, 10.0)),
    "max_points_per_vehicle": (_LIMITS.max_points_per_vehicle, "A box holding more points is skipped "
                                                               "(too_many_points).", _int(1, 100000000)),
    "max_output_points": (_LIMITS.max_output_points, "Points published per frame at most, whole vehicles nearest "
                                                     "first; the rest are skipped (output_limit).",
                          _int(1, 1000000000)),
    "time_budget": (_LIMITS.time_budget_s, "Seconds of completion per frame; vehicles not started by then are "
                                           "skipped (time_budget), nearest first.", _float(0.01, 3600.0)),
    # track fusion (gd_completion.fusion): complete each tracked vehicle (box id = track id) from all its frames
    "track_fusion": (False, "Complete each tracked vehicle (track ids: track_ids) from its points of all frames "
                            "so far, in its box frame.", {}),
    "publish_fused_points": (False, "With track_fusion, publish a vehicle's fused measured points (generated=0) "
                                    "instead of the frame's own.", {}),
    "fusion_max_tracks": (_FUSION.max_tracks, "Tracks kept at most; the least recently seen is dropped beyond it.",
                          _int(1, 100000)),
    "fusion_max_points": (_FUSION.max_points_per_track, "Fused points kept per track at most (oldest frames "
                                                        "dropped first).", _int(100, 10000000)),
    "fusion_expiry": (_FUSION.expiry_s, "Seconds (stamp time) after which a track not seen is dropped.",
                      _float(0.05, 3600.0)),
    "fusion_align": (True, "Align each new frame of a track to its fused points (x, y, yaw; bounded ICP) against "
                           "box jitter; false stores it as its box places it.", {}),
    # track identity (gd_completion.association) and completion reuse (gd_completion.reuse)
    "track_ids": ("associate", "Track id of each box: associate (built-in association of consecutive frames' boxes: "
                               "works with any detector), message (the boxes' own ids: a tracker's) or off (no "
                               "tracks: no fusion, no reuse).", {}),
    "association_max_distance": (_ASSOCIATION.max_distance, "Metres between a track's predicted and a box's centre "
                                                            "(plus a quarter of its length) to associate them.",
                                 _float(0.1, 50.0)),
    "reuse": (True, "Run the network for a tracked vehicle only when due (new points, size change, age) and "
                    "publish its cached completion, placed by the current box, otherwise.", {}),
    "reuse_new_points": (_REUSE.new_points, "Share of a vehicle's points farther than reuse_distance from those of "
                                            "its last completion that makes it due.", _float(0.01, 1.0)),
    "reuse_distance": (_REUSE.distance, "Metres: a point this far from the points of the last completion is new.",
                       _float(0.01, 10.0)),
    "reuse_size_change": (_REUSE.size_change, "Relative change of the box length, width or height that makes a "
                                              "vehicle due.", _float(0.001, 10.0)),
    "reuse_max_age": (_REUSE.max_age_s, "Seconds (stamp time) after which a cached completion is due.",
                      _float(0.01, 3600.0)),
    "completion_budget": (COMPLETION_BUDGET_S, "Seconds of network work per frame with reuse: the due vehicles run "
                                               "most urgent first (never completed, then new points, nearer), the "
                                               "rest keep their cached completion until a later frame.",
                          _float(0.001, 3600.0)),
    "max_boxes_per_message": (1000, "A boxes message with more boxes is refused before it is converted "
                                    "(skipped_box_message_too_large).", _int(1, 1000000)),
}
LIMIT_PARAMETERS = {"max_boxes": "max_boxes", "max_box_length": "max_box_length", "max_box_width": "max_box_width",
                    "max_box_height": "max_box_height", "min_box_length": "min_box_length",
                    "duplicate_distance": "duplicate_distance", "max_points_per_vehicle": "max_points_per_vehicle",
                    "max_output_points": "max_output_points", "time_budget": "time_budget_s"}

REUSE_PARAMETERS = frozenset({"reuse_new_points", "reuse_distance", "reuse_size_change", "reuse_max_age",
                              "completion_budget"})

# Applied while the node runs (`ros2 param set`); every other parameter is declared read-only, so a set
# is refused with rclpy's reason instead of reporting success and changing nothing.
LIVE_PARAMETERS = frozenset({"min_points", "crop_margin", "labels", "class_map", "sync_tolerance", "sync_max_wait",
                             "fresh_frame_age", "include_input_points", "measured_merge", *LIMIT_PARAMETERS})
# Parameters every rclpy node may be given, besides the completer's own.
STANDARD_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service", "start_parameter_services"})


def declare_parameters(node: Any) -> None:
    """Declare every completer parameter on `node` with its description, range and read-only flag;
    ParameterError (one line) for an override of the wrong type or outside its range."""
    from rclpy.exceptions import ParameterException

    for name, (default, description, ranges) in PARAMETERS.items():
        descriptor = ParameterDescriptor(name=name, description=description, read_only=name not in LIVE_PARAMETERS,
                                         **ranges)
        try:
            node.declare_parameter(name, default, descriptor)
        except ParameterException as exc:
            raise ParameterError(f"parameter {name}: {str(exc).splitlines()[0]}") from exc


def unknown_parameters(names: Iterable[str]) -> list[str]:
    """Warnings for parameter names the completer does not have (a typo is otherwise silently ignored)."""
    known = set(PARAMETERS) | STANDARD_PARAMETERS
    out = []
    for name in sorted(set(names) - known):
        if name.startswith("qos_overrides."):
            continue
        close = difflib.get_close_matches(name, known, n=1)
        out.append(f"unknown parameter '{name}' is ignored" + (f" (did you mean '{close[0]}'?)" if close else ""))
    return out


def params_file_problems(args: Sequence[str], node_names: Sequence[str]) -> list[str]:
    """Warnings for --params-file files (in ROS arguments `args`) with no section for this node."""
    import yaml

    problems = []
    files = [args[i + 1] for i, a in enumerate(args[:-1]) if a == "--params-file"]
    for path in files:
        try:
            sections = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError):
            continue   # rcl has already refused an unreadable file
        keys = [str(k) for k in sections] if isinstance(sections, dict) else []
        if not any(k in ("/**", "**") or k.lstrip("/") in node_names for k in keys):
            problems.append(f"params file {path} has no section for this node ({', '.join(node_names)}); its "
                            f"sections {keys} are not applied")
    return problems


def read_parameters(node: Any) -> CompleterParams:
    """Read the declared parameters and validate them; raises ParameterError naming the parameter."""
    values = {name: node.get_parameter(name).value for name in PARAMETERS}
    return validate(values)


def validate(values: dict[str, Any]) -> CompleterParams:
    """Check cross-field rules that a ParameterDescriptor cannot express."""
    if values["boxes_type"] not in BOXES_TYPES:
        raise ParameterError(f"parameter boxes_type={values['boxes_type']!r} must be one of {BOXES_TYPES}")
    device = str(values["device"])
    if not (device == "cpu" or device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit())):
        raise ParameterError(f"parameter device={device!r} must be cpu, cuda or cuda:N")
    labels = tuple(str(v).strip().lower() for v in values["labels"])
    unknown = [v for v in labels if v not in LABEL_IDS]
    if not labels or unknown:
        raise ParameterError(f"parameter labels={list(values['labels'])} must be a non-empty subset of "
                             f"{sorted(LABEL_IDS)}")
    try:
        class_map = parse_class_map(values["class_map"])
    except BoxError as exc:
        raise ParameterError(f"parameter class_map: {exc}") from exc
    if values["crop_margin"] != -1.0 and values["crop_margin"] < 0.0:
        raise ParameterError(f"parameter crop_margin={values['crop_margin']} must be -1 (the checkpoint's) "
                             "or in [0, 5]")
    for name in ("cloud_topic", "boxes_topic", "output_topic"):
        if not str(values[name]).strip():
            raise ParameterError(f"parameter {name} must not be empty")
    try:
        limits = FrameLimits(**{field: values[name] for name, field in LIMIT_PARAMETERS.items()})
    except ValueError as exc:
        raise ParameterError(f"frame limits: {exc}") from exc
    if values["track_ids"] not in TRACK_ID_MODES:
        raise ParameterError(f"parameter track_ids={values['track_ids']!r} must be one of {TRACK_ID_MODES}")
    reuse = ReuseSettings(new_points=values["reuse_new_points"], distance=values["reuse_distance"],
                          size_change=values["reuse_size_change"], max_age_s=values["reuse_max_age"],
                          budget_s=values["completion_budget"]) if values["reuse"] else None
    plain = {k: v for k, v in values.items() if k not in LIMIT_PARAMETERS and k not in REUSE_PARAMETERS}
    return CompleterParams(**{**plain, "device": device, "labels": labels, "class_map": class_map, "limits": limits,
                              "reuse": reuse})


def check_model_sizes(params: CompleterParams, num_input: int, num_output: int, source: str) -> None:
    """Raise ParameterError when num_input_points / num_output_points disagree with the checkpoint."""
    for name, wanted, actual in (("num_input_points", params.num_input_points, num_input),
                                 ("num_output_points", params.num_output_points, num_output)):
        if wanted and wanted != actual:
            raise ParameterError(
                f"parameter {name}={wanted} does not match the checkpoint {source} ({actual}); "
                f"set it to {actual} or 0 (take it from the checkpoint)")


def parameters_markdown() -> str:
    """The README's parameters table: every parameter, its default (as in `config/completer.yaml`) and meaning."""
    import yaml

    rows = ["| parameter | default | meaning |", "|---|---|---|"]
    for name, (default, description, _) in PARAMETERS.items():
        text = yaml.safe_dump(default, default_flow_style=True, width=1000).strip().removesuffix("...").strip()
        rows.append(f"| `{name}` | `{text}` | {description} |")
    return "\n".join(rows)


def print_help() -> None:
    """`completer --help`: usage and every parameter with its default and whether it can change live."""
    print("usage: completer [--help] [--ros-args -p NAME:=VALUE ... --params-file FILE]\n\n"
          "ROS 2 node `completer` of gd_completion: completes the vehicles of PointCloud2 frames from their 3D "
          "boxes and publishes dense vehicle clouds.\n\nparameters (live: applied on `ros2 param set`; the others "
          "are read-only):")
    for name, (default, description, _) in PARAMETERS.items():
        print(f"  {name} (default {default!r}{', live' if name in LIVE_PARAMETERS else ''})\n      {description}")


def wants_help(argv: Sequence[str]) -> bool:
    """True when the user's arguments (before --ros-args) ask for -h or --help."""
    user = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    return any(a in ("-h", "--help") for a in user)
