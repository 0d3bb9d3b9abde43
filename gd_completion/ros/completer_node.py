"""ROS 2 node `completer`: pairs clouds with 3D boxes by stamp and publishes completed vehicle clouds."""
from __future__ import annotations

import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64, Header
from visualization_msgs.msg import MarkerArray

from gd_completion.box_messages import BoxSet, detections_to_boxes, markers_to_boxes
from gd_completion.errors import GDCompletionError, PointCloud2Error
from gd_completion.pipeline import VehicleCompleter, completion_to_structured
from gd_completion.pointcloud2 import read_xyz
from gd_completion.ros.cloud_messages import structured_to_msg
from gd_completion.ros.params import (
    CompleterParams,
    ParameterError,
    check_model_sizes,
    declare_parameters,
    read_parameters,
)
from gd_completion.stamp_sync import LatestSlot, Pair, StampSync, stamp_to_ns

NODE_NAME = "completer"
WARN_THROTTLE_S = 5.0
DIAGNOSTICS_PERIOD_S = 1.0
# Counters always present in the diagnostics, so a consumer can rely on the keys.
COUNTER_KEYS = (
    "clouds_received", "boxes_received", "frames_published", "vehicles_completed", "ignored_labels",
    "skipped_degenerate_box", "skipped_too_few_points", "boxes_wrong_frame", "boxes_without_header",
    "skipped_implausible_box", "skipped_duplicate_box", "skipped_too_many_boxes", "skipped_too_many_points",
    "skipped_output_limit", "skipped_time_budget",
    "bad_cloud", "nonfinite_points", "drop_superseded", "frames_without_subscribers", "errors",
)
PROCESSING_TIME_TOPIC = "~/debug/processing_time_ms"


def resolve_boxes_type(boxes_type: str) -> tuple[type, Callable[..., BoxSet], str]:
    """(message class, converter to BoxSet, type name) for the `boxes_type` parameter."""
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


def _percentile_ms(values: deque, q: float) -> float:
    return float(np.percentile(np.fromiter(values, float), q) * 1e3) if values else 0.0


