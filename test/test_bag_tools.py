"""`complete`, `play` and `render` on a converted KITTI bag; bad bags fail cleanly with no output."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from interfaces import ros_test_domain_id

from gd_completion import __version__
from gd_completion.bags.completion import complete_bag
from gd_completion.bags.frames import read_frame
from gd_completion.bags.messages import header, marker_array_msg, pointcloud2_msg, stamp
from gd_completion.bags.provenance import read_provenance
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import MARKER_ARRAY, POINTCLOUD2, deserialize, message_class, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer, copy_connection
from gd_completion.cli import main
from gd_completion.errors import GDCompletionError
from gd_completion.geometry import Box3D
from gd_completion.pointcloud2 import read_points, write_points
from gd_completion.ros.player import CLOCK_TOPIC
from gd_completion.settings import CompletionSettings
from gd_completion.stamp_sync import SYNC_TOLERANCE_S, stamp_to_ns

pytestmark = pytest.mark.integration  # processes, ROS nodes, builds or bags: the slow part of the suite

CLOCK = "rosgraph_msgs/msg/Clock"

KITTI = "kitti-object-sample/training"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The shipped weights, else a randomly initialised checkpoint (the bag plumbing is what is tested)."""
    from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, save_checkpoint

    if DEFAULT_WEIGHTS.is_file():
        return str(DEFAULT_WEIGHTS)
    import torch

    from gd_completion.model.config import GGDConfig
    from gd_completion.model.network import GGDNet

    torch.manual_seed(0)
    return str(save_checkpoint(tmp_path_factory.mktemp("model") / "random.pt", GGDNet(GGDConfig())))


