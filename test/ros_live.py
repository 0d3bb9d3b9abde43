"""Test helper: the completer node in a subprocess and a ROS client that feeds it (tests and benchmarks)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from kitti_frames import KittiFrame, cloud_msg, marker_array
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from ros_domain import allocate_domain_id
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64
from visualization_msgs.msg import MarkerArray

from gd_completion.geometry import Box3D

REPO = Path(__file__).resolve().parents[1]
DOMAIN_ID = allocate_domain_id("node_live")  # this process holds it: no concurrent test run shares it
# Large PointCloud2 over Fast DDS's default transports loses fragments between processes here; the shipped
# profile (big shared-memory segment, big UDP buffers) is given to both sides.
FASTDDS_PROFILE = REPO / "config" / "fastdds_large_messages.xml"


def ros_env(tmp: Path) -> dict[str, str]:
    profile = FASTDDS_PROFILE
    return {"ROS_DOMAIN_ID": str(DOMAIN_ID), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile), "ROS_LOG_DIR": str(tmp / "roslog"),
            "RCUTILS_COLORIZED_OUTPUT": "0", "PYTHONUNBUFFERED": "1"}


class NodeProcess:
    """`python -m gd_completion.ros.completer_main` (the `completer` executable) with stdout/stderr in files."""

    def __init__(self, tmp: Path, params: dict[str, str], env: dict[str, str], name: str) -> None:
        self.stderr_path = tmp / f"{name}.stderr"
        self.exit_code: int | None = None
        args = [sys.executable, "-m", "gd_completion.ros.completer_main", "--ros-args", "-r", f"__node:={name}"]
        for k, v in params.items():
            args += ["-p", f"{k}:={v}"]
        self._err = open(self.stderr_path, "w")
        full_env = {**os.environ, **env}
        full_env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in full_env.get("PYTHONPATH", "").split(
            os.pathsep) if p])
        self.proc = subprocess.Popen(args, cwd=REPO, env=full_env, stdout=subprocess.DEVNULL, stderr=self._err)

    @property
    def stderr(self) -> str:
        return self.stderr_path.read_text()

    def wait_ready(self, timeout: float = 90.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if "completer ready" in self.stderr:
                return
            if self.proc.poll() is not None:
                raise RuntimeError(f"completer exited with {self.proc.returncode} before ready:\n{self.stderr[-3000:]}")
            time.sleep(0.1)
        raise RuntimeError(f"completer not ready after {timeout} s:\n{self.stderr[-3000:]}")

    def _status_mib(self, field: str) -> float:
        try:
            lines = Path(f"/proc/{self.proc.pid}/status").read_text().splitlines()
        except OSError:
            return float("nan")
        return next((int(line.split()[1]) / 1024 for line in lines if line.startswith(f"{field}:")), float("nan"))

    def peak_rss_mib(self) -> float:
        """The node's peak resident memory (VmHWM), MiB; nan once it has exited."""
        return self._status_mib("VmHWM")

    def rss_mib(self) -> float:
        """The node's resident memory now (VmRSS), MiB; nan once it has exited."""
        return self._status_mib("VmRSS")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            self._err.close()


# -- test-side ROS client ------------------------------------------------------------------------------

