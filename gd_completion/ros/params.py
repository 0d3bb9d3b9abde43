"""Parameters of the completer node: declarations with descriptions and ranges, read and validated once."""
from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from gd_completion.errors import GDCompletionError
from gd_completion.settings import SETTINGS, CompletionSettings, Setting, SettingsError
from gd_completion.stamp_sync import FRESH_FRAME_AGE_S, SYNC_MAX_WAIT_S, SYNC_QUEUE_SIZE

BOXES_TYPES = ("auto", "detection3d", "marker", "autoware_detected", "autoware_tracked")


class ParameterError(GDCompletionError):
    """A completer parameter with an unusable value."""


@dataclass(frozen=True)
class CompleterParams:
    """Validated parameter values of one completer node: its own (topics, message type, queues) and the
    completion's (`settings`, shared with the offline tools)."""

    cloud_topic: str
    boxes_topic: str
    output_topic: str
    refined_boxes_topic: str
    boxes_type: str
    num_input_points: int
    num_output_points: int
    sync_max_wait: float
    queue_size: int
    fresh_frame_age: float
    max_boxes_per_message: int
    settings: CompletionSettings


# The node's own parameters (the completion's are `settings.SETTINGS`).
NODE_SETTINGS: dict[str, Setting] = {
    "cloud_topic": Setting("points", "Input sensor_msgs/PointCloud2 topic (sensor-data QoS)."),
    "boxes_topic": Setting("detections", "Input 3D boxes topic (vision_msgs/Detection3DArray, "
                                         "visualization_msgs/MarkerArray, or autoware_perception_msgs/DetectedObjects "
                                         "or TrackedObjects: see boxes_type)."),
    "output_topic": Setting("completed_vehicles", "Output PointCloud2: x, y, z, instance_id, label, generated; "
                                                  "input header."),
    "refined_boxes_topic": Setting("", "Also publish each completed vehicle's refined box (where the box refiner "
                                       "places the true box; the cloud's header, the box's id and label) on this "
                                       "topic: vision_msgs/Detection3DArray, or autoware_perception_msgs/"
                                       "DetectedObjects with an Autoware boxes_type; empty = off."),
    "boxes_type": Setting("auto", "Boxes message type: auto (Detection3DArray when vision_msgs is installed, else "
                                  "MarkerArray), detection3d, marker, autoware_detected "
                                  "(autoware_perception_msgs/DetectedObjects: instance id = index in the array) or "
                                  "autoware_tracked (TrackedObjects: instance id from the object's UUID, the same in "
                                  "every frame; set track_ids:=message to key fusion and reuse by it). Only "
                                  "BOUNDING_BOX shapes are boxes; other shapes are skipped "
                                  "(skipped_unsupported_shape).",
                          choices=BOXES_TYPES),
    "num_input_points": Setting(0, "Points per vehicle fed to the network; must match the checkpoint (0 = take it "
                                   "from the checkpoint).", 0, 65536),
    "num_output_points": Setting(0, "Points the network generates per vehicle; must match the checkpoint (0 = take "
                                    "it from the checkpoint).", 0, 65536),
    "sync_max_wait": Setting(SYNC_MAX_WAIT_S, "Seconds a cloud (or boxes message) waits for its partner before it is "
                                              "dropped.", 0.01, 60.0, live=True),
    "queue_size": Setting(SYNC_QUEUE_SIZE, "Clouds and boxes messages buffered per stream while waiting for their "
                                           "partner.", 1, 1000),
    "fresh_frame_age": Setting(FRESH_FRAME_AGE_S, "Seconds; when the node is slower than its input, a paired frame "
                                                  "that has waited longer than this for the worker is held back for "
                                                  "the next frame if that is due within this time too, and replaced "
                                                  "by it (drop_stale); else it is completed as is. Lower latency; may "
                                                  "answer fewer frames. 0 = complete the newest pending frame "
                                                  "whatever its age.", 0.0, 10.0, live=True),
    "max_boxes_per_message": Setting(1000, "A boxes message with more boxes is refused before it is converted "
                                           "(skipped_box_message_too_large).", 1, 1_000_000),
}
_TOPICS = ("cloud_topic", "boxes_topic", "output_topic", "refined_boxes_topic", "boxes_type")
# Every parameter of the node, in the order of `completer --help`, the README table and config/completer.yaml.
ALL_SETTINGS: dict[str, Setting] = {**{k: NODE_SETTINGS[k] for k in _TOPICS}, **SETTINGS,
                                    **{k: v for k, v in NODE_SETTINGS.items() if k not in _TOPICS}}


