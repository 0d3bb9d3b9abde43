"""ROS 2 node `completer`: pairs clouds with 3D boxes by stamp and publishes completed vehicle clouds."""
from __future__ import annotations

import importlib
import math
import os
import signal
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64, Header
from visualization_msgs.msg import MarkerArray

from gd_completion.autoware_messages import detected_objects_to_boxes, tracked_objects_to_boxes
from gd_completion.box_messages import BoxSet, box_count, detections_to_boxes, markers_to_boxes
from gd_completion.class_maps import unmapped_ids
from gd_completion.errors import GDCompletionError, PointCloud2Error
from gd_completion.fusion import TrackFusion
from gd_completion.kernels import kernels_cached
from gd_completion.pipeline import VehicleCompleter, completion_to_structured
from gd_completion.pointcloud2 import read_xyz
from gd_completion.ros.cloud_messages import structured_to_msg
from gd_completion.ros.params import (
    PARAMETERS,
    CompleterParams,
    ParameterError,
    check_model_sizes,
    declare_parameters,
    params_file_problems,
    read_parameters,
    track_ids_problems,
    unknown_parameters,
    validate,
)
from gd_completion.ros.refined_boxes import refined_boxes_output
from gd_completion.settings import CompletionSettings
from gd_completion.stamp_sync import LatestSlot, Pair, StampSync, stamp_to_ns
from gd_completion.transforms import TransformBuffer, boxes_in_frame

NODE_NAME = "completer"
WARN_PERIOD_S = 60.0        # a warning's cause is logged at most once per minute; counts are in /diagnostics
DIAGNOSTICS_PERIOD_S = 1.0  # on the steady clock: diagnostics and expiry also run under sim time without /clock
STOP_TIMEOUT_S = 1.5        # the worker stops between vehicles; the node exits within 2 s of SIGINT/SIGTERM
LARGE_CLOUD_BYTES = 1 << 20  # clouds above this get lost over Fast DDS's default transports
SIM_CLOCK_GRACE_S = 3.0
# Skips of normal operation (distant vehicles, a slow model): logged once, then only counted.
ROUTINE_CAUSES = frozenset({"too_few_points", "superseded", "no_subscribers", "deferred"})
# Counters always present in the diagnostics, so a consumer can rely on the keys.
COUNTER_KEYS = (
    "clouds_received", "boxes_received", "frames_published", "vehicles_completed", "ignored_labels",
    "unmapped_class_ids", "skipped_degenerate_box", "skipped_too_few_points", "boxes_wrong_frame",
    "boxes_no_transform", "boxes_without_header",
    "skipped_implausible_box", "skipped_duplicate_box", "skipped_too_many_boxes", "skipped_too_many_points",
    "skipped_output_limit", "skipped_time_budget",
    "bad_cloud", "nonfinite_points", "drop_superseded", "frames_without_subscribers", "errors",
    "completions_run", "completions_reused", "completions_deferred", "skipped_deferred",
    "skipped_box_message_too_large", "skipped_unsupported_shape",
)
PROCESSING_TIME_TOPIC = "~/debug/processing_time_ms"
# /diagnostics levels: counters that grew since the last report and call for action. Everything else (distant
# vehicles with too few points, frames superseded or deferred under load, classes not completed, no subscriber,
# non-finite points of organised clouds) is normal operation: counted, level OK.
WARN_COUNTERS = frozenset({
    "bad_cloud", "boxes_wrong_frame", "boxes_no_transform", "boxes_without_header", "unmapped_class_ids",
    "skipped_degenerate_box", "skipped_implausible_box", "skipped_box_message_too_large", "skipped_unsupported_shape",
    "skipped_too_many_boxes", "skipped_too_many_points", "skipped_output_limit", "skipped_time_budget",
    "drop_cloud_no_boxes", "drop_boxes_no_cloud",
})
ERROR_COUNTERS = frozenset({"errors"})   # a frame or boxes message that failed with an exception


