"""The completer node in a subprocess against real rclpy pub/sub: KITTI frames in, completed vehicles out,
bad input skipped and counted in /diagnostics, clean exit on SIGTERM/SIGINT."""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from kitti_frames import KittiFrame, cloud_msg, read_frame

from gd_completion.geometry import Box3D, crop_boxes
from gd_completion.pipeline import LABEL_IDS
from gd_completion.pointcloud2 import read_points

rclpy = pytest.importorskip("rclpy")
from ros_live import DOMAIN_ID, REPO, Client, NodeProcess, ros_env  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

pytestmark = pytest.mark.integration  # processes, ROS nodes, builds or bags: the slow part of the suite

NUM_OUTPUT = 2048  # points of a completion with the shipped model

# -- test frames ---------------------------------------------------------------------------------------

def around_boxes(frame: KittiFrame, radius: float = 12.0) -> KittiFrame:
    """The real frame cut to the points within `radius` m (xy) of a box: small messages, same vehicles."""
    centres = np.array([b.center[:2] for b in frame.boxes])
    d2 = ((frame.points[:, None, :2] - centres[None]) ** 2).sum(-1)
    return KittiFrame(frame.index, frame.points[(d2 < radius**2).any(1)], frame.boxes)


@pytest.fixture(scope="module")
def frames(shared_data: Path) -> dict[int, KittiFrame]:
    training = shared_data / "kitti-object-sample" / "training"
    return {i: around_boxes(read_frame(training, f"{i:06d}")) for i in (1, 3, 4)}


# -- node process --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ros_context(tmp_path_factory):
    env = ros_env(tmp_path_factory.mktemp("ros"))
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # the Fast DDS profile is read from the environment when the participant starts
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    yield env, context
    rclpy.try_shutdown(context=context)
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


# kitti_frames.detection_array numbers the classes 1/2/3 (OpenPCDet's style): numeric ids complete only through a map
NUMBERED_CLASSES = {"boxes_type": "detection3d", "class_map": "['1:car','2:van','3:truck']"}
# reuse off: these tests expect every vehicle of every frame completed by the network (with reuse, a vehicle never
# completed may wait a frame for the frame budget); test_reuse_live turns it on. A generous time budget: a slow phase
# of a shared machine must not skip a vehicle (the 2 s default did once in CI); test_limits covers the budget itself
BASE_PARAMS = {"num_threads": "1", "boxes_type": "marker", "sync_tolerance": "0.05", "sync_max_wait": "2.0",
               "reuse": "false", "time_budget": "60.0"}


@pytest.fixture(scope="module")
def marker_node(ros_context, frames, tmp_path_factory):
    env, context = ros_context
    node = NodeProcess(tmp_path_factory.mktemp("node"), BASE_PARAMS, env, "marker")
    node.wait_ready()
    client = Client(context, node_name="marker")
    client.warm_up(frames[3])
    yield node, client
    client.close()
    node.stop(signal.SIGKILL)


@contextmanager
def own_node(ros_context, tmp_path: Path, name: str, stop_signal: int = signal.SIGTERM, *,
             params: dict[str, str] | None = None, env: dict[str, str] | None = None,
             **client_kwargs) -> Iterator[tuple[NodeProcess, Client]]:
    """A completer of the test's own (`<name>_points`, `<name>_detections` -> `<name>_completed_vehicles`) and
    its client. On leaving, the client is closed and the node stopped with `stop_signal` (unless the test
    stopped it): it must have exited with 0 and without a traceback."""
    base_env, context = ros_context
    topics = {"cloud_topic": f"{name}_points", "boxes_topic": f"{name}_detections",
              "output_topic": f"{name}_completed_vehicles"}
    node = NodeProcess(tmp_path, {**BASE_PARAMS, **topics, **(params or {})}, {**base_env, **(env or {})}, name)
    client = None
    try:
        node.wait_ready()
        client = Client(context, prefix=f"{name}_", node_name=name, **client_kwargs)
        yield node, client
    finally:
        if client is not None:
            client.close()
        code = node.stop(stop_signal)
    assert code == 0, node.stderr[-2000:]
    assert "Traceback" not in node.stderr


# -- checks --------------------------------------------------------------------------------------------

