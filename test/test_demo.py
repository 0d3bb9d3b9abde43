"""`gd-completion demo`, the README's first command, on a small drive: bag, renders, completed vehicles."""
from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import deserialize
from gd_completion.box_messages import detections_to_boxes, markers_to_boxes
from gd_completion.geometry import Box3D, crop_boxes
from gd_completion.pointcloud2 import read_points

REPO = Path(__file__).resolve().parents[1]
NUM_OUTPUT = 2048  # points of a completion with the shipped model
LABEL_IDS = {"car": 1, "van": 2, "truck": 3}  # README: label uint8, 1 car, 2 van, 3 truck
TOPICS = {"/points": "sensor_msgs/msg/PointCloud2", "/boxes/markers": "visualization_msgs/msg/MarkerArray",
          "/boxes/detections": "vision_msgs/msg/Detection3DArray",
          "/completed_vehicles": "sensor_msgs/msg/PointCloud2"}

pytestmark = pytest.mark.integration  # a process that loads the model and writes a bag


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("demo") / "out"
    proc = subprocess.run([sys.executable, "-m", "gd_completion.cli", "demo", "--frames", "2", "--vehicles", "2",
                           "--output", str(out)], cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc.stdout


def read_bag(bag: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(bag time ns, message)] in bag order; the connection types are checked against TOPICS."""
    messages = defaultdict(list)
    with open_bag(bag) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TOPICS
        for conn, t, raw in iter_raw(reader):
            messages[conn.topic].append((t, deserialize(raw, conn.msgtype, str(bag))))
    return messages


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_demo_writes_bag_and_renders(demo_run):
    out, stdout = demo_run
    assert (out / "demo_drive").is_dir()
    for png in ("demo_vehicles.png", "demo_frame.png"):
        data = (out / png).read_bytes()
        assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 10_000, png
    assert "demo: 2 frames" in stdout and str(out / "demo_drive") in stdout


def test_demo_bag_holds_completed_vehicles(demo_run):
    out, stdout = demo_run
    messages = read_bag(out / "demo_drive")
    assert {topic: len(msgs) for topic, msgs in messages.items()} == dict.fromkeys(TOPICS, 2)
    completed = 0
    for k in range(2):
        t, cloud = messages["/points"][k]
        detections = detections_to_boxes(messages["/boxes/detections"][k][1])
        markers = markers_to_boxes(messages["/boxes/markers"][k][1])
        assert detections.boxes == markers.boxes and len(detections.boxes) == 2
        boxes = {b.instance_id: b for b in detections.boxes}
        assert read_points(cloud).dtype.names == ("x", "y", "z", "intensity") and cloud.width > 50_000
        msg = messages["/completed_vehicles"][k][1]
        assert messages["/completed_vehicles"][k][0] == t == stamp_ns(msg) == stamp_ns(cloud)
        assert msg.header.frame_id == cloud.header.frame_id == "lidar"
        pts = read_points(msg)
        assert pts.dtype.names == ("x", "y", "z", "instance_id", "label", "generated")
        for iid in np.unique(pts["instance_id"]).tolist():
            mine = pts[pts["instance_id"] == iid]
            box = boxes[iid]
            measured = int((mine["generated"] == 0).sum())
            assert NUM_OUTPUT - measured <= (mine["generated"] == 1).sum() < NUM_OUTPUT   # merged: <= measured
            assert measured > 0 and (mine["label"] == LABEL_IDS[box.label]).all()
            xyz = np.stack([mine["x"], mine["y"], mine["z"]], axis=1)
            grown = Box3D(box.center, tuple(s + 1.0 for s in box.size), box.yaw)  # 0.5 m on every side
            assert len(crop_boxes(xyz, [grown], 0.0)[0]) >= 0.9 * len(xyz)
            completed += 1
    assert completed >= 1
    assert f"{completed} vehicle completions" in stdout