class Client:
    """Publishes clouds and boxes, collects completed clouds by stamp and the node's latest diagnostics."""

    def __init__(self, context, boxes_cls=MarkerArray, prefix: str = "", node_name: str = "completer",
                 subscribe_output: bool = True) -> None:
        self.status_name = f"/{node_name}: vehicle completion"  # diagnostics of that node only
        self.node = rclpy.create_node(f"completer_test_client{prefix}", context=context)
        self.cloud_pub = self.node.create_publisher(PointCloud2, f"{prefix}points", qos_profile_sensor_data)
        self.boxes_pub = self.node.create_publisher(boxes_cls, f"{prefix}detections", QoSProfile(depth=10))
        self._cond = threading.Condition()
        self.replies: dict[int, PointCloud2] = {}
        self.reply_times: dict[int, float] = {}  # time.monotonic() at arrival, by stamp
        self.diag: dict[str, float] = {}
        self.diag_count = 0
        self.diag_levels: list[tuple[int, str]] = []   # (level, message) of every report of the node, in order
        self.output_topic = f"{prefix}completed_vehicles"
        if subscribe_output:
            self.subscribe_output()
        self.processing_times: list[float] = []   # the node's ~/debug/processing_time_ms
        self.node.create_subscription(Float64, f"/{node_name}/debug/processing_time_ms",
                                      lambda m: self.processing_times.append(m.data), QoSProfile(depth=50))
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, QoSProfile(depth=10))
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()
        self.stamp_ns = 1_000_000_000_000

    def subscribe_output(self) -> None:
        """Subscribe to the node's completed clouds (the node does no model work while nobody does)."""
        self.node.create_subscription(PointCloud2, self.output_topic, self._on_reply, QoSProfile(depth=50))

    def _on_reply(self, msg: PointCloud2) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self._cond:
            self.replies[stamp] = msg
            self.reply_times[stamp] = time.monotonic()
            self._cond.notify_all()

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == self.status_name:
                with self._cond:
                    self.diag = {kv.key: float(kv.value) for kv in status.values}
                    self.diag_levels.append((status.level[0] if isinstance(status.level, bytes) else status.level,
                                             status.message))
                    self.diag_count += 1
                    self._cond.notify_all()

    def next_stamp(self) -> int:
        self.stamp_ns += 1_000_000_000
        return self.stamp_ns

    def wait_reply(self, stamp_ns: int, timeout: float = 20.0) -> PointCloud2 | None:
        with self._cond:
            self._cond.wait_for(lambda: stamp_ns in self.replies, timeout)
            return self.replies.get(stamp_ns)

    def send(self, frame: KittiFrame, stamp_ns: int | None = None, *, boxes: list[Box3D] | None = None,
             cloud=None, frame_id: str = "velodyne") -> int:
        stamp_ns = stamp_ns or self.next_stamp()
        self.cloud_pub.publish(cloud if cloud is not None else cloud_msg(frame.points, stamp_ns, frame_id))
        self.boxes_pub.publish(self.boxes_msg(frame.boxes if boxes is None else boxes, stamp_ns, frame_id))
        return stamp_ns

    def send_until_reply(self, frame: KittiFrame, timeout: float = 60.0, every: float = 5.0) -> PointCloud2 | None:
        """Send `frame` with fresh stamps until one is answered. The cloud goes out best effort (sensor-data QoS,
        as lidar drivers publish), so on a loaded machine a 2 MB cloud can be lost in transport: a test of the
        node's recovery must not hinge on one delivery."""
        end = time.monotonic() + timeout
        sent: list[int] = []
        while time.monotonic() < end:
            sent.append(self.send(frame))
            with self._cond:
                wait = min(every, end - time.monotonic())
                if self._cond.wait_for(lambda: any(s in self.replies for s in sent), wait):
                    return next(self.replies[s] for s in sent if s in self.replies)
        return None

    def boxes_msg(self, boxes, stamp_ns, frame_id):
        return marker_array(boxes, stamp_ns, frame_id)

    def warm_up(self, frame: KittiFrame, timeout: float = 30.0) -> None:
        """Send frames until one is answered: both directions of discovery are then complete."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.send(frame)
            with self._cond:
                if self._cond.wait_for(lambda: self.replies, timeout=0.7):
                    return
        raise RuntimeError("the completer never answered a frame")

    def settled_diagnostics(self, timeout: float = 10.0) -> dict[str, float]:
        """The first diagnostics report that counts every reply received so far."""
        with self._cond:
            ok = self._cond.wait_for(lambda: self.diag.get("frames_published", -1) >= len(self.replies), timeout)
            assert ok, f"diagnostics never caught up with {len(self.replies)} replies: {self.diag}"
            return dict(self.diag)

    def wait_diagnostics(self, base: dict[str, float], expected: dict[str, int], timeout: float = 10.0
                         ) -> dict[str, float]:
        """Wait until every counter in `expected` grew by at least that much over `base`; returns the deltas."""
        def deltas() -> dict[str, float]:
            return {k: self.diag.get(k, 0) - base.get(k, 0) for k in expected}
        with self._cond:
            self._cond.wait_for(lambda: all(deltas()[k] >= v for k, v in expected.items()), timeout)
            return deltas()

    def close(self) -> None:
        self.executor.shutdown()
        self._thread.join(timeout=5.0)
        self.node.destroy_node()




@contextmanager
def benchmark_session(params: dict[str, str], name: str) -> Iterator[tuple[NodeProcess, Client]]:
    """For the benchmark scripts: a completer subprocess with `params` and a client in this process, on the
    large-message profile. On leaving, the node is stopped with SIGTERM; its exit code is printed and kept in
    `node.exit_code`."""
    tmp = Path(tempfile.mkdtemp(prefix=f"{name}_"))
    env = ros_env(tmp)
    os.environ.update(env)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    node = NodeProcess(tmp, params, env, name)
    client = None
    try:
        node.wait_ready()
        client = Client(context, node_name=name)
        yield node, client
    finally:
        if client is not None:
            client.close()
        node.exit_code = node.stop()
        rclpy.try_shutdown(context=context)
        print(f"node exit code after SIGTERM: {node.exit_code}")
