"""One typed settings object for every caller of the completer: the node, `complete`, `complete-cloud`, the
worker processes and the Ray actors.

`SETTINGS` is the one table of what can be set: each entry's default, meaning and range. The node declares its
ROS parameters from it (`ros/params.py`), the command line generates its flags from it (`add_flags`), and both
turn the values into a validated `CompletionSettings` (`CompletionSettings.from_values`). A setting therefore
exists once. Offline, a few defaults differ so the output never depends on the machine's load (`OFFLINE`).
"""
from __future__ import annotations

import argparse
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from gd_completion.association import TRACK_ID_MODES, AssociationSettings
from gd_completion.class_maps import CLASS_PRESETS, DEFAULT_PRESET, class_table
from gd_completion.errors import BoxError, GDCompletionError
from gd_completion.fusion import FusionLimits
from gd_completion.labels import DEFAULT_LABELS, LABEL_IDS
from gd_completion.limits import FrameLimits
from gd_completion.merge import PLANE_MIN_MOVE, PLANE_SHARE
from gd_completion.preprocess import POOL_MARGIN
from gd_completion.registration import AlignSettings
from gd_completion.reuse import ReuseSettings
from gd_completion.stamp_sync import SYNC_TOLERANCE_S


class SettingsError(GDCompletionError):
    """A setting (node parameter or command-line flag) with an unusable value."""


@dataclass(frozen=True)
class Setting:
    """One entry of the table: default, meaning, numeric range, allowed values and how it appears elsewhere."""

    default: Any
    help: str
    low: float | None = None          # numeric range, inclusive (the node's ParameterDescriptor, the flag's check)
    high: float | None = None
    choices: tuple[str, ...] = ()
    live: bool = False                # the node applies it on `ros2 param set`
    flag: str | None = ""             # command-line flag: "" = derived from the name, None = none
    offline: Any = None               # the offline default where it differs (None: the same)

    @property
    def kind(self) -> type:
        """bool, int, float, str or list (of strings), from the default."""
        return type(self.default)


_LIMITS = FrameLimits()
_FUSION = FusionLimits()
_REUSE = ReuseSettings()
_ASSOCIATION = AssociationSettings()
# The node's frame budget of network work when reusing completions (offline: none, so output never depends on load).
COMPLETION_BUDGET_S = 0.03