def _ranges(setting: Setting) -> dict[str, Any]:
    """ParameterDescriptor keyword arguments of a numeric setting's range."""
    if setting.low is None or setting.high is None:
        return {}
    if setting.kind is int:
        return {"integer_range": [IntegerRange(from_value=int(setting.low), to_value=int(setting.high), step=1)]}
    return {"floating_point_range": [FloatingPointRange(from_value=float(setting.low), to_value=float(setting.high),
                                                        step=0.0)]}


# name -> (default, description, range keyword arguments of ParameterDescriptor)
PARAMETERS: dict[str, tuple[Any, str, dict[str, Any]]] = {
    name: (s.default, s.help, _ranges(s)) for name, s in ALL_SETTINGS.items()}
# Applied while the node runs (`ros2 param set`); every other parameter is declared read-only, so a set
# is refused with rclpy's reason instead of reporting success and changing nothing.
LIVE_PARAMETERS = frozenset(name for name, s in ALL_SETTINGS.items() if s.live)
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
    """Check every value (types, ranges, cross-field rules a ParameterDescriptor cannot express)."""
    for name in ("cloud_topic", "boxes_topic", "output_topic"):
        if not str(values[name]).strip():
            raise ParameterError(f"parameter {name} must not be empty")
    if values["boxes_type"] not in BOXES_TYPES:
        raise ParameterError(f"parameter boxes_type={values['boxes_type']!r} must be one of {BOXES_TYPES}")
    try:
        settings = CompletionSettings.from_values({k: v for k, v in values.items() if k in SETTINGS})
    except SettingsError as exc:
        raise ParameterError(f"parameter {exc}") from exc
    return CompleterParams(**{k: values[k] for k in NODE_SETTINGS}, settings=settings)


def track_ids_problems(params: CompleterParams) -> list[str]:
    """Warnings for a boxes_type whose ids do not suit `track_ids` while tracks are used (track_fusion or reuse): a
    tracker's UUIDs left unused (autoware_tracked without track_ids=message), or array indices taken for track
    ids (autoware_detected with track_ids=message: index i is another vehicle in every frame)."""
    s = params.settings
    if not (s.track_fusion or s.reuse is not None):
        return []
    if params.boxes_type == "autoware_tracked" and s.track_ids == "associate":
        return ["boxes_type autoware_tracked with track_ids 'associate': the tracker's UUIDs are not used as track "
                "ids (the built-in association is); set track_ids:=message to key fusion and reuse by them"]
    if params.boxes_type == "autoware_detected" and s.track_ids == "message":
        return ["boxes_type autoware_detected with track_ids 'message': DetectedObjects carry no ids, their index in "
                "the array is no track id (fusion and reuse would mix vehicles); use track_ids:=associate, or "
                "TrackedObjects (autoware_tracked)"]
    return []


def check_model_sizes(params: CompleterParams, num_input: int, num_output: int, source: str) -> None:
    """Raise ParameterError when num_input_points / num_output_points disagree with the checkpoint."""
    for name, wanted, actual in (("num_input_points", params.num_input_points, num_input),
                                 ("num_output_points", params.num_output_points, num_output)):
        if wanted and wanted != actual:
            raise ParameterError(
                f"parameter {name}={wanted} does not match the checkpoint {source} ({actual}); "
                f"set it to {actual} or 0 (take it from the checkpoint)")


def _yaml(value: Any) -> str:
    """`value` as one line of YAML (as a params file writes it)."""
    import yaml

    return str(yaml.safe_dump(value, default_flow_style=True, width=1000)).strip().removesuffix("...").strip()


def parameters_markdown() -> str:
    """The README's parameters table: every parameter, its default (as in `config/completer.yaml`) and meaning."""
    rows = ["| parameter | default | meaning |", "|---|---|---|"]
    for name, (default, description, _) in PARAMETERS.items():
        rows.append(f"| `{name}` | `{_yaml(default)}` | {description} |")
    return "\n".join(rows)


def parameters_yaml() -> str:
    """`config/completer.yaml`: every parameter with its default, its description as the comment above it."""
    lines = ["# Parameters of the `completer` node (gd_completion). Every parameter and its default;",
             "# generated from the table in gd_completion/settings.py and gd_completion/ros/params.py.",
             "completer:", "  ros__parameters:"]
    for name, (default, description, _) in PARAMETERS.items():
        lines += [f"    # {description}", f"    {name}: {_yaml(default)}"]
    return "\n".join(lines) + "\n"


def write_parameter_docs(readme: Path, config: Path) -> None:
    """Regenerate the README's parameters table and `config/completer.yaml` from the tables
    (`python -c "from gd_completion.ros.params import write_parameter_docs as w; w(...)"`, or
    `scripts/regenerate_parameters.sh`)."""
    text = readme.read_text()
    start = text.index("| parameter | default | meaning |")
    readme.write_text(text[:start] + parameters_markdown() + text[text.index("\n\n", start):])
    config.write_text(parameters_yaml())


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