# boxes_type -> (autoware_perception_msgs message, its converter)
AUTOWARE_BOXES_TYPES: dict[str, tuple[str, Callable[..., BoxSet]]] = {
    "autoware_detected": ("DetectedObjects", detected_objects_to_boxes),
    "autoware_tracked": ("TrackedObjects", tracked_objects_to_boxes),
}


def resolve_boxes_type(boxes_type: str) -> tuple[type, Callable[..., BoxSet], str]:
    """(message class, converter to BoxSet, type name) for the `boxes_type` parameter."""
    if boxes_type in AUTOWARE_BOXES_TYPES:
        name, convert = AUTOWARE_BOXES_TYPES[boxes_type]
        try:
            msgs = importlib.import_module("autoware_perception_msgs.msg")
        except ImportError as exc:
            raise ParameterError(
                f"parameter boxes_type={boxes_type!r} but autoware_perception_msgs is not importable ({exc}); "
                "install ros-<distro>-autoware-perception-msgs (or build it with scripts/build_interfaces.sh and "
                "source its install prefix)") from exc
        return getattr(msgs, name), convert, f"autoware_perception_msgs/msg/{name}"
    if boxes_type in ("auto", "detection3d"):
        try:
            from vision_msgs.msg import Detection3DArray
        except ImportError as exc:
            if boxes_type == "detection3d":
                raise ParameterError(
                    "parameter boxes_type='detection3d' but vision_msgs is not importable "
                    f"({exc}); install ros-<distro>-vision-msgs or use boxes_type='marker'") from exc
        else:
            return Detection3DArray, detections_to_boxes, "vision_msgs/msg/Detection3DArray"
    return MarkerArray, markers_to_boxes, "visualization_msgs/msg/MarkerArray"


def diagnostic_level(grown: dict[str, int]) -> tuple[bytes, str]:
    """The status level and message for the counters that grew since the last report: ERROR for failures, WARN
    for input or capacity problems (`WARN_COUNTERS`), else OK."""
    errors = sorted(k for k in grown if k in ERROR_COUNTERS)
    warnings = sorted(k for k in grown if k in WARN_COUNTERS)
    if errors:
        return DiagnosticStatus.ERROR, "failed: " + ", ".join(errors + warnings)
    if warnings:
        return DiagnosticStatus.WARN, "check the input: " + ", ".join(warnings)
    return DiagnosticStatus.OK, "ok"


def _percentile_ms(values: deque, q: float) -> float:
    return float(np.percentile(np.fromiter(values, float), q) * 1e3) if values else 0.0