SETTINGS: dict[str, Setting] = {
    "model_path": Setting("", "GGD-Net checkpoint (.pt); empty = the weights shipped with the package.",
                          flag="--model"),
    "device": Setting("cpu", "Torch device: cpu, cuda or cuda:N."),
    "num_threads": Setting(0, "CPU threads completing a frame's vehicles in parallel, one torch thread each; 0 = one "
                              "per core (the node: 1 with reuse, as a frame's network work is then small and a "
                              "second thread only contends with the node's other threads).", 0, 256, flag="--threads"),
    "min_points": Setting(0, "Vehicles with fewer measured points above the ground in their box are skipped; 0 = the "
                             "checkpoint's preprocessing (20 for the shipped weights).", 0, 1_000_000, live=True),
    "crop_margin": Setting(-1.0, "Metres added to each side of a box when cropping the points fed to the network; -1 = "
                                 "the checkpoint's preprocessing (0.1 for the shipped weights, best with exact and "
                                 "with a detector's boxes alike: pool_margin publishes the ends a box cuts off; "
                                 "docs/MODEL.md).", -1.0, 5.0, live=True),
    "pool_margin": Setting(POOL_MARGIN, "Metres around a box within which measured points above the ground are "
                                        "published with its completion (pooled by the measured merge, generated=0) "
                                        "though not fed to the network, where wider than the crop margin: the ends "
                                        "a detector's box cuts off. 0 = the crop's points only.", 0.0, 5.0,
                           live=True),
    "labels": Setting(list(DEFAULT_LABELS), f"Labels to complete (of {sorted(LABEL_IDS)}).", live=True),
    "class_preset": Setting(DEFAULT_PRESET, "Detector classes -> labels: names (KITTI, nuScenes and Autoware class "
                                            "names; numeric ids unmapped), kitti, nuscenes, autoware or "
                                            "openpcdet_kitti (1 Car, 2 Pedestrian, 3 Cyclist).",
                            choices=tuple(CLASS_PRESETS), live=True),
    "class_map": Setting([""], "Extra 'class:label' entries on top of class_preset (e.g. '7:car', 'SUV:car', "
                               "'bus:ignore'; [''] = none); 'ignore' drops the box. A numeric id that no entry maps "
                               "is skipped and counted (unmapped_class_ids), never guessed.", live=True),
    "sync_tolerance": Setting(SYNC_TOLERANCE_S, "Largest stamp difference (s) between a cloud and its boxes.",
                              0.0, 10.0, live=True),
    "use_tf": Setting(True, "Boxes in another frame than the cloud's are moved into the cloud's frame at the cloud's "
                            "stamp with the transforms of /tf and /tf_static (offline: the bag's); boxes whose "
                            "transform is unknown are skipped (boxes_no_transform). false: such boxes are skipped "
                            "(boxes_wrong_frame)."),
    "transform_tolerance": Setting(0.05, "Seconds a stamp may lie outside the transforms received for it; within, the "
                                         "nearest transform is used (no extrapolation), beyond, the boxes are skipped.",
                                   0.0, 10.0),
    "transform_wait": Setting(0.1, "Seconds to wait for /tf to reach a frame's stamp before its boxes from another "
                                   "frame are moved (tf2's message filter; the transform often arrives after the "
                                   "cloud): live the worker waits, offline the bag is read that much further (bag "
                                   "time); then the nearest transform within transform_tolerance is used, or the "
                                   "boxes are skipped. 0 = no wait.", 0.0, 2.0),
    "include_input_points": Setting(True, "Also publish the measured points of each completed vehicle (generated=0); "
                                          "without them, a merged completion's own measured points still carry "
                                          "generated=0.", live=True, flag="--no-input-points"),
    "measured_merge": Setting(True, "Thin each completion together with every measured point of the vehicle (one "
                                    "per 1 % voxel; a track's: its fused partial) and their mirror image, measured "
                                    "points first (they replace network points wherever the vehicle was seen).",
                              live=True),
    "mirror_plane": Setting(PLANE_SHARE, "Share (0-1) of the offset across the box at which a clearly seen side "
                                         "and the box's width place the vehicle's plane of symmetry, by which the "
                                         "measured merge moves the plane it mirrors the measured points about where "
                                         f"that offset is at least {PLANE_MIN_MOVE * 100:g} % of the length (a "
                                         "detector's box is off by decimetres); 0 = always the box's own plane.",
                            0.0, 1.0,
                            live=True),
    "even_spacing": Setting(True, "Move the network's points along their own surface until their spacing is even "
                                  "(5 pushes away from the nearest points within the local plane, then 30 % of the "
                                  "way onto it), before the merge; false: the network's points are not moved.",
                            live=True),
    # per-frame work limits (gd_completion.limits.FrameLimits); every skip is a counter in /diagnostics
    "max_boxes": Setting(_LIMITS.max_boxes, "Boxes completed per frame at most, nearest first; the rest are skipped "
                                            "(too_many_boxes).", 1, 100_000, live=True),
    "max_box_length": Setting(_LIMITS.max_box_length, "Metres; longer boxes are not vehicles and are skipped "
                                                      "(implausible_box).", 1.0, 1000.0, live=True),
    "max_box_width": Setting(_LIMITS.max_box_width, "Metres; wider boxes are skipped (implausible_box).",
                             0.5, 1000.0, live=True),
    "max_box_height": Setting(_LIMITS.max_box_height, "Metres; taller boxes are skipped (implausible_box).",
                              0.5, 1000.0, live=True),
    "min_box_length": Setting(_LIMITS.min_box_length, "Metres; shorter boxes are skipped (implausible_box).",
                              0.01, 100.0, live=True),
    "duplicate_distance": Setting(_LIMITS.duplicate_distance, "Metres; a box whose centre is this close to a nearer "
                                                              "kept box is a duplicate, skipped (duplicate_box).",
                                  0.001, 10.0, live=True),
    "max_points_per_vehicle": Setting(_LIMITS.max_points_per_vehicle, "A box holding more points is skipped "
                                                                      "(too_many_points).", 1, 100_000_000, live=True),
    "max_output_points": Setting(_LIMITS.max_output_points, "Points published per frame at most, whole vehicles "
                                                            "nearest first; the rest are skipped (output_limit).",
                                 1, 1_000_000_000, live=True),
    "time_budget": Setting(_LIMITS.time_budget_s, "Seconds of completion per frame; vehicles not started by then are "
                                                  "skipped (time_budget), nearest first. Offline: none, so the output "
                                                  "never depends on the machine's load.", 0.01, 3600.0, live=True,
                           offline=math.inf),
    # track fusion (gd_completion.fusion): complete each tracked vehicle (box id = track id) from all its frames
    "track_fusion": Setting(False, "Complete each tracked vehicle (track ids: track_ids) from its points of all "
                                   "frames so far, in its box frame."),
    "publish_fused_points": Setting(False, "With track_fusion, publish a vehicle's fused measured points "
                                           "(generated=0) instead of the frame's own."),
    "fusion_max_tracks": Setting(_FUSION.max_tracks, "Tracks kept at most; the least recently seen is dropped "
                                                     "beyond it.", 1, 100_000),
    "fusion_max_points": Setting(_FUSION.max_points_per_track, "Fused points kept per track at most (oldest frames "
                                                               "dropped first).", 100, 10_000_000),
    "fusion_expiry": Setting(_FUSION.expiry_s, "Seconds (stamp time) after which a track not seen is dropped.",
                             0.05, 3600.0),
    "fusion_align": Setting(True, "Align each new frame of a track to its fused points (x, y, yaw; bounded ICP) "
                                  "against box jitter; false stores it as its box places it."),
    # track identity (gd_completion.association) and completion reuse (gd_completion.reuse)
    "track_ids": Setting("associate", "Track id of each box: associate (built-in association of consecutive frames' "
                                      "boxes: works with any detector), message (the boxes' own ids: a tracker's) "
                                      "or off (no tracks: no fusion, no reuse).", choices=TRACK_ID_MODES),
    "association_max_distance": Setting(_ASSOCIATION.max_distance, "Metres between a track's predicted and a box's "
                                                                   "centre (plus a quarter of its length) to "
                                                                   "associate them.", 0.1, 50.0),
    "reuse": Setting(True, "Run the network for a tracked vehicle only when due (new points, size change, age) and "
                           "publish its cached completion, placed by the current box, otherwise. Offline: off unless "
                           "asked for.", offline=False),
    "reuse_new_points": Setting(_REUSE.new_points, "Share of a vehicle's points farther than reuse_distance from "
                                                   "those of its last completion that makes it due.", 0.01, 1.0),
    "reuse_distance": Setting(_REUSE.distance, "Metres: a point this far from the points of the last completion is "
                                               "new.", 0.01, 10.0),
    "reuse_size_change": Setting(_REUSE.size_change, "Relative change of the box length, width or height that makes "
                                                     "a vehicle due.", 0.001, 10.0),
    "reuse_max_age": Setting(_REUSE.max_age_s, "Seconds (stamp time) after which a cached completion is due.",
                             0.01, 3600.0),
    "completion_budget": Setting(COMPLETION_BUDGET_S, "Seconds of network work per frame with reuse: the due "
                                                      "vehicles run most urgent first (never completed, then new "
                                                      "points, nearer), the rest keep their cached completion until "
                                                      "a later frame. Offline: none.", 0.001, 3600.0,
                                 offline=math.inf),
}