class CompleterNode(Node):
    """Thin shell: subscriptions feed a StampSync; a worker thread completes the newest paired frame."""

    def __init__(self, completer: VehicleCompleter | None = None, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        declare_parameters(self)
        self.params: CompleterParams = read_parameters(self)
        p = self.params
        self.completer = completer or VehicleCompleter.from_checkpoint(
            p.model_path or None, device=p.device, num_threads=p.num_threads or None, labels=p.labels,
            min_points=p.min_points or None, crop_margin=p.crop_margin if p.crop_margin >= 0 else None,
            include_input_points=p.include_input_points, limits=p.limits)
        check_model_sizes(p, self.completer.num_input, self.completer.num_output, p.model_path or "(shipped weights)")
        self.completer.warm_up()
        boxes_cls, self._to_boxes, boxes_type_name = resolve_boxes_type(p.boxes_type)

        self._lock = threading.Lock()  # guards counts, latencies and published times (worker vs. timer)
        self.counts: Counter = Counter({k: 0 for k in COUNTER_KEYS})
        self._latencies: deque = deque(maxlen=500)
        self._published_times: deque = deque(maxlen=1000)
        self._last_report: dict[str, int] = {}
        self.sync: StampSync[tuple[Header, np.ndarray], BoxSet] = StampSync(
            int(p.sync_tolerance * 1e9), p.queue_size, max_wait_ns=int(p.sync_max_wait * 1e9))
        self._slot: LatestSlot[tuple[Pair, float]] = LatestSlot()
        self._stopping = threading.Event()

        self._output_pub = self.create_publisher(PointCloud2, p.output_topic, QoSProfile(depth=5))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self._time_pub = self.create_publisher(Float64, PROCESSING_TIME_TOPIC, QoSProfile(depth=10))
        self._worker = threading.Thread(target=self._work, name="completer-worker", daemon=True)
        self._worker.start()
        self.create_subscription(PointCloud2, p.cloud_topic, self._on_cloud, qos_profile_sensor_data)
        self.create_subscription(boxes_cls, p.boxes_topic, self._on_boxes, QoSProfile(depth=max(10, p.queue_size)))
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._on_timer)
        self.get_logger().info(
            f"completer ready: {self.resolve_topic_name(p.cloud_topic)} (PointCloud2) + "
            f"{self.resolve_topic_name(p.boxes_topic)} ({boxes_type_name}) -> "
            f"{self.resolve_topic_name(p.output_topic)}; model {p.model_path or '(shipped weights)'} on {p.device}, "
            f"{self.completer.num_input} -> {self.completer.num_output} points, labels {list(p.labels)}")

    # -- subscription side (executor thread) ---------------------------------------------------------

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def _offer(self, pair: Pair | None) -> None:
        if pair is not None and self._slot.put((pair, time.monotonic())):
            self._count("drop_superseded")
            self.get_logger().warning(
                "completion slower than the input: dropped an older pending frame (newest wins)",
                throttle_duration_sec=WARN_THROTTLE_S)

    def _on_cloud(self, msg: PointCloud2) -> None:
        self._count("clouds_received")
        try:  # decoding is one copy of x, y, z (~1 ms for 120k points): bad clouds never wait for boxes
            points = read_xyz(msg)
        except PointCloud2Error as exc:
            self._count("bad_cloud")
            self.get_logger().warning(f"skipping malformed cloud on {self.params.cloud_topic} "
                                      f"(stamp {stamp_to_ns(msg.header.stamp) * 1e-9:.3f}): {exc}",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return
        self._offer(self.sync.add_cloud(stamp_to_ns(msg.header.stamp), (msg.header, points), time.monotonic_ns()))

    def _on_boxes(self, msg: Any) -> None:
        self._count("boxes_received")
        try:
            boxes = self._to_boxes(msg, self.params.class_map)
        except (GDCompletionError, TypeError, ValueError) as exc:
            self._count("errors")
            self.get_logger().warning(f"skipping unreadable boxes message on {self.params.boxes_topic}: {exc}",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return
        if boxes.stamp_ns is None:
            self._count("boxes_without_header")
            self.get_logger().warning(
                f"skipping an empty MarkerArray on {self.params.boxes_topic}: it has no header to pair by stamp "
                "(publish a DELETEALL marker with the frame's header for frames without vehicles)",
                throttle_duration_sec=WARN_THROTTLE_S)
            return
        self._offer(self.sync.add_boxes(boxes.stamp_ns, boxes, time.monotonic_ns()))

    def _on_timer(self) -> None:
        self.sync.expire(time.monotonic_ns())
        self._publish_diagnostics()

    # -- worker thread ---------------------------------------------------------------------------------

    def _work(self) -> None:
        while not self._stopping.is_set():
            item = self._slot.take(timeout=0.5)
            if item is None:
                continue
            try:
                self._complete(*item)
            except Exception as exc:  # noqa: BLE001 - the node must outlive any single frame
                if self._stopping.is_set():
                    return
                self._count("errors")
                self.get_logger().error(f"frame skipped after an unexpected error: {exc!r}",
                                        throttle_duration_sec=WARN_THROTTLE_S)

    def _complete(self, pair: Pair, ready_at: float) -> None:
        if self._output_pub.get_subscription_count() == 0:   # lazy: no model work that nobody receives
            self._count("frames_without_subscribers")
            return
        started = time.perf_counter()
        header, points = pair.cloud
        frame_id = header.frame_id
        boxes, wrong_frame = pair.boxes.split_by_frame(frame_id)
        if wrong_frame:
            self._count("boxes_wrong_frame", wrong_frame)
            self.get_logger().warning(
                f"skipping {wrong_frame} box(es) not in the cloud's frame '{frame_id}' (no tf transform here)",
                throttle_duration_sec=WARN_THROTTLE_S)
        completion = self.completer.complete_frame(points, boxes, cancel=self._stopping)
        stats = completion.stats
        if stats.nonfinite_points:
            self.get_logger().warning(f"dropped {stats.nonfinite_points} non-finite point(s) of a cloud on "
                                      f"{self.params.cloud_topic}", throttle_duration_sec=WARN_THROTTLE_S)
        if stats.skipped:
            self.get_logger().warning(f"skipped vehicles: {dict(stats.skipped)}", throttle_duration_sec=WARN_THROTTLE_S)
        msg = structured_to_msg(completion_to_structured(completion), header)
        if self._stopping.is_set():
            return
        self._output_pub.publish(msg)
        self._time_pub.publish(Float64(data=(time.perf_counter() - started) * 1e3))
        done = time.monotonic()
        with self._lock:
            self.counts["frames_published"] += 1
            self.counts["vehicles_completed"] += stats.completed
            self.counts["ignored_labels"] += stats.ignored_labels
            self.counts["nonfinite_points"] += stats.nonfinite_points
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
        return values

    def _publish_diagnostics(self) -> None:
        values = self.diagnostics_values()
        problems = {k: int(v) for k, v in values.items()
                    if (k.startswith(("drop_", "skipped_", "bad_", "boxes_wrong", "boxes_without", "errors"))
                        or k == "nonfinite_points") and v > self._last_report.get(k, 0)}
        self._last_report = {k: int(v) for k, v in values.items()}
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
            name=f"{self.get_fully_qualified_name()}: vehicle completion",
            hardware_id=self.get_fully_qualified_name(),
            message=("new skips/drops: " + ", ".join(sorted(problems))) if problems else "ok",
            values=[KeyValue(key=k, value=(f"{v:.3f}" if isinstance(v, float) else str(v)))
                    for k, v in values.items()],
        )
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(array)

    def close(self) -> None:
        """Stop the worker thread and destroy the node."""
        self._stopping.set()
        self._slot.close()
        self._worker.join(timeout=10.0)
        self.completer.close()
        self.destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run gd_completion completer`: spin until SIGINT/SIGTERM; exit 0 then, 2 on a configuration error."""
    rclpy.init(args=args)
    node: CompleterNode | None = None
    code = 0
    try:
        node = CompleterNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except GDCompletionError as exc:
        print(f"[{NODE_NAME}] error: {exc}", file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            node.close()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