class CompleterNode(Node):
    """Thin shell: subscriptions feed a StampSync; a worker thread completes the newest paired frame."""

    def __init__(self, completer: VehicleCompleter | None = None, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        self._warned: dict[str, tuple[float, int]] = {}
        for problem in unknown_parameters(self._parameter_overrides):
            self.get_logger().warning(problem)
        declare_parameters(self)
        self.params: CompleterParams = read_parameters(self)
        p = self.params
        s = p.settings
        # live settings are applied by _apply on top of the checkpoint's preprocessing, kept here
        self.completer = completer or VehicleCompleter.from_settings(replace(
            s, num_threads=s.num_threads or (1 if s.reuse else 0), min_points=0, crop_margin=-1.0))
        if completer is not None and s.track_fusion:
            completer.fusion = TrackFusion(s.fusion)
            completer.publish_fused_points = s.publish_fused_points
        self._checkpoint_preprocessing = self.completer.preprocessing
        check_model_sizes(p, self.completer.num_input, self.completer.num_output, s.model_path or "(shipped weights)")
        if not kernels_cached():
            self.get_logger().info("compiling the CPU kernels (first start after an install without "
                                   "`python -m gd_completion.warmup`: about a minute; cached on disk after)")
        self.completer.warm_up()
        boxes_cls, self._to_boxes, boxes_type_name = resolve_boxes_type(p.boxes_type)
        for problem in track_ids_problems(p):
            self.get_logger().warning(problem)

        self._lock = threading.Lock()  # guards counts, latencies and published times (worker vs. timer)
        self.counts: Counter = Counter({k: 0 for k in COUNTER_KEYS})
        self._latencies: deque = deque(maxlen=500)
        self._published_times: deque = deque(maxlen=1000)
        self._last_report: dict[str, int] = {}
        self.sync: StampSync[tuple[Header, np.ndarray], BoxSet] = StampSync(
            int(s.sync_tolerance * 1e9), p.queue_size, max_wait_ns=int(p.sync_max_wait * 1e9))
        self._apply(p)
        self._slot: LatestSlot[tuple[Pair, float]] = LatestSlot()
        self._stopping = threading.Event()
        self._started = time.monotonic()

        self._output_pub = self.create_publisher(PointCloud2, p.output_topic, QoSProfile(depth=5))
        self._refined_pub, self._refined_msg = None, None
        if p.refined_boxes_topic.strip():
            refined_cls, self._refined_msg, _ = refined_boxes_output(p.boxes_type)
            self._refined_pub = self.create_publisher(refined_cls, p.refined_boxes_topic, QoSProfile(depth=5))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self._time_pub = self.create_publisher(Float64, PROCESSING_TIME_TOPIC, QoSProfile(depth=10))
        self._tf = self._subscribe_tf(p.settings)
        self._worker = threading.Thread(target=self._work, name="completer-worker", daemon=True)
        self._worker.start()
        self.create_subscription(PointCloud2, p.cloud_topic, self._on_cloud, qos_profile_sensor_data)
        self.create_subscription(boxes_cls, p.boxes_topic, self._on_boxes, QoSProfile(depth=max(10, p.queue_size)))
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._on_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f"completer ready: {self.resolve_topic_name(p.cloud_topic)} (PointCloud2) + "
            f"{self.resolve_topic_name(p.boxes_topic)} ({boxes_type_name}) -> "
            f"{self.resolve_topic_name(p.output_topic)}; model {s.model_path or '(shipped weights)'} on {s.device}, "
            f"{self.completer.num_input} -> {self.completer.num_output} points, labels {list(s.labels)}")

    def _subscribe_tf(self, s: CompletionSettings) -> TransformBuffer | None:
        """A transform buffer fed by /tf and /tf_static (tf2's topics and QoS), or None when use_tf is off or
        tf2_msgs is not importable (then boxes in another frame than the cloud's are skipped)."""
        if not s.use_tf:
            return None
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError as exc:
            self.get_logger().warning(f"use_tf: tf2_msgs is not importable ({exc}); boxes in another frame than the "
                                      "cloud's are skipped (install ros-jazzy-tf2-msgs, or build it with "
                                      "scripts/build_interfaces.sh)")
            return None
        buffer = TransformBuffer(extrapolation_s=s.transform_tolerance)
        static = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                            reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(TFMessage, "/tf", lambda msg: buffer.add_message(msg, static=False),
                                 QoSProfile(depth=100))
        self.create_subscription(TFMessage, "/tf_static", lambda msg: buffer.add_message(msg, static=True), static)
        return buffer

    # -- parameters ------------------------------------------------------------------------------------

    def _apply(self, p: CompleterParams) -> None:
        """Put the live parameters into effect (at start and on `ros2 param set`)."""
        s = p.settings
        overrides = {k: v for k, v in (("min_points", s.min_points or None),
                                       ("crop_margin", s.crop_margin if s.crop_margin >= 0 else None)) if v is not None}
        self.completer.preprocessing = replace(self._checkpoint_preprocessing, **overrides)
        self.completer.labels = frozenset(s.labels)
        self.completer.include_input_points = s.include_input_points
        self.completer.measured_merge = s.measured_merge
        self.completer.even_spacing = s.even_spacing
        self.completer.mirror_plane = s.mirror_plane
        self.completer.pool_margin = s.pool_margin
        self.completer.limits = s.limits
        self._classes = s.classes
        self.sync.tolerance_ns = int(s.sync_tolerance * 1e9)
        self.sync.max_wait_ns = int(p.sync_max_wait * 1e9)
        self.params = p

    def _on_set_parameters(self, changes: Sequence[Any]) -> SetParametersResult:
        """Validate the new values together with the others; apply them, or refuse with the reason."""
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        values.update({c.name: c.value for c in changes if c.name in PARAMETERS})
        try:
            params = validate(values)
        except ParameterError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self._apply(params)
        self.get_logger().info("parameters changed: " + ", ".join(f"{c.name}={c.value!r}" for c in changes))
        return SetParametersResult(successful=True)

    def _warn(self, cause: str, text: str) -> None:
        """Log `text` the first time `cause` happens, then at most once per minute (routine causes: only
        the first time); every occurrence is counted in /diagnostics anyway."""
        now = time.monotonic()
        last, missed = self._warned.get(cause, (-math.inf, 0))
        if cause in ROUTINE_CAUSES and last > -math.inf:
            return
        if now - last < WARN_PERIOD_S:
            self._warned[cause] = (last, missed + 1)
            return
        self._warned[cause] = (now, 0)
        suffix = f" ({missed} more since the last such warning)" if missed else ""
        if cause in ROUTINE_CAUSES:
            self.get_logger().info(text + " (normal under load or for distant vehicles; counted in /diagnostics, "
                                   "not logged again)")
        else:
            self.get_logger().warning(text + suffix)

    # -- subscription side (executor thread) ---------------------------------------------------------

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def _offer(self, pair: Pair | None) -> None:
        if pair is not None and self._slot.put((pair, time.monotonic())):
            self._count("drop_superseded")
            self._warn("superseded", "completion slower than the input: dropped an older pending frame (newest wins)")

    def _on_cloud(self, msg: PointCloud2) -> None:
        self._count("clouds_received")
        if len(msg.data) > LARGE_CLOUD_BYTES and not os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"):
            self._warn("large_cloud", f"received a {len(msg.data) / 2**20:.1f} MiB cloud: over Fast DDS's default "
                       "transports many clouds this large are lost; give the publisher (and this node) "
                       "FASTRTPS_DEFAULT_PROFILES_FILE=<share/gd_completion>/config/fastdds_large_messages.xml "
                       "(the launch file sets it for the node)")
        try:  # decoding is one copy of x, y, z (~1 ms for 120k points): bad clouds never wait for boxes
            points = read_xyz(msg)
        except PointCloud2Error as exc:
            self._count("bad_cloud")
            self._warn("bad_cloud", f"skipping malformed cloud on {self.params.cloud_topic} "
                                    f"(stamp {stamp_to_ns(msg.header.stamp) * 1e-9:.3f}): {exc}")
            return
        self._offer(self.sync.add_cloud(stamp_to_ns(msg.header.stamp), (msg.header, points), time.monotonic_ns()))

    def _on_boxes(self, msg: Any) -> None:
        self._count("boxes_received")
        started = time.perf_counter()
        count = box_count(msg)
        if count > self.params.max_boxes_per_message:
            self._count("skipped_box_message_too_large")
            self._warn("box_message_too_large", f"refused a boxes message on {self.params.boxes_topic} with {count} "
                       f"boxes (max_boxes_per_message {self.params.max_boxes_per_message}) before converting it")
            return
        try:
            boxes = self._to_boxes(msg, self._classes)
        except (GDCompletionError, TypeError, ValueError) as exc:
            self._count("errors")
            self._warn("bad_boxes", f"skipping unreadable boxes message on {self.params.boxes_topic}: {exc}")
            return
        if boxes.unsupported_shapes:
            self._count("skipped_unsupported_shape", boxes.unsupported_shapes)
            self._warn("unsupported_shape", f"skipped {boxes.unsupported_shapes} object(s) on "
                       f"{self.params.boxes_topic} whose shape is no BOUNDING_BOX (CYLINDER, POLYGON)")
        if boxes.stamp_ns is None:
            self._count("boxes_without_header")
            self._warn("boxes_without_header",
                       f"skipping an empty MarkerArray on {self.params.boxes_topic}: it has no header to pair by "
                       "stamp (publish a DELETEALL marker with the frame's header for frames without vehicles)")
            return
        boxes = replace(boxes, decode_s=time.perf_counter() - started)
        self._offer(self.sync.add_boxes(boxes.stamp_ns, boxes, time.monotonic_ns()))

    def _on_timer(self) -> None:
        """Steady-clock housekeeping: expiry, diagnostics, and one warning for sim time without /clock."""
        self.sync.expire(time.monotonic_ns())
        self._publish_diagnostics()
        if (self.get_parameter("use_sim_time").value and self.get_clock().now().nanoseconds == 0
                and time.monotonic() - self._started > SIM_CLOCK_GRACE_S):
            self._warn("no_clock", "use_sim_time is true but nothing publishes /clock: ROS time stands at 0 "
                                   "(pairing, expiry and diagnostics run on the steady clock and go on)")

    # -- worker thread ---------------------------------------------------------------------------------

    def _work(self) -> None:
        while not self._stopping.is_set():
            item = self._slot.take(timeout=0.5, fresh_age=self.params.fresh_frame_age)
            if item is None:
                continue
            try:
                self._complete(*item)
            except Exception as exc:  # noqa: BLE001 - the node must outlive any single frame
                if self._stopping.is_set():
                    return
                self._count("errors")
                self._warn("error", f"frame skipped after an unexpected error: {exc!r}")

    def _complete(self, pair: Pair, ready_at: float) -> None:
        publishers = [pub for pub in (self._output_pub, self._refined_pub) if pub is not None]
        if not any(pub.get_subscription_count() for pub in publishers):   # lazy: no model work nobody receives
            self._count("frames_without_subscribers")
            self._warn("no_subscribers", f"nobody subscribes to {self.params.output_topic}: frames are paired "
                                         "and dropped without model work")
            return
        started = time.perf_counter()
        header, points = pair.cloud
        frame_id = header.frame_id
        stamp_ns = stamp_to_ns(header.stamp)
        problems: list[str] = []
        boxes, missing = boxes_in_frame(pair.boxes, frame_id, stamp_ns, self._tf, problems,
                                        self.params.settings.transform_wait)
        if missing and self._tf is None:
            self._count("boxes_wrong_frame", missing)
            self._warn("wrong_frame", f"skipping {missing} box(es) not in the cloud's frame '{frame_id}' "
                                      "(use_tf is off or tf2_msgs is not importable)")
        elif missing:
            self._count("boxes_no_transform", missing)
            self._warn("no_transform", f"skipping {missing} box(es) of a frame without a transform into "
                                       f"'{frame_id}': {problems[0]}")
        completion = self.completer.complete_frame(points, boxes, cancel=self._stopping, stamp_ns=stamp_ns)
        stats = completion.stats
        if stats.nonfinite_points:
            self._warn("nonfinite", f"dropped {stats.nonfinite_points} non-finite point(s) of a cloud on "
                                    f"{self.params.cloud_topic}")
        for reason, n in stats.skipped.items():
            self._warn(reason, f"skipped vehicles: {n} {reason}")
        if stats.unmapped_class_ids:
            ids = ", ".join(unmapped_ids(b.label for b in pair.boxes.boxes))
            self._warn("unmapped_class_ids", f"skipped {stats.unmapped_class_ids} box(es) with numeric class ids that "
                       f"class_preset '{self.params.settings.class_preset}' and class_map do not name (ids: {ids}); "
                       "numeric ids mean different classes in different detectors: set class_preset (e.g. "
                       "openpcdet_kitti) or class_map (e.g. ['1:car'])")
        msg = structured_to_msg(completion_to_structured(completion), header)
        if self._stopping.is_set():
            return
        self._output_pub.publish(msg)
        if self._refined_pub is not None and self._refined_msg is not None:
            self._refined_pub.publish(self._refined_msg(completion.boxes, header))
        self._time_pub.publish(Float64(data=(time.perf_counter() - started + pair.boxes.decode_s) * 1e3))
        done = time.monotonic()
        with self._lock:
            self.counts["frames_published"] += 1
            self.counts["vehicles_completed"] += stats.completed
            self.counts["ignored_labels"] += stats.ignored_labels
            self.counts["unmapped_class_ids"] += stats.unmapped_class_ids
            self.counts["nonfinite_points"] += stats.nonfinite_points
            self.counts["completions_run"] += stats.completions_run
            self.counts["completions_reused"] += stats.completions_reused
            self.counts["completions_deferred"] += stats.completions_deferred
            for reason, n in stats.skipped.items():
                self.counts[f"skipped_{reason}"] += n
            self._latencies.append(done - ready_at)
            self._published_times.append(done)

    # -- diagnostics ------------------------------------------------------------------------------------

    def diagnostics_values(self) -> dict[str, float]:
        """Cumulative counters plus rate and latency over the recent frames."""
        now = time.monotonic()
        with self._lock:
            values: dict[str, float] = dict(self.counts)
            recent = [t for t in self._published_times if now - t <= 5.0]
            values["rate_hz"] = len(recent) / 5.0
            values["latency_p50_ms"] = _percentile_ms(self._latencies, 50)
            values["latency_p95_ms"] = _percentile_ms(self._latencies, 95)
        for key, n in self.sync.counters.as_dict().items():
            values["frames_paired" if key == "paired" else f"drop_{key}"] = n
        clouds, boxes = self.sync.pending
        values["pending_clouds"], values["pending_boxes"] = clouds, boxes
        values["drop_stale"] = self._slot.stale
        if self.completer.fusion is not None:
            values.update(self.completer.fusion.counters)
        if self.params.settings.track_ids == "associate":
            values.update(self.completer.associator.counters)
        if self.completer.cache is not None:
            values["reuse_cached_tracks"] = len(self.completer.cache)
        return values

    def _publish_diagnostics(self) -> None:
        values = self.diagnostics_values()
        grown = {k: int(v) for k, v in values.items() if v > self._last_report.get(k, 0)}
        self._last_report = {k: int(v) for k, v in values.items()}
        level, message = diagnostic_level(grown)
        status = DiagnosticStatus(
            level=level,
            name=f"{self.get_fully_qualified_name()}: vehicle completion",
            hardware_id=self.get_fully_qualified_name(),
            message=message,
            values=[KeyValue(key=k, value=(f"{v:.3f}" if isinstance(v, float) else str(v)))
                    for k, v in values.items()],
        )
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(array)

    def close(self) -> None:
        """Stop the worker (it stops between vehicles), the vehicle threads, and destroy the node."""
        self._stopping.set()
        self._slot.close()
        self._worker.join(timeout=STOP_TIMEOUT_S)
        self.completer.close()
        self.destroy_node()