LIMIT_SETTINGS = {"max_boxes": "max_boxes", "max_box_length": "max_box_length", "max_box_width": "max_box_width",
                  "max_box_height": "max_box_height", "min_box_length": "min_box_length",
                  "duplicate_distance": "duplicate_distance", "max_points_per_vehicle": "max_points_per_vehicle",
                  "max_output_points": "max_output_points", "time_budget": "time_budget_s"}


def defaults(offline: bool = False) -> dict[str, Any]:
    """Every setting's default value: the node's, or (`offline`) the offline tools'."""
    return {name: (s.offline if offline and s.offline is not None else s.default) for name, s in SETTINGS.items()}


@dataclass(frozen=True)
class CompletionSettings:
    """What a `VehicleCompleter` is built with; made from the table's values by `from_values` (or `offline`), so
    its defaults are the table's."""

    model_path: str
    device: str
    num_threads: int
    min_points: int              # 0: the checkpoint's
    crop_margin: float           # -1: the checkpoint's
    pool_margin: float
    labels: tuple[str, ...]
    class_preset: str
    class_map: tuple[str, ...]   # the user's entries, as given (blank ones dropped)
    sync_tolerance: float
    use_tf: bool
    transform_tolerance: float
    transform_wait: float
    include_input_points: bool
    measured_merge: bool
    mirror_plane: float
    even_spacing: bool
    limits: FrameLimits
    track_fusion: bool
    publish_fused_points: bool
    fusion: FusionLimits
    track_ids: str
    association: AssociationSettings
    reuse: ReuseSettings | None

    @classmethod
    def from_values(cls, values: Mapping[str, Any], offline: bool = False) -> CompletionSettings:
        """Validate `values` (names of `SETTINGS`; missing ones take their defaults) together; SettingsError
        naming the setting for an unusable value."""
        unknown = sorted(set(values) - set(SETTINGS))
        if unknown:
            raise SettingsError(f"unknown settings {unknown}")
        v = {**defaults(offline), **values}
        for name, setting in SETTINGS.items():
            _check(name, setting, v[name])
        device = str(v["device"])
        if not (device in ("cpu", "cuda") or (device.startswith("cuda:") and device[5:].isdigit())):
            raise SettingsError(f"device={device!r} must be cpu, cuda or cuda:N")
        if v["crop_margin"] != -1.0 and v["crop_margin"] < 0.0:
            raise SettingsError(f"crop_margin={v['crop_margin']} must be -1 (the checkpoint's) or in [0, 5]")
        labels = tuple(str(x).strip().lower() for x in v["labels"])
        if not labels or any(x not in LABEL_IDS for x in labels):
            raise SettingsError(f"labels={list(v['labels'])} must be a non-empty subset of {sorted(LABEL_IDS)}")
        try:
            class_table(v["class_preset"], v["class_map"])
        except BoxError as exc:
            raise SettingsError(f"class_map: {exc}") from exc
        try:
            limits = FrameLimits(**{fld: v[name] for name, fld in LIMIT_SETTINGS.items()})
        except ValueError as exc:
            raise SettingsError(f"frame limits: {exc}") from exc
        fusion = FusionLimits(max_tracks=v["fusion_max_tracks"], max_points_per_track=v["fusion_max_points"],
                              expiry_s=v["fusion_expiry"], align=AlignSettings() if v["fusion_align"] else None)
        reuse = ReuseSettings(new_points=v["reuse_new_points"], distance=v["reuse_distance"],
                              size_change=v["reuse_size_change"], max_age_s=v["reuse_max_age"],
                              budget_s=v["completion_budget"]) if v["reuse"] else None
        return cls(model_path=str(v["model_path"]), device=device, num_threads=int(v["num_threads"]),
                   min_points=int(v["min_points"]), crop_margin=float(v["crop_margin"]),
                   pool_margin=float(v["pool_margin"]), labels=labels,
                   class_preset=str(v["class_preset"]),
                   class_map=tuple(str(e) for e in v["class_map"] if str(e).strip()),
                   sync_tolerance=float(v["sync_tolerance"]), use_tf=bool(v["use_tf"]),
                   transform_tolerance=float(v["transform_tolerance"]), transform_wait=float(v["transform_wait"]),
                   include_input_points=bool(v["include_input_points"]),
                   measured_merge=bool(v["measured_merge"]), mirror_plane=float(v["mirror_plane"]),
                   even_spacing=bool(v["even_spacing"]),
                   limits=limits, track_fusion=bool(v["track_fusion"]),
                   publish_fused_points=bool(v["publish_fused_points"]), fusion=fusion, track_ids=str(v["track_ids"]),
                   association=AssociationSettings(max_distance=float(v["association_max_distance"])), reuse=reuse)

    @classmethod
    def offline(cls, **values: Any) -> CompletionSettings:
        """The offline tools' settings: their defaults with `values` on top."""
        return cls.from_values(values, offline=True)

    @property
    def classes(self) -> dict[str, str]:
        """Detector class -> label: the preset with the `class_map` entries on top."""
        return class_table(self.class_preset, self.class_map)


