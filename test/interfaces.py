"""Test helpers for the locally generated vision_msgs Python bindings (built by scripts/build_interfaces.sh)."""
from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from ros_domain import allocate_domain_id

REPO = Path(__file__).resolve().parents[1]
BUILD_SCRIPT = REPO / "scripts" / "build_interfaces.sh"
VISION_MSGS_DIR = REPO / "gd_completion" / "msg" / "vision_msgs"
VISION_MSGS_TYPES = ("BoundingBox3D", "Detection3D", "Detection3DArray", "ObjectHypothesis", "ObjectHypothesisWithPose")
# Upstream vision_msgs 4.x (Jazzy) type hash of Detection3DArray; identical .msg text gives identical hashes.
DETECTION3DARRAY_TYPE_HASH = "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"

_PRELOAD_ORDER = (
    "rosidl_generator_c",
    "rosidl_typesupport_c",
    "rosidl_typesupport_cpp",
    "rosidl_typesupport_introspection_c",
    "rosidl_typesupport_introspection_cpp",
    "rosidl_typesupport_fastrtps_c",
    "rosidl_typesupport_fastrtps_cpp",
    "rosidl_generator_py",
)
_lock = threading.Lock()
_preloaded: list[ctypes.CDLL] = []


class InterfaceBuildError(RuntimeError):
    """scripts/build_interfaces.sh failed; the message carries the end of its log."""


def interfaces_build_dir() -> Path:
    """`$GD_INTERFACES_BUILD_DIR`, else `<repo>/build/interfaces`."""
    return Path(os.environ.get("GD_INTERFACES_BUILD_DIR", REPO / "build" / "interfaces")).resolve()