def main(args: list[str] | None = None, start_up_handler: Callable[[int, Any], None] | None = None) -> int:
    """`ros2 run gd_completion completer`: spin until SIGINT/SIGTERM, then exit 0 within 2 s (a second signal,
    as `ros2 launch` sends, changes nothing); exit 2 with one line on a configuration error. A signal while the
    node is being constructed (model loading, warm-up) goes to `start_up_handler` (`completer_main`: exit 0 at
    once); without one it is acted on once the node is constructed. `--help` is `completer_main`'s."""
    argv = list(sys.argv[1:] if args is None else args)
    stop = threading.Event()
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - rcl's RCLError: unreadable params file, bad --ros-args
        print(f"[{NODE_NAME}] error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    def request_stop(*_: Any) -> None:
        stop.set()
        for sig in (signal.SIGINT, signal.SIGTERM):   # further signals ignored, through interpreter exit too
            signal.signal(sig, signal.SIG_IGN)        # (Python restores SIG_DFL for handled signals at exit)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, start_up_handler or request_stop)
    node: CompleterNode | None = None
    code = 0
    try:
        node = CompleterNode()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, request_stop)
        for problem in params_file_problems(argv, (node.get_name(), node.get_fully_qualified_name().lstrip("/"))):
            node.get_logger().warning(problem)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except GDCompletionError as exc:
        print(f"[{NODE_NAME}] error: {exc}", file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            node.close()
        rclpy.try_shutdown()
    return code