def _check(name: str, setting: Setting, value: Any) -> None:
    """SettingsError unless `value` has the setting's kind, range and choices."""
    kind = setting.kind
    ok = (isinstance(value, bool) if kind is bool else
          isinstance(value, (int, float)) and not isinstance(value, bool) if kind is float else
          isinstance(value, int) and not isinstance(value, bool) if kind is int else
          isinstance(value, (list, tuple)) and all(isinstance(x, str) for x in value) if kind is list else
          isinstance(value, str))
    if not ok:
        raise SettingsError(f"{name}={value!r} must be {kind.__name__}")
    if setting.choices and value not in setting.choices:
        raise SettingsError(f"{name}={value!r} must be one of {setting.choices}")
    if kind in (int, float) and setting.offline is not None and value == setting.offline:
        return   # the offline default (e.g. no time budget) lies outside the node's range on purpose
    if setting.low is not None and setting.high is not None and not setting.low <= value <= setting.high:
        raise SettingsError(f"{name}={value} must be in [{setting.low}, {setting.high}]")


# -- command line ------------------------------------------------------------------------------------------------

def flag_name(name: str) -> str | None:
    """The command-line flag of setting `name` (None: not on the command line)."""
    setting = SETTINGS[name]
    if setting.flag is None or setting.flag:
        return setting.flag
    dashed = name.replace("_", "-")
    on = setting.offline if setting.offline is not None else setting.default
    return f"--no-{dashed}" if setting.kind is bool and on else f"--{dashed}"