def build_interfaces(build_dir: Path | None = None) -> Path:
    """Build (or find up to date) the vision_msgs bindings; returns the install prefix `<build_dir>/install`."""
    build_dir = Path(build_dir) if build_dir is not None else interfaces_build_dir()
    env = dict(os.environ)
    if "GD_VENV" not in env and sys.prefix != sys.base_prefix:
        env["GD_VENV"] = sys.prefix  # the venv running the tests is the ROS prefix
    proc = subprocess.run(
        ["bash", str(BUILD_SCRIPT), str(build_dir)], capture_output=True, text=True, timeout=900, check=False, env=env
    )
    if proc.returncode != 0:
        raise InterfaceBuildError(
            f"{BUILD_SCRIPT} {build_dir} failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        )
    return build_dir / "install"


def _site_packages(prefix: Path) -> Path:
    return prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"


def _prepend(var: str, value: str, base: dict[str, str] | None = None) -> str:
    old = (base if base is not None else os.environ).get(var, "")
    parts = [value] + [p for p in old.split(os.pathsep) if p and p != value]
    return os.pathsep.join(parts)


def vision_msgs_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment additions (PYTHONPATH, LD_LIBRARY_PATH, AMENT_PREFIX_PATH, CMAKE_PREFIX_PATH) for a subprocess.

    Each value is the generated path prepended to the variable's value in `base` (default: os.environ), so
    `env = {**os.environ, **vision_msgs_env()}` is ready to pass to subprocess. Builds on demand.
    """
    prefix = build_interfaces()
    return {
        "PYTHONPATH": _prepend("PYTHONPATH", str(_site_packages(prefix)), base),
        "LD_LIBRARY_PATH": _prepend("LD_LIBRARY_PATH", str(prefix / "lib"), base),
        "AMENT_PREFIX_PATH": _prepend("AMENT_PREFIX_PATH", str(prefix), base),
        "CMAKE_PREFIX_PATH": _prepend("CMAKE_PREFIX_PATH", str(prefix), base),
    }


def import_vision_msgs():
    """Make `from vision_msgs.msg import Detection3DArray` work in this process; returns the `vision_msgs.msg` module.

    LD_LIBRARY_PATH is read once at process start, so the generated libraries are preloaded by absolute path with
    ctypes (RTLD_GLOBAL): rosidl_typesupport_c later dlopen()s `libvision_msgs__rosidl_typesupport_fastrtps_c.so` by
    bare name, and glibc then returns the already loaded object (matched by soname). The libraries also carry an
    RPATH to their own folder and the venv's lib, so the Python extension resolves its dependencies either way.
    """
    with _lock:
        prefix = build_interfaces()
        lib = prefix / "lib"
        if not _preloaded:
            for kind in _PRELOAD_ORDER:
                path = lib / f"libvision_msgs__{kind}.so"
                if path.exists():
                    _preloaded.append(ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL))
        site = str(_site_packages(prefix))
        if site not in sys.path:
            sys.path.insert(0, site)
        os.environ["AMENT_PREFIX_PATH"] = _prepend("AMENT_PREFIX_PATH", str(prefix))
        import vision_msgs.msg as msgs

        if Path(msgs.__file__).resolve().parents[2] != Path(site).resolve():
            raise ImportError(f"vision_msgs imported from {msgs.__file__}, expected the build in {site}")
        msgs.Detection3DArray.__class__.__import_type_support__()
        if msgs.Detection3DArray._TYPE_SUPPORT is None:  # type: ignore[attr-defined]
            raise ImportError(f"vision_msgs type support from {site} could not be loaded")
        return msgs


def vision_msgs_definitions() -> dict[str, str]:
    """`{"vision_msgs/msg/Detection3DArray": <.msg text>, ...}` for registering the types (e.g. in rosbags)."""
    return {f"vision_msgs/msg/{p.stem}": p.read_text() for p in sorted(VISION_MSGS_DIR.glob("*.msg"))}


def ros_test_domain_id(name: str = "default") -> int:
    """A ROS_DOMAIN_ID that no other test process on this machine holds (`ros_domain.allocate_domain_id`: one per
    `name`, kept for the life of the process); `$GD_TEST_DOMAIN_ID` overrides the default one."""
    if name == "default" and "GD_TEST_DOMAIN_ID" in os.environ:
        return int(os.environ["GD_TEST_DOMAIN_ID"])
    return allocate_domain_id(name)


def vision_msgs_type_hash(name: str = "Detection3DArray") -> str:
    """The RIHS01 type hash of `vision_msgs/msg/<name>` from the generated type description (builds on demand)."""
    import json

    desc = build_interfaces() / "share" / "vision_msgs" / "msg" / f"{name}.json"
    hashes = json.loads(desc.read_text())["type_hashes"]
    return next(h["hash_string"] for h in hashes if h["type_name"] == f"vision_msgs/msg/{name}")


def make_detection_array(msgs=None, frame_id: str = "lidar", n: int = 2):
    """A filled Detection3DArray with `n` detections (box i at x = 10 + i, size 4.5 x 1.8 x 1.5, class "car")."""
    msgs = msgs or import_vision_msgs()
    arr = msgs.Detection3DArray()
    arr.header.frame_id = frame_id
    arr.header.stamp.sec = 1700000000
    arr.header.stamp.nanosec = 123
    for i in range(n):
        det = msgs.Detection3D()
        det.header = arr.header
        det.id = f"track-{i}"
        det.bbox.center.position.x = 10.0 + i
        det.bbox.center.position.y = -2.0
        det.bbox.center.orientation.z = 0.38268343236508984  # yaw 45 deg
        det.bbox.center.orientation.w = 0.9238795325112867
        det.bbox.size.x, det.bbox.size.y, det.bbox.size.z = 4.5, 1.8, 1.5
        hyp = msgs.ObjectHypothesisWithPose()
        hyp.hypothesis.class_id = "car"
        hyp.hypothesis.score = 0.9 - 0.1 * i
        hyp.pose.pose = det.bbox.center
        det.results.append(hyp)
        arr.detections.append(det)
    return arr


def roundtrip_detection_array(timeout: float = 10.0):
    """Publish a Detection3DArray from one node and receive it on another in this process (loopback only, own domain).

    Returns `(sent, received)`; raises TimeoutError when nothing arrives. Uses its own rclpy Context, so it does not
    disturb a default context that other tests initialised.
    """
    msgs = import_vision_msgs()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_test_domain_id())
    try:
        qos = QoSProfile(depth=5, reliability=QoSReliabilityPolicy.RELIABLE, durability=QoSDurabilityPolicy.VOLATILE)
        talker = rclpy.create_node("gd_vision_msgs_talker", context=ctx)
        listener = rclpy.create_node("gd_vision_msgs_listener", context=ctx)
        got: list = []
        pub = talker.create_publisher(msgs.Detection3DArray, "gd_test/detections", qos)
        listener.create_subscription(msgs.Detection3DArray, "gd_test/detections", got.append, qos)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(talker)
        ex.add_node(listener)
        sent = make_detection_array(msgs)
        deadline = time.monotonic() + timeout
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        while not got and time.monotonic() < deadline:
            pub.publish(sent)
            end = time.monotonic() + 0.2
            while not got and time.monotonic() < end:
                ex.spin_once(timeout_sec=0.05)
        ex.shutdown()
        talker.destroy_node()
        listener.destroy_node()
        if not got:
            raise TimeoutError(f"no Detection3DArray received on gd_test/detections within {timeout} s")
        return sent, got[0]
    finally:
        rclpy.shutdown(context=ctx)


if __name__ == "__main__":
    t0 = time.monotonic()
    m = import_vision_msgs()
    print(f"vision_msgs from {m.__file__} ({time.monotonic() - t0:.1f} s)")
    s, r = roundtrip_detection_array()
    print("round trip ok:", r == s, r.detections[0].bbox.size, r.detections[0].results[0].hypothesis)