def check_completion(msg: PointCloud2, frame: KittiFrame, stamp_ns: int, expected_ids: set[int]) -> np.ndarray:
    """Header kept, fields as documented, each expected vehicle measured + generated and inside its box."""
    assert msg.header.frame_id == "velodyne"
    assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == stamp_ns
    pts = read_points(msg)
    assert pts.dtype.names == ("x", "y", "z", "instance_id", "label", "generated")
    assert [pts.dtype[n] for n in pts.dtype.names] == [np.dtype("<f4")] * 3 + [np.dtype("<i4"), np.dtype("u1"),
                                                                                 np.dtype("u1")]
    assert set(np.unique(pts["instance_id"]).tolist()) == expected_ids
    boxes = {b.instance_id: b for b in frame.boxes}
    for iid in expected_ids:
        box = boxes[iid]
        mine = pts[pts["instance_id"] == iid]
        xyz = np.stack([mine["x"], mine["y"], mine["z"]], 1)
        assert np.isfinite(xyz).all()
        assert (mine["label"] == LABEL_IDS[box.label]).all()
        measured = int((mine["generated"] == 0).sum())
        assert measured > 0   # the completion's measured points are published once, as measured
        assert NUM_OUTPUT - measured <= (mine["generated"] == 1).sum() < NUM_OUTPUT   # merged: <= measured
        grown = Box3D(box.center, tuple(s + 1.0 for s in box.size), box.yaw)  # 0.5 m on every side
        inside = len(crop_boxes(xyz, [grown], 0.0)[0]) / len(xyz)
        assert inside >= 0.9, f"instance {iid}: only {inside:.1%} of its points within its box + 0.5 m"
        # the generated shape spans the vehicle, not a blob at its centre
        gen = xyz[mine["generated"] == 1] - np.asarray(box.center)
        along = gen[:, :2] @ np.array([math.cos(box.yaw), math.sin(box.yaw)])
        assert np.ptp(along) > 0.6 * box.size[0]
    return pts


# -- tests: good frames --------------------------------------------------------------------------------