def _parse(name: str, setting: Setting) -> Any:
    """argparse type for one setting: the value converted and checked as `CompletionSettings` checks it."""
    def parse(text: str) -> Any:
        try:
            value: Any = ([x.strip() for x in text.split(",") if x.strip()] if setting.kind is list
                          else setting.kind(text))
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {setting.kind.__name__} {text!r}") from None
        try:
            _check(name, setting, value)
        except SettingsError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return value
    return parse


_METAVARS = {int: "N", float: "VALUE", str: "TEXT", list: "A,B,..."}


def add_flags(parser: argparse.ArgumentParser, names: Iterable[str] | None = None) -> None:
    """Add the flags of the settings `names` (default: every one that has a flag) with the offline defaults; their
    values land in `args.setting_<name>` (None when not given)."""
    offline = defaults(offline=True)
    for name in names if names is not None else SETTINGS:
        setting, flag = SETTINGS[name], flag_name(name)
        if flag is None:
            continue
        text = setting.help.replace("%", "%%")  # argparse formats help with %
        dest = f"setting_{name}"
        if setting.kind is bool:
            parser.add_argument(flag, dest=dest, action="store_const", const=not offline[name], default=None,
                                help=f"{text} (the node's {name}:={str(not offline[name]).lower()})")
            continue
        shown = (",".join(x for x in offline[name] if x) if setting.kind is list else offline[name]) or "none"
        parser.add_argument(flag, dest=dest, type=_parse(name, setting), default=None,
                            metavar=None if setting.choices else _METAVARS[setting.kind],
                            choices=setting.choices or None,
                            help=f"{text} (default {shown}; the node's {name})")


def from_args(args: argparse.Namespace) -> CompletionSettings:
    """The offline settings of the flags given (see `add_flags`)."""
    given = {key.removeprefix("setting_"): value for key, value in vars(args).items()
             if key.startswith("setting_") and value is not None}
    return CompletionSettings.from_values(given, offline=True)