@pytest.fixture(scope="module")
def kitti_bag(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bags") / "kitti"
    assert main(["convert", "kitti", str(shared_data / KITTI), str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def completed_bag(kitti_bag: Path, model_path: str) -> Path:
    out = kitti_bag.parent / "kitti_completed"
    assert main(["complete", str(kitti_bag), str(out), "--model", model_path, "--threads", "1", "--quiet"]) == 0
    return out


def _raw(path: Path) -> tuple[dict[str, tuple], dict[str, list[tuple[int, bytes]]]]:
    with open_bag(path) as reader:
        conns = {c.topic: (c.msgtype, c.msgdef.data, c.digest, c.ext.serialization_format,
                           list(c.ext.offered_qos_profiles)) for c in reader.connections}
        messages: dict[str, list] = {}
        for conn, stamp, raw in iter_raw(reader, reader.connections):
            messages.setdefault(conn.topic, []).append((stamp, bytes(raw)))
    return conns, messages


def test_complete_keeps_every_input_message(kitti_bag: Path, completed_bag: Path) -> None:
    in_conns, in_msgs = _raw(kitti_bag)
    out_conns, out_msgs = _raw(completed_bag)
    for topic, meta in in_conns.items():
        assert out_conns[topic] == meta  # type, definition, hash, QoS
        assert out_msgs[topic] == in_msgs[topic]  # count, order, stamps and bytes
    assert set(out_conns) - set(in_conns) == {"/kitti/completed"}
    completed = out_msgs["/kitti/completed"]
    assert [s for s, _ in completed] == [s for s, _ in in_msgs["/kitti/points"]]
    n_generated = 0
    for (_stamp, raw), (_, cloud_raw) in zip(completed, in_msgs["/kitti/points"]):
        msg = deserialize(raw, POINTCLOUD2)
        cloud = deserialize(cloud_raw, POINTCLOUD2)
        assert msg.header.frame_id == cloud.header.frame_id and msg.header.stamp == cloud.header.stamp
        pts = read_points(msg)
        assert pts.dtype.names == ("x", "y", "z", "instance_id", "label", "generated")
        n_generated += int((pts["generated"] == 1).sum())
    assert n_generated > 0


def test_complete_without_measured_merge(kitti_bag: Path, completed_bag: Path, model_path: str, tmp_path: Path
                                        ) -> None:
    """`--no-measured-merge` writes the network's completions as they are (num_output generated points per vehicle,
    no measured point among them) and records it; the default merge keeps some measured points in each."""
    from gd_completion.model.checkpoint import load_model

    out = tmp_path / "unmerged"
    assert main(["complete", str(kitti_bag), str(out), "--model", model_path, "--threads", "1", "--quiet",
                 "--no-measured-merge"]) == 0
    params = json.loads(read_provenance(out)["gd_completion.parameters"])
    assert params["completer"]["measured_merge"] is False
    assert json.loads(read_provenance(completed_bag)["gd_completion.parameters"])["completer"]["measured_merge"]
    assert json.loads(read_provenance(completed_bag)["gd_completion.parameters"])["completer"]["even_spacing"]
    num_output = load_model(model_path).config.num_output
    for bag, merged in ((out, False), (completed_bag, True)):
        vehicles = 0
        for _stamp, raw in _raw(bag)[1]["/kitti/completed"]:
            pts = read_points(deserialize(raw, POINTCLOUD2))
            for iid in np.unique(pts["instance_id"]).tolist():
                generated = int((pts[pts["instance_id"] == iid]["generated"] == 1).sum())
                assert generated < num_output if merged else generated == num_output
                vehicles += 1
        assert vehicles >= 5


def test_complete_sqlite3_output(kitti_bag: Path, model_path: str, tmp_path: Path) -> None:
    out = tmp_path / "done"
    summary = complete_bag(kitti_bag, out, CompletionSettings.offline(model_path=model_path), storage="sqlite3",
                           progress=False, output_topic="/vehicles")
    assert (out / "done.db3").is_file() and summary.frames == 6 and summary.vehicles_completed > 0
    assert "6 frames" in summary.text()
    assert len(_raw(out)[1]["/vehicles"]) == 6


def test_failure_mid_write_leaves_no_output(kitti_bag: Path, tmp_path: Path) -> None:
    class Stub:
        def __init__(self) -> None:
            self.n = 0

        def complete_frame(self, points, boxes):
            self.n += 1
            if self.n == 3:
                raise GDCompletionError("model failed on frame 3")
            from gd_completion.pipeline import FrameCompletion, FrameStats

            return FrameCompletion(np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros(0, np.uint8),
                                   np.zeros(0, np.uint8), FrameStats())

    out = tmp_path / "half"
    with pytest.raises(GDCompletionError, match="frame 3"):
        complete_bag(kitti_bag, out, completer=Stub(), progress=False)
    assert list(tmp_path.iterdir()) == []


def _all_raw(path: Path) -> list[tuple[str, int, bytes]]:
    with open_bag(path) as reader:
        return [(conn.topic, stamp, bytes(raw)) for conn, stamp, raw in iter_raw(reader, reader.connections)]


def test_complete_workers_match_one_process(kitti_bag: Path, completed_bag: Path, model_path: str,
                                            tmp_path: Path) -> None:
    out = tmp_path / "parallel"
    summary = complete_bag(kitti_bag, out, CompletionSettings.offline(model_path=model_path), workers=2, progress=False)
    assert summary.frames == 6 and summary.vehicles_completed > 0
    assert summary.copied_messages == len(_all_raw(kitti_bag))
    assert _raw(out)[0] == _raw(completed_bag)[0]  # connections: types, definitions, QoS
    assert _all_raw(out) == _all_raw(completed_bag)  # every message: topic, order, bag timestamp, bytes
    assert read_provenance(out) == read_provenance(completed_bag)  # the worker count changes nothing


@pytest.mark.parametrize("case", ["missing", "corrupt"])
def test_complete_worker_error_leaves_no_output(case: str, kitti_bag: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
    model = tmp_path / "model.pt"
    if case == "corrupt":
        model.write_bytes(b"not a torch checkpoint")
    out = tmp_path / "out"
    before = sorted(p.name for p in tmp_path.iterdir())
    code = main(["complete", str(kitti_bag), str(out), "--model", str(model), "--workers", "2", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"error: checkpoint {model}: " in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no partial bag


def test_complete_workers_arguments(kitti_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["complete", str(kitti_bag), str(tmp_path / "out"), "--workers", "-1"])
    assert exit_info.value.code == 2 and "--workers: invalid worker count -1" in capsys.readouterr().err
    with pytest.raises(ValueError, match="workers=1"):
        complete_bag(kitti_bag, tmp_path / "out", completer=object(), workers=2)
    assert list(tmp_path.iterdir()) == []


UNKNOWN_TYPE = "acme_msgs/msg/Thing"  # made up: in no typestore, and its bag stores no definition


def _write_bag(path: Path, with_boxes: bool, boxes_frame: str = "lidar", unknown_type: bool = False) -> None:
    cloud = np.zeros(10, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    with atomic_bag_writer(path) as writer:
        pts = add_connection(writer, "/points", POINTCLOUD2)
        other = add_connection(writer, "/other", "pandar_msgs/msg/PandarScan")
        boxes = add_connection(writer, "/boxes", MARKER_ARRAY) if with_boxes else None
        # rosbags writes raw bytes on any type given a definition text (empty here) and a hash
        thing = writer.add_connection("/acme/thing", UNKNOWN_TYPE, msgdef="", rihs01="RIHS01_" + "0" * 64) \
            if unknown_type else None
        for k in range(2):
            if thing is not None:
                writer.write(thing, k, b"\x00\x01\x00\x00" + bytes([k]) * 8)  # CDR header and a payload
            writer.write(pts, k, serialize(pointcloud2_msg(write_points(cloud), "lidar", k), POINTCLOUD2))
            writer.write(other, k, serialize(message_class("pandar_msgs/msg/PandarScan")(
                header=header("lidar", k), packets=[]), "pandar_msgs/msg/PandarScan"))
            if boxes is not None:
                writer.write(boxes, k, serialize(marker_array_msg(
                    [Box3D((1, 2, 0), (4, 2, 1.5), 0.1, "car", 3)], boxes_frame, k), MARKER_ARRAY))


@pytest.mark.parametrize("case", ["truncated", "not_a_bag", "missing", "no_boxes", "unknown_boxes_type",
                                  "cloud_topic_wrong_type", "output_exists"])
def test_bad_bags(case: str, kitti_bag: Path, model_path: str, tmp_path: Path,
                  capsys: pytest.CaptureFixture) -> None:
    src = tmp_path / "in"
    extra: list[str] = []
    if case == "truncated":
        src.mkdir()
        for f in kitti_bag.iterdir():
            data = f.read_bytes()
            (src / f.name).write_bytes(data[: len(data) // 2] if f.suffix == ".mcap" else data)
    elif case == "not_a_bag":
        src.mkdir()
        (src / "metadata.yaml").write_text("this: is not rosbag2 metadata\n")
    elif case == "missing":
        pass
    elif case == "no_boxes":
        _write_bag(src, with_boxes=False)
    elif case == "unknown_boxes_type":
        _write_bag(src, with_boxes=True)
        extra = ["--boxes-topic", "/other"]
    elif case == "cloud_topic_wrong_type":
        _write_bag(src, with_boxes=True)
        extra = ["--cloud-topic", "/boxes"]
    out = tmp_path / "out"
    if case == "output_exists":
        _write_bag(src, with_boxes=True)
        out.mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    code = main(["complete", str(src), str(out), "--model", model_path, "--quiet", *extra])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "error" in err and (str(src) in err or str(out) in err)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no leftovers
    if case != "output_exists":
        assert not out.exists()


def test_marker_boxes_and_unknown_types_are_copied(model_path: str, tmp_path: Path) -> None:
    src = tmp_path / "in"
    _write_bag(src, with_boxes=True)
    summary = complete_bag(src, tmp_path / "out", CompletionSettings.offline(model_path=model_path), progress=False)
    assert summary.frames == 2 and dict(summary.skipped) == {"too_few_points": 2}
    assert _raw(tmp_path / "out")[1]["/other"] == _raw(src)[1]["/other"]


def test_unknown_type_without_definition(model_path: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`complete` cannot copy a topic of an unknown type without a stored definition: it refuses the bag and names
    --skip-unknown-types, which leaves the topic out with a warning and says so in the summary. `render` reads
    only the clouds and boxes and renders the bag as it is."""
    src = tmp_path / "in"
    _write_bag(src, with_boxes=True, unknown_type=True)
    in_conns, in_msgs = _raw(src)
    assert in_conns["/acme/thing"][:3] == (UNKNOWN_TYPE, "", "RIHS01_" + "0" * 64)  # no definition stored
    out = tmp_path / "out"
    assert main(["complete", str(src), str(out), "--model", model_path, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"error: {src}: topic /acme/thing has unknown type {UNKNOWN_TYPE} and no stored definition" in err
    assert "--skip-unknown-types" in err and not out.exists()

    assert main(["complete", str(src), str(out), "--model", model_path, "--quiet", "--skip-unknown-types"]) == 0
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"gd-completion complete: warning: {src}: skipping /acme/thing: type "
                                         f"{UNKNOWN_TYPE} is unknown and the bag stores no definition; not copied"]
    assert "; 6 input messages copied; 2 messages of /acme/thing not copied (unknown type);" in captured.out
    out_conns, out_msgs = _raw(out)
    assert set(out_conns) == {"/points", "/other", "/boxes", "/completed"}
    assert all(out_msgs[topic] == in_msgs[topic] for topic in ("/points", "/other", "/boxes"))

    assert main(["render", str(src), str(tmp_path / "frame.png")]) == 0
    assert (tmp_path / "frame.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_boxes_in_another_frame_are_skipped_and_counted(model_path: str, tmp_path: Path) -> None:
    src = tmp_path / "in"
    _write_bag(src, with_boxes=True, boxes_frame="map")   # the clouds are in "lidar"; the bag has no /tf
    summary = complete_bag(src, tmp_path / "out", CompletionSettings.offline(model_path=model_path), progress=False)
    assert summary.frames == 2 and summary.boxes_no_transform == 2 and dict(summary.skipped) == {}
    assert summary.counters()["boxes_no_transform"] == 2 and "boxes_no_transform 2" in summary.text()
    off = complete_bag(src, tmp_path / "off", CompletionSettings.offline(model_path=model_path, use_tf=False),
                       progress=False)   # without tf the same boxes count as in the wrong frame
    assert off.boxes_wrong_frame == 2 and off.boxes_no_transform == 0


DETECTOR_DELAY_NS = 3_000_000  # the detector stamps its boxes 3 ms after the cloud (and they are recorded later)


@pytest.fixture(scope="module")
def delayed_boxes_bag(kitti_bag: Path) -> Path:
    """The KITTI bag with every boxes message (header, per-detection and per-marker headers, bag time) 3 ms later."""
    out = kitti_bag.parent / "kitti_delayed_boxes"
    with open_bag(kitti_bag) as reader, atomic_bag_writer(out) as writer:
        conns = {conn.id: copy_connection(writer, conn, kitti_bag) for conn in reader.connections}
        for conn, bag_ns, raw in iter_raw(reader, reader.connections):
            if conn.topic in ("/kitti/detections", "/kitti/markers"):
                msg = deserialize(raw, conn.msgtype)
                headers = [msg.header, *(d.header for d in msg.detections)] if conn.topic == "/kitti/detections" \
                    else [m.header for m in msg.markers]
                for hdr in headers:
                    hdr.stamp = stamp(stamp_to_ns(hdr.stamp) + DETECTOR_DELAY_NS)
                raw, bag_ns = serialize(msg, conn.msgtype), bag_ns + DETECTOR_DELAY_NS
            writer.write(conns[conn.id], bag_ns, raw)
    return out


def test_complete_pairs_boxes_within_the_sync_tolerance(delayed_boxes_bag: Path, completed_bag: Path,
                                                        model_path: str, tmp_path: Path) -> None:
    """Boxes stamped 3 ms after their cloud pair as in the node (sync_tolerance 0.05 s): the same completions,
    with the cloud's stamp, header and bag time; with a 1 ms tolerance no frame pairs, as live."""
    delayed = _raw(delayed_boxes_bag)[1]
    assert [s for s, _ in delayed["/kitti/detections"]] == [s + DETECTOR_DELAY_NS for s, _ in
                                                          delayed["/kitti/points"]]
    out = tmp_path / "paired"
    summary = complete_bag(delayed_boxes_bag, out, CompletionSettings.offline(model_path=model_path, num_threads=1),
                           progress=False)
    reference = _raw(completed_bag)[1]["/kitti/completed"]
    assert summary.frames == 6 and summary.sync.paired == 6 and summary.frames_without_boxes == 0
    vehicles = sum(len(np.unique(read_points(deserialize(raw, POINTCLOUD2))["instance_id"])) for _, raw in reference)
    assert summary.vehicles_completed == vehicles > 0
    completed = _raw(out)[1]["/kitti/completed"]
    assert completed == reference  # bag timestamps (the clouds') and bytes, headers included
    for (bag_ns, raw), (cloud_ns, cloud_raw) in zip(completed, delayed["/kitti/points"]):
        msg, cloud = deserialize(raw, POINTCLOUD2), deserialize(cloud_raw, POINTCLOUD2)
        assert bag_ns == cloud_ns and msg.header.stamp == cloud.header.stamp
        assert msg.header.frame_id == cloud.header.frame_id == "velo_link"

    strict = tmp_path / "strict"
    assert main(["complete", str(delayed_boxes_bag), str(strict), "--model", model_path, "--threads", "1",
                 "--quiet", "--sync-tolerance", "0.001"]) == 0
    completed = _raw(strict)[1]["/kitti/completed"]
    assert [s for s, _ in completed] == [s for s, _ in delayed["/kitti/points"]]
    assert all(deserialize(raw, POINTCLOUD2).width == 0 for _, raw in completed)
    assert json.loads(read_provenance(strict)["gd_completion.parameters"])["sync_tolerance"] == 0.001


def test_complete_counts_pairing_as_the_node(delayed_boxes_bag: Path, model_path: str, tmp_path: Path) -> None:
    settings = CompletionSettings.offline(model_path=model_path, num_threads=1, sync_tolerance=0.001)
    summary = complete_bag(delayed_boxes_bag, tmp_path / "out", settings, progress=False)
    counters = summary.counters()
    assert summary.frames == 6 and summary.frames_without_boxes == 6 and summary.vehicles_completed == 0
    assert (counters["frames_paired"], counters["drop_cloud_no_boxes"], counters["drop_boxes_no_cloud"]) == (0, 6, 6)
    assert "drop_cloud_no_boxes 6" in summary.text() and "6 frames without boxes" in summary.text()


def test_render_pairs_as_complete(delayed_boxes_bag: Path, kitti_bag: Path) -> None:
    topic, cloud, boxes, completed = read_frame(delayed_boxes_bag, 1)
    assert topic == "/kitti/points" and completed is None
    assert stamp_to_ns(cloud.header.stamp) == 100_000_000
    assert boxes and boxes == read_frame(kitti_bag, 1)[2]
    assert read_frame(delayed_boxes_bag, 1, sync_tolerance=0.001)[2] == []


def test_complete_records_provenance(completed_bag: Path, model_path: str, tmp_path: Path) -> None:
    """Version, the model's SHA-256 and the parameters in metadata.yaml's custom_data (what `ros2 bag info` reads)."""
    from gd_completion.model.checkpoint import read_checkpoint_metadata

    info = read_provenance(completed_bag)
    assert info["gd_completion.version"] == __version__
    assert info["gd_completion.command"] == "complete"
    assert info["gd_completion.model"] == model_path
    assert info["gd_completion.model_sha256"] == hashlib.sha256(Path(model_path).read_bytes()).hexdigest()
    params = json.loads(info["gd_completion.parameters"])
    assert (params["cloud_topic"], params["boxes_topic"], params["output_topic"]) == (
        "/kitti/points", "/kitti/detections", "/kitti/completed")
    assert params["sync_tolerance"] == SYNC_TOLERANCE_S == 0.05
    completer = params["completer"]
    assert completer["labels"] == ["car", "truck", "van"] and completer["include_input_points"] is True
    config = read_checkpoint_metadata(model_path)["config"]
    assert (completer["num_input_points"], completer["num_output_points"], completer["device"]) == (
        config["num_input"], 2048, "cpu")
    assert completer["preprocessing"]["min_points"] == 20 and completer["preprocessing"]["crop_margin"] == 0.1
    # the sqlite3 storage keeps the same metadata
    out = tmp_path / "db"
    complete_bag(completed_bag, out, CompletionSettings.offline(model_path=model_path, min_points=50),
                 storage="sqlite3", progress=False, output_topic="/again")
    again = read_provenance(out)
    assert again["gd_completion.model_sha256"] == info["gd_completion.model_sha256"]
    assert json.loads(again["gd_completion.parameters"])["completer"]["preprocessing"]["min_points"] == 50


def test_render_completed_bag(completed_bag: Path, tmp_path: Path) -> None:
    assert main(["render", str(completed_bag), str(tmp_path / "frame.png"), "--frame", "1",
                 "--vehicles", str(tmp_path / "vehicles.png")]) == 0
    for name in ("frame.png", "vehicles.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def _play_and_listen(bag: Path, subscriptions: dict[str, type], monkeypatch: pytest.MonkeyPatch,
                     env_extra: dict[str, str | None] | None = None,
                     args: tuple[str, ...] = ("--delay", "0.5", "--wait-for-subscribers", "30"),
                     late: bool = False) -> tuple[dict[str, list[bytes]], str, str]:
    """Run `play` in a subprocess and collect the raw messages a live rclpy subscriber receives.

    `env_extra` changes the player's environment (None removes a variable). Every topic of `subscriptions` but
    /clock is played. `late`: those topics are subscribed only 2 s after the
    player's publishers appear in the graph (the player is up and waiting); /clock is subscribed from the start.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    domain = str(ros_test_domain_id())
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env = {k: v for k, v in {**os.environ, **(env_extra or {})}.items() if v is not None}
    played = [topic for topic in subscriptions if topic != CLOCK_TOPIC]
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("gd_completion_play_test", context=context)
        got: dict[str, list[bytes]] = {topic: [] for topic in subscriptions}
        qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)

        def subscribe(topics: list[str]) -> None:
            for topic in topics:
                node.create_subscription(subscriptions[topic], topic, got[topic].append, qos, raw=True)

        subscribe([topic for topic in subscriptions if not late or topic not in played])
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        player = subprocess.Popen(
            [sys.executable, "-m", "gd_completion.tools.play", str(bag), "--rate", "2", *args, "--topics", *played,
             *(["/kitti/detections"] if "/kitti/detections" not in played else [])],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        started = time.monotonic()
        if late:
            while node.count_publishers(played[0]) == 0 and player.poll() is None and time.monotonic() - started < 45:
                executor.spin_once(timeout_sec=0.05)
            seen = time.monotonic()
            while time.monotonic() - seen < 2.0:  # longer than the --delay and the whole bag at --rate 2
                executor.spin_once(timeout_sec=0.05)
            assert node.count_publishers(played[0]) == 1 and player.poll() is None  # up, waiting for subscribers
            subscribe(played)
        while player.poll() is None and time.monotonic() - started < 45:
            executor.spin_once(timeout_sec=0.05)
        for _ in range(20):
            executor.spin_once(timeout_sec=0.05)
        out, err = player.communicate(timeout=10)
        assert player.returncode == 0, err
        executor.shutdown()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    return got, out, err


def _assert_same_messages(got: dict[str, list[bytes]], recorded: dict[str, list[tuple[int, bytes]]]) -> None:
    for topic, messages in got.items():
        assert len(messages) == len(recorded[topic]), topic
        for live, (_, raw) in zip(messages, recorded[topic]):
            live = bytes(live)  # DDS may pad the payload with zeros to a multiple of 4 bytes
            assert live[:len(raw)] == raw and len(live) - len(raw) < 4 and not any(live[len(raw):]), topic


def test_play_feeds_live_subscriber(kitti_bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    got, out, err = _play_and_listen(kitti_bag, {"/kitti/points": PointCloud2, "/kitti/markers": MarkerArray},
                                     monkeypatch)
    assert "/kitti/points 6" in out and "/kitti/markers 6" in out
    _assert_same_messages(got, _raw(kitti_bag)[1])
    if "/kitti/detections" not in out:  # vision_msgs not importable in the player's environment
        assert "skipping /kitti/detections" in err


def test_play_waits_for_late_subscribers_and_publishes_clock(kitti_bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The subscriptions appear only after the player is up: it waits for them (--wait-subscribers) and delivers
    every message from the first on. With --clock, /clock carries the bag time, from the start of the bag to its
    last message, never backwards, and reaches each message's bag time before that message is published. The
    player's environment names no Fast DDS profile: it sets the large-message one itself (2 MB clouds)."""
    pytest.importorskip("rclpy")
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    got, out, _ = _play_and_listen(kitti_bag, {"/kitti/points": PointCloud2, "/kitti/markers": MarkerArray,
                                               CLOCK_TOPIC: Clock}, monkeypatch,
                                   env_extra={"FASTRTPS_DEFAULT_PROFILES_FILE": None},
                                   args=("--clock", "100", "--wait-subscribers", "60"), late=True)
    assert "/kitti/points 6" in out and "/kitti/markers 6" in out
    recorded = _raw(kitti_bag)[1]
    _assert_same_messages({topic: got[topic] for topic in ("/kitti/points", "/kitti/markers")}, recorded)
    clock = [stamp_to_ns(deserialize(bytes(raw), CLOCK).clock) for raw in got[CLOCK_TOPIC]]
    bag_times = sorted(stamp for topic in ("/kitti/points", "/kitti/markers") for stamp, _ in recorded[topic])
    start = min(stamp for messages in recorded.values() for stamp, _ in messages)
    assert clock == sorted(clock) and clock[0] == start and clock[-1] == bag_times[-1] == 500_000_000
    assert set(bag_times) <= set(clock)


def test_play_detections_with_vision_msgs(kitti_bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    from interfaces import import_vision_msgs, vision_msgs_env

    msgs = import_vision_msgs()  # builds the bindings (cmake + compiler are part of the set-up)
    env = vision_msgs_env()
    got, out, _ = _play_and_listen(kitti_bag, {"/kitti/detections": msgs.Detection3DArray}, monkeypatch, env)
    assert "/kitti/detections 6" in out
    _assert_same_messages(got, _raw(kitti_bag)[1])


def test_foxglove_layout_names_the_written_topics() -> None:
    from gd_completion.bags.dataset_conversion import KITTI_TOPICS
    from gd_completion.bags.topics import default_output_topic
    from gd_completion.datasets import pandaset

    layout = json.loads((REPO / "foxglove" / "gd_completion_layout.json").read_text())
    panels = {k: v for k, v in layout["configById"].items() if k.startswith("3D!")}
    assert panels
    topics = set().union(*(p["topics"] for p in panels.values()))
    expected = {KITTI_TOPICS[0], KITTI_TOPICS[2], default_output_topic(KITTI_TOPICS[0]),
                pandaset.SENSOR_TOPICS[0], pandaset.BOX_TOPICS[1], default_output_topic(pandaset.SENSOR_TOPICS[0])}
    assert expected <= topics
    assert layout["layout"]["first"]["first"] in layout["configById"]


def test_complete_with_track_fusion(shared_data: Path, model_path: str, tmp_path: Path) -> None:
    """A PandaSet bag (track ids from the cuboids' uuids): with --track-fusion a parked car's fused measured points
    grow frame after frame; without it each frame has its own; --workers 2 is refused for fusion."""
    bag = tmp_path / "panda"
    assert main(["convert", "pandaset", str(shared_data / "pandaset-002"), str(bag), "--frames", "4",
                 "--quiet"]) == 0
    plain, fused = tmp_path / "plain", tmp_path / "fused"
    # without the merge, the points published as measured are exactly the frame's (or the track's fused) points: the
    # merge's kept ground-band points (tyres) depend on each completion
    base = ["--model", model_path, "--threads", "1", "--quiet", "--cloud-topic", "/pandar64/points",
            "--no-measured-merge"]
    assert main(["complete", str(bag), str(plain), *base]) == 0
    assert main(["complete", str(bag), str(fused), *base, "--track-fusion", "--publish-fused-points"]) == 0

    def measured_per_frame(path: Path) -> list[dict[int, int]]:
        with open_bag(path) as reader:
            conns = [c for c in reader.connections if c.topic == "/pandar64/completed"]
            frames = []
            for conn, _, raw in iter_raw(reader, conns):
                pts = read_points(deserialize(raw, conn.msgtype))
                ids, counts = np.unique(pts["instance_id"][pts["generated"] == 0], return_counts=True)
                frames.append(dict(zip(ids.tolist(), counts.tolist())))
            return frames
    def measured_points(path: Path) -> list[np.ndarray]:
        with open_bag(path) as reader:
            conns = [c for c in reader.connections if c.topic == "/pandar64/completed"]
            return [np.stack([(p := read_points(deserialize(raw, conn.msgtype)))[a][p["generated"] == 0]
                              for a in "xyz"], 1) for conn, _, raw in iter_raw(reader, conns)]
    plain_counts, fused_counts = measured_per_frame(plain), measured_per_frame(fused)
    assert len(fused_counts) == 4
    seen_all = set.intersection(*(set(f) for f in fused_counts))
    assert seen_all, "no vehicle completed in all four frames"
    for track in seen_all:
        fused_track = [f[track] for f in fused_counts]
        assert fused_track == sorted(fused_track) and fused_track[-1] > fused_track[0]   # accumulates
        assert fused_track[-1] > max(f[track] for f in plain_counts)                      # more than any frame
    # --no-fusion-align: the same points per frame, stored where the boxes put them (the first frame unmoved)
    unaligned = tmp_path / "unaligned"
    assert main(["complete", str(bag), str(unaligned), *base, "--track-fusion", "--publish-fused-points",
                 "--no-fusion-align"]) == 0
    assert measured_per_frame(unaligned) == fused_counts
    first, moved = measured_points(fused), measured_points(unaligned)
    assert first[0].tobytes() == moved[0].tobytes() and first[-1].tobytes() != moved[-1].tobytes()
    code = main(["complete", str(bag), str(tmp_path / "refused"), *base, "--track-fusion", "--workers", "2"])
    assert code == 2 and not (tmp_path / "refused").exists()