def test_completes_kitti_frames_from_markers(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    for index, expected in ((3, {0}), (4, {0, 1}), (1, {0})):  # frame 1: the 9-point car (id 1) is skipped
        stamp = client.send(frames[index])
        msg = client.wait_reply(stamp)
        assert msg is not None, f"no completion for KITTI frame {index}\n{node.stderr[-2000:]}"
        check_completion(msg, frames[index], stamp, expected)
    expected = {"vehicles_completed": 4, "skipped_too_few_points": 1, "frames_published": 3}
    assert client.wait_diagnostics(base, expected) == expected
    assert node.stderr.count("completer ready") == 1
    assert client.diag["latency_p95_ms"] > 0 and client.diag["rate_hz"] > 0
    # normal operation (a distant car with too few points among them): every report OK, so a monitor can trust WARN
    assert client.diag_levels and {level for level, _ in client.diag_levels} == {0}, client.diag_levels


def test_diagnostic_levels_call_for_action_only():
    from diagnostic_msgs.msg import DiagnosticStatus

    from gd_completion.ros.completer_node import diagnostic_level

    assert diagnostic_level({"skipped_too_few_points": 3, "drop_superseded": 1, "completions_deferred": 5,
                             "frames_published": 10}) == (DiagnosticStatus.OK, "ok")
    assert diagnostic_level({"boxes_no_transform": 2, "skipped_too_few_points": 1}) == (
        DiagnosticStatus.WARN, "check the input: boxes_no_transform")
    assert diagnostic_level({"errors": 1, "bad_cloud": 1})[0] == DiagnosticStatus.ERROR


def test_slow_model_newest_frame_wins(marker_node, frames):
    """Frames faster than the model: no backlog, older pending frames dropped and counted, newest answered."""
    node, client = marker_node
    base = client.settled_diagnostics()
    stamps = [client.send(frames[4]) for _ in range(6)]
    assert client.wait_reply(stamps[-1]) is not None
    assert client.wait_diagnostics(base, {"drop_superseded": 1})["drop_superseded"] >= 1
    # every frame is answered or counted: superseded in the size-1 slot, held while stale and replaced by
    # the next, or (a cloud lost by best-effort transport or the reader's KEEP_LAST history) its boxes
    # dropped as boxes_no_cloud
    keys = ("frames_published", "drop_superseded", "drop_stale", "drop_boxes_no_cloud", "drop_cloud_no_boxes")
    end = time.monotonic() + 10.0
    while time.monotonic() < end:
        deltas = {k: client.diag.get(k, 0) - base.get(k, 0) for k in keys}
        if sum(deltas.values()) >= 6:
            break
        time.sleep(0.1)
    assert sum(deltas.values()) == 6, deltas
    assert deltas["frames_published"] == sum(s in client.replies for s in stamps) < 6


# -- tests: bad input ----------------------------------------------------------------------------------

def _bad_field_cloud(frame: KittiFrame, stamp: int, mutate) -> PointCloud2:
    msg = cloud_msg(frame.points, stamp)
    mutate(msg)
    return msg


def _rename_xyz(msg):
    msg.fields = [PointField(name=n, offset=f.offset, datatype=f.datatype, count=1)
                  for n, f in zip("abcd", msg.fields)]


def _bad_datatype(msg):
    msg.fields[0].datatype = 42


def _short_data(msg):
    msg.data = msg.data[: len(msg.data) // 2]


def _big_endian(msg):
    """A correct big-endian encoding of the same points: the node must read it, not just survive it."""
    be = np.frombuffer(bytes(msg.data), dtype="<f4").astype(">f4")
    msg.data = be.tobytes()
    msg.is_bigendian = True


BAD_CLOUDS = {"missing_xyz": _rename_xyz, "unsupported_datatype": _bad_datatype, "short_data": _short_data}


@pytest.mark.parametrize("case", sorted(BAD_CLOUDS))
def test_malformed_cloud_is_skipped(marker_node, frames, case):
    node, client = marker_node
    base = client.settled_diagnostics()
    bad_stamp = client.next_stamp()
    client.send(frames[3], bad_stamp, cloud=_bad_field_cloud(frames[3], bad_stamp, BAD_CLOUDS[case]))
    assert client.send_until_reply(frames[3]) is not None, node.stderr[-2000:]
    assert client.wait_diagnostics(base, {"bad_cloud": 1})["bad_cloud"] == 1
    assert bad_stamp not in client.replies
    assert node.proc.poll() is None
    assert "skipping malformed cloud" in node.stderr


def test_big_endian_cloud_is_decoded(marker_node, frames):
    node, client = marker_node
    stamp = client.next_stamp()
    client.send(frames[3], stamp, cloud=_bad_field_cloud(frames[3], stamp, _big_endian))
    msg = client.wait_reply(stamp)
    assert msg is not None, node.stderr[-2000:]
    check_completion(msg, frames[3], stamp, {0})


def test_nonfinite_points_are_dropped_and_counted(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    pts = frames[3].points.copy()
    pts[::100, 0] = np.nan
    pts[5::200, 2] = np.inf
    n_bad = int((~np.isfinite(pts[:, :3]).all(1)).sum())
    stamp = client.next_stamp()
    client.send(frames[3], stamp, cloud=cloud_msg(pts, stamp))
    msg = client.wait_reply(stamp)
    assert msg is not None, node.stderr[-2000:]
    check_completion(msg, frames[3], stamp, {0})
    assert client.wait_diagnostics(base, {"nonfinite_points": n_bad})["nonfinite_points"] == n_bad


def test_empty_cloud_gets_empty_reply(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    stamp = client.next_stamp()
    client.send(frames[3], stamp, cloud=cloud_msg(np.zeros((0, 4), np.float32), stamp))
    msg = client.wait_reply(stamp)
    assert msg is not None and msg.width * msg.height == 0 and msg.header.frame_id == "velodyne"
    assert client.wait_diagnostics(base, {"skipped_too_few_points": 1})["skipped_too_few_points"] == 1
    assert client.send_until_reply(frames[3]) is not None, node.stderr[-2000:]


def test_frame_without_vehicles_gets_empty_reply_and_empty_marker_array_is_counted(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    stamp = client.send(frames[3], boxes=[])  # only the DELETEALL marker carrying the header
    msg = client.wait_reply(stamp)
    assert msg is not None and msg.width == 0
    client.boxes_pub.publish(MarkerArray())  # no marker, no header: cannot be paired
    assert client.send_until_reply(frames[3]) is not None, node.stderr[-2000:]
    assert client.wait_diagnostics(base, {"boxes_without_header": 1})["boxes_without_header"] == 1
    assert node.proc.poll() is None


def test_degenerate_boxes_are_skipped(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    car = frames[3].boxes[0]
    bad = [Box3D(car.center, (0.0, 1.8, 1.5), car.yaw, "car", 90),
           Box3D(car.center, (4.0, -1.0, 1.5), car.yaw, "car", 91),
           Box3D((math.nan, 0.0, 0.0), car.size, car.yaw, "car", 92)]
    stamp = client.send(frames[3], boxes=frames[3].boxes + bad)
    msg = client.wait_reply(stamp)
    assert msg is not None, node.stderr[-2000:]
    check_completion(msg, frames[3], stamp, {0})
    assert client.wait_diagnostics(base, {"skipped_degenerate_box": 3})["skipped_degenerate_box"] == 3
    assert "skipped vehicles" in node.stderr


def test_boxes_in_another_frame_are_skipped(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    stamp = client.next_stamp()
    other = client.boxes_msg([frames[4].boxes[0]], stamp, "map")
    good = client.boxes_msg(frames[3].boxes, stamp, "velodyne")
    good.markers.extend(m for m in other.markers if m.action == m.ADD)
    client.cloud_pub.publish(cloud_msg(frames[3].points, stamp))
    client.boxes_pub.publish(good)
    msg = client.wait_reply(stamp)
    assert msg is not None
    check_completion(msg, frames[3], stamp, {0})
    assert client.wait_diagnostics(base, {"boxes_wrong_frame": 1})["boxes_wrong_frame"] == 1
    assert "not in the cloud's frame" in node.stderr


def test_unpaired_boxes_and_clouds_are_dropped_and_counted(marker_node, frames):
    node, client = marker_node
    base = client.settled_diagnostics()
    lonely_boxes = client.next_stamp()
    client.boxes_pub.publish(client.boxes_msg(frames[3].boxes, lonely_boxes, "velodyne"))
    lonely_cloud = client.next_stamp()
    client.cloud_pub.publish(cloud_msg(frames[3].points, lonely_cloud))
    time.sleep(0.3)
    assert client.send_until_reply(frames[3]) is not None, node.stderr[-2000:]
    deltas = client.wait_diagnostics(base, {"drop_boxes_no_cloud": 1, "drop_cloud_no_boxes": 1})
    assert deltas == {"drop_boxes_no_cloud": 1, "drop_cloud_no_boxes": 1}
    assert lonely_boxes not in client.replies and lonely_cloud not in client.replies
    # a stream that stops: the waiting cloud is dropped after sync_max_wait (2 s), not kept for ever
    base = client.settled_diagnostics()
    client.cloud_pub.publish(cloud_msg(frames[3].points, client.next_stamp()))
    deltas = client.wait_diagnostics(base, {"drop_cloud_no_boxes": 1}, timeout=6.0)
    assert deltas["drop_cloud_no_boxes"] == 1
    assert client.diag["pending_clouds"] == 0


def test_sigterm_mid_frame_exits_cleanly(ros_context, frames, tmp_path):
    """SIGTERM while frames are being completed: exit code 0 within 10 s, no traceback. Its own node, so the
    test holds in any order and leaves the shared marker node running."""
    with own_node(ros_context, tmp_path, "sigterm") as (node, client):
        client.warm_up(frames[3])  # discovery done both ways: the frames below reach the model
        for _ in range(5):
            client.send(frames[3], client.next_stamp())
            time.sleep(0.1)
        started = time.monotonic()
        assert node.stop(signal.SIGTERM) == 0, node.stderr[-2000:]
        assert time.monotonic() - started < 10.0


# -- lazy output, processing time ----------------------------------------------------------------------

def test_no_model_work_without_subscribers(ros_context, frames, tmp_path):
    """Paired frames are counted, not completed, while nobody subscribes to the output; each completed
    frame's processing time goes out on ~/debug/processing_time_ms."""
    with own_node(ros_context, tmp_path, "lazy", subscribe_output=False) as (node, client):
        end = time.monotonic() + 30.0
        while client.diag.get("frames_without_subscribers", 0) < 3 and time.monotonic() < end:
            client.send(frames[3])
            time.sleep(0.3)
        assert client.diag.get("frames_without_subscribers", 0) >= 3, node.stderr[-2000:]
        assert client.diag["frames_published"] == 0 and client.diag["vehicles_completed"] == 0
        assert client.processing_times == []
        client.subscribe_output()
        client.warm_up(frames[3])
        stamp = client.send(frames[4])
        msg = client.wait_reply(stamp)
        assert msg is not None, node.stderr[-2000:]
        check_completion(msg, frames[4], stamp, {0, 1})
        published = client.settled_diagnostics()["frames_published"]
        end = time.monotonic() + 5.0
        while len(client.processing_times) < published and time.monotonic() < end:
            time.sleep(0.05)
        assert len(client.processing_times) == published >= 2
        assert all(0.0 < t < 60_000.0 for t in client.processing_times)


# -- Detection3DArray, SIGINT, configuration errors ----------------------------------------------------

def test_detection3d_boxes_live_and_sigint(ros_context, frames, tmp_path):
    import interfaces

    msgs = interfaces.import_vision_msgs()
    from kitti_frames import detection_array

    env = interfaces.vision_msgs_env({**os.environ, **ros_context[0]})
    with own_node(ros_context, tmp_path, "detection3d", signal.SIGINT, params=NUMBERED_CLASSES,
                  env=env, boxes_cls=msgs.Detection3DArray) as (node, client):
        assert "vision_msgs/msg/Detection3DArray" in node.stderr
        client.boxes_msg = detection_array
        client.warm_up(frames[3])
        for index, expected in ((4, {0, 1}), (1, {0})):
            stamp = client.send(frames[index])
            msg = client.wait_reply(stamp)
            assert msg is not None, node.stderr[-2000:]
            check_completion(msg, frames[index], stamp, expected)
        base = client.settled_diagnostics()
        stamp = client.send(frames[3], boxes=[])  # an empty Detection3DArray still pairs: empty reply
        msg = client.wait_reply(stamp)
        assert msg is not None and msg.width == 0
        assert client.wait_diagnostics(base, {"frames_published": 1})["frames_published"] == 1


def test_model_size_mismatch_is_a_clear_error(ros_context, tmp_path):
    env, _ = ros_context
    node = NodeProcess(tmp_path, {**BASE_PARAMS, "num_input_points": "999"}, env, "mismatch")
    code = node.proc.wait(90)
    node.stop()
    assert code == 2
    assert "num_input_points=999 does not match the checkpoint" in node.stderr
    assert "Traceback" not in node.stderr


# -- hostile input, live parameters, sim time, configuration errors (issue 11) --------------------------

def test_hostile_boxes_are_screened_and_counted(marker_node, frames):
    """200 duplicates, 20 boxes of 10 km and a box in millimetres next to a real car: the car is completed,
    nothing of the cloud is re-published as measured points of the hostile boxes, every skip is counted."""
    node, client = marker_node
    base = client.settled_diagnostics()
    car = frames[3].boxes[0]
    hostile = ([Box3D(car.center, car.size, car.yaw, "car", 500 + i) for i in range(200)]
               + [Box3D(car.center, (1e4, 1e4, 1e4), 0.0, "car", 800 + i) for i in range(20)]
               + [Box3D(car.center, tuple(s * 1000 for s in car.size), car.yaw, "car", 900)])
    stamp = client.send(frames[3], boxes=frames[3].boxes + hostile)
    msg = client.wait_reply(stamp)
    assert msg is not None, node.stderr[-2000:]
    pts = check_completion(msg, frames[3], stamp, {0})
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1)
    measured = pts["generated"] == 0
    assert len(crop_boxes(xyz[measured], [car], 0.2)[0]) == measured.sum()   # the real car's measured points only
    grown = Box3D(car.center, tuple(s + 1.0 for s in car.size), car.yaw)    # a completion may pass the box a little
    assert len(crop_boxes(xyz, [grown], 0.0)[0]) == len(pts)                 # every published point is the car's
    deltas = client.wait_diagnostics(base, {"skipped_duplicate_box": 200, "skipped_implausible_box": 21})
    assert deltas == {"skipped_duplicate_box": 200, "skipped_implausible_box": 21}


def test_param_set_applied_or_refused(marker_node, frames, ros_context):
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    node, client = marker_node
    params = AsyncParameterClient(client.node, "/marker")
    assert params.wait_for_services(timeout_sec=10.0)

    def set_params(**values) -> list:
        future = params.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        end = time.monotonic() + 10.0
        while not future.done() and time.monotonic() < end:
            time.sleep(0.05)
        return list(future.result().results)

    base = client.settled_diagnostics()
    assert set_params(min_points=100000)[0].successful      # live: no car has that many points
    stamp = client.send(frames[3])
    msg = client.wait_reply(stamp)
    assert msg is not None and msg.width == 0
    assert client.wait_diagnostics(base, {"skipped_too_few_points": 1})["skipped_too_few_points"] >= 1
    assert set_params(min_points=0)[0].successful            # back to the checkpoint's value
    assert client.send_until_reply(frames[3]).width > 0
    assert set_params(measured_merge=False)[0].successful   # live: the network's output as it is
    unmerged = read_points(client.send_until_reply(frames[3]))
    for iid in np.unique(unmerged["instance_id"]).tolist():
        assert (unmerged[unmerged["instance_id"] == iid]["generated"] == 1).sum() == NUM_OUTPUT
    assert set_params(even_spacing=False)[0].successful      # live: the network's points are not moved
    unspaced = read_points(client.send_until_reply(frames[3]))
    xyz = lambda cloud: np.stack([cloud["x"], cloud["y"], cloud["z"]], 1)  # noqa: E731
    assert len(unspaced) == len(unmerged) and not np.allclose(xyz(unspaced), xyz(unmerged), atol=1e-3)
    assert all(r.successful for r in set_params(even_spacing=True, measured_merge=True))
    assert set_params(pool_margin=0.0)[0].successful          # live: the crop's measured points only
    assert not set_params(pool_margin=6.0)[0].successful      # beyond its range
    assert set_params(pool_margin=0.4)[0].successful
    refused = set_params(cloud_topic="elsewhere")[0]          # read-only: refused with a reason
    assert not refused.successful and "read-only" in refused.reason
    refused = set_params(crop_margin=-0.5)[0]                 # in the declared range, but not -1 nor >= 0
    assert not refused.successful and "crop_margin" in refused.reason
    refused = set_params(max_boxes=0)[0]
    assert not refused.successful
    assert "parameters changed: min_points=100000" in node.stderr


def test_sim_time_without_clock_keeps_housekeeping(ros_context, frames, tmp_path):
    with own_node(ros_context, tmp_path, "simtime", params={"use_sim_time": "true"}) as (node, client):
        client.warm_up(frames[3])
        base = client.settled_diagnostics()
        client.cloud_pub.publish(cloud_msg(frames[3].points, client.next_stamp()))   # never gets boxes
        deltas = client.wait_diagnostics(base, {"drop_cloud_no_boxes": 1}, timeout=8.0)
        assert deltas["drop_cloud_no_boxes"] == 1       # expired on the steady clock, diagnostics still flow
        end = time.monotonic() + 10.0
        while "nothing publishes /clock" not in node.stderr and time.monotonic() < end:
            time.sleep(0.2)
        assert node.stderr.count("nothing publishes /clock") == 1


def test_detection_id_beyond_int32_is_hashed(ros_context, frames, tmp_path):
    import zlib

    import interfaces

    msgs = interfaces.import_vision_msgs()
    from kitti_frames import detection_array

    def with_big_id(boxes, stamp_ns, frame_id):
        array = detection_array(boxes, stamp_ns, frame_id)
        for det in array.detections:
            det.id = "99999999999"
        return array
    env = interfaces.vision_msgs_env({**os.environ, **ros_context[0]})
    with own_node(ros_context, tmp_path, "bigid", params=NUMBERED_CLASSES, env=env,
                  boxes_cls=msgs.Detection3DArray) as (node, client):
        client.boxes_msg = with_big_id
        client.warm_up(frames[3])
        msg = client.send_until_reply(frames[3])
        ids = set(read_points(msg)["instance_id"].tolist())
        assert ids == {zlib.crc32(b"99999999999") & 0x7FFFFFFF}
        assert "OverflowError" not in node.stderr


def test_double_sigint_mid_frame_exits_cleanly(ros_context, frames, tmp_path):
    """What `ros2 launch` does on Ctrl-C: SIGINT, then another one, while frames are being completed."""
    with own_node(ros_context, tmp_path, "sigint2", stop_signal=signal.SIGINT) as (node, client):
        client.warm_up(frames[4])
        for _ in range(3):
            client.send(frames[4])
        time.sleep(0.15)
        node.proc.send_signal(signal.SIGINT)
        time.sleep(0.05)
        node.proc.send_signal(signal.SIGINT)
        assert node.proc.wait(timeout=20) == 0, node.stderr[-2000:]
    assert "Traceback" not in node.stderr and "terminate called" not in node.stderr


@pytest.mark.parametrize("args, message", [
    (["-p", "min_points:=abc"], "parameter min_points"),
    (["-p", "crop_margin:=10.0"], "parameter crop_margin"),
    (["--params-file", "/nonexistent/completer.yaml"], "params file"),
    (["-p", "device:=cuda:7"], "device 'cuda:7'"),
    (["-p", "num_input_points:=999"], "num_input_points=999 does not match the checkpoint"),
], ids=["wrong type", "out of range", "missing params file", "no such device", "model size"])
def test_configuration_errors_are_one_line_exit_2(ros_context, tmp_path, args, message):
    env, _ = ros_context
    proc = subprocess.run([sys.executable, "-m", "gd_completion.ros.completer_main", "--ros-args", *args],
                          cwd=REPO, env={**os.environ, **env}, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert "weights_only=False" not in proc.stderr


def test_help_and_unknown_parameters(ros_context, tmp_path):
    env, _ = ros_context
    help_run = subprocess.run([sys.executable, "-m", "gd_completion.ros.completer_main", "--help"], cwd=REPO,
                              env={**os.environ, **env}, capture_output=True, text=True, timeout=60)
    assert help_run.returncode == 0 and "min_points" in help_run.stdout and "live" in help_run.stdout
    node = NodeProcess(tmp_path, {**BASE_PARAMS, "min_point": "5"}, env, "typo")
    try:
        node.wait_ready()
        assert "unknown parameter 'min_point' is ignored (did you mean 'min_points'?)" in node.stderr
    finally:
        assert node.stop(signal.SIGTERM) == 0


def test_track_fusion_live(ros_context, frames, tmp_path):
    """With track_fusion, the same tracked car over three frames: its fused measured points grow, the track is
    counted alive in /diagnostics."""
    params = {"track_fusion": "true", "publish_fused_points": "true", "fusion_expiry": "30.0"}
    with own_node(ros_context, tmp_path, "fusion", params=params) as (node, client):
        client.warm_up(frames[3])
        measured = []
        for _ in range(3):
            msg = client.send_until_reply(frames[3])
            assert msg is not None, node.stderr[-2000:]
            pts = read_points(msg)
            assert set(pts["instance_id"].tolist()) == {0}
            measured.append(int((pts["generated"] == 0).sum()))
            assert NUM_OUTPUT - measured[-1] <= (pts["generated"] == 1).sum() < NUM_OUTPUT
        assert measured[0] < measured[1] < measured[2]          # the track's points accumulate
        diag = client.settled_diagnostics()
        end = time.monotonic() + 5.0
        while "tracks_alive" not in client.diag and time.monotonic() < end:
            time.sleep(0.1)
        assert client.diag["tracks_alive"] == 1 and client.diag["tracks_reset"] == 0
        assert diag["frames_published"] >= 4


def test_reuse_live_publishes_the_cached_completion_and_counts_it(ros_context, frames, tmp_path):
    """The defaults (association, reuse): a parked car seen again 1 s later is published from its cached completion
    (the same generated points, placed by the same box), counted in /diagnostics; an oversized boxes message is
    refused before it is converted."""
    params = {"max_boxes_per_message": "50", "reuse": "true"}
    with own_node(ros_context, tmp_path, "reuse", params=params) as (node, client):
        client.warm_up(frames[3])
        time.sleep(1.0)
        base = client.settled_diagnostics()
        replies = []
        for _ in range(2):
            stamp = client.send(frames[3])
            msg = client.wait_reply(stamp)
            assert msg is not None, node.stderr[-2000:]
            replies.append(read_points(msg))
        deltas = client.wait_diagnostics(base, {"completions_reused": 1, "frames_published": 2})
        assert deltas["completions_reused"] >= 1 and deltas["frames_published"] == 2
        generated = [np.sort(np.stack([p["x"], p["y"], p["z"]], 1)[p["generated"] == 1], axis=0) for p in replies]
        if client.diag["completions_run"] == base["completions_run"]:   # both frames reused: the same points
            np.testing.assert_array_equal(generated[0], generated[1])
        assert NUM_OUTPUT - int((replies[0]["generated"] == 0).sum()) <= len(generated[0]) < NUM_OUTPUT
        car = frames[3].boxes[0]
        crowd = [Box3D((car.center[0] + 10 + i, car.center[1], car.center[2]), car.size, car.yaw, "car", 100 + i)
                 for i in range(60)]
        client.send(frames[3], boxes=crowd)
        assert client.wait_diagnostics(base, {"skipped_box_message_too_large": 1}) == \
            {"skipped_box_message_too_large": 1}
        assert "refused a boxes message" in node.stderr
