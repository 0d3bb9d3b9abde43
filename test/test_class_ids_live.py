"""Numeric class ids: never guessed (skipped, counted, warned about once), mapped by a preset, and the same bag
completes the same vehicles live and offline."""
from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("rclpy")
from kitti_frames import detection_array  # noqa: E402
from test_node_live import frames, own_node, ros_context  # noqa: E402, F401  (fixtures)
from test_tf_live import max_centre_error  # noqa: E402

from gd_completion.bags.messages import detection3d_array_msg, pointcloud2_msg  # noqa: E402
from gd_completion.bags.typestore import DETECTION3D_ARRAY, POINTCLOUD2, deserialize, serialize  # noqa: E402
from gd_completion.bags.writer import add_connection, atomic_bag_writer  # noqa: E402
from gd_completion.class_maps import CLASS_PRESETS, class_table, map_label  # noqa: E402
from gd_completion.pointcloud2 import read_points, write_points  # noqa: E402

pytestmark = pytest.mark.integration
OPENPCDET_IDS = {"car": "1", "van": "1", "truck": "1"}   # kitti_frames.detection_array numbers car 1, van 2, truck 3


def test_presets_map_their_detectors_classes():
    assert {map_label(c, class_table("kitti")) for c in ("Car", "Van", "Truck", "Pedestrian", "Cyclist")} == {
        "car", "van", "truck", "ignore"}
    assert [map_label(c, class_table("nuscenes")) for c in ("car", "bus", "vehicle.construction", "pedestrian")] == [
        "car", "truck", "truck", "ignore"]
    assert [map_label(c, class_table("autoware")) for c in ("car", "truck", "trailer", "bicycle")] == [
        "car", "truck", "truck", "ignore"]
    assert [map_label(c, class_table("openpcdet_kitti")) for c in ("1", "2", "3")] == ["car", "ignore", "ignore"]
    for preset in CLASS_PRESETS:   # no preset but OpenPCDet's names a numeric id; none is ever guessed
        numeric = [k for k in CLASS_PRESETS[preset] if k.isdigit()]
        assert (preset == "openpcdet_kitti") == bool(numeric)
        assert map_label("7", class_table(preset)) == "unmapped:7"
    assert map_label("7", class_table("names", ["7:truck", ""])) == "truck"


def write_numbered_bag(path, frame, stamp: int) -> None:
    """One cloud and its Detection3DArray with OpenPCDet's numeric class ids."""
    table = np.zeros(len(frame.points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    table["x"], table["y"], table["z"] = frame.points[:, 0], frame.points[:, 1], frame.points[:, 2]
    boxes = [replace(b, label=OPENPCDET_IDS[b.label]) for b in frame.boxes]
    with atomic_bag_writer(path, storage="mcap") as writer:
        cloud = add_connection(writer, "/points", POINTCLOUD2)
        dets = add_connection(writer, "/detections", DETECTION3D_ARRAY)
        writer.write(cloud, stamp, serialize(pointcloud2_msg(write_points(table), "velodyne", stamp), POINTCLOUD2))
        writer.write(dets, stamp + 1, serialize(detection3d_array_msg(boxes, "velodyne", stamp), DETECTION3D_ARRAY))


def test_numeric_ids_live_and_offline(ros_context, frames, tmp_path):  # noqa: F811
    import interfaces

    msgs = interfaces.import_vision_msgs()
    env = interfaces.vision_msgs_env({**os.environ, **ros_context[0]})
    frame = frames[4]
    cars = len(frame.boxes)
    with own_node(ros_context, tmp_path, "ids", params={"boxes_type": "detection3d"}, env=env,
                  boxes_cls=msgs.Detection3DArray) as (node, client):
        client.boxes_msg = detection_array
        client.warm_up(frame)
        base = client.settled_diagnostics()
        for _ in range(2):
            msg = client.send_until_reply(frame)
            assert msg is not None and msg.width == 0
        assert client.wait_diagnostics(base, {"unmapped_class_ids": 2 * cars})["unmapped_class_ids"] >= 2 * cars
        assert node.stderr.count("numeric class ids") == 1 and "(ids: 1)" in node.stderr
    with own_node(ros_context, tmp_path, "pcdet", params={"boxes_type": "detection3d",
                                                           "class_preset": "openpcdet_kitti"},
                  env=env, boxes_cls=msgs.Detection3DArray) as (node, client):
        client.boxes_msg = detection_array
        client.warm_up(frame)
        stamp = client.next_stamp()
        live = None
        for _ in range(5):
            client.send(frame, stamp)
            msg = client.wait_reply(stamp, timeout=10.0)
            if msg is not None:
                live = read_points(msg)
                break
            stamp = client.next_stamp()
        assert live is not None and set(np.unique(live["instance_id"]).tolist()) == {b.instance_id for b in frame.boxes}

    from gd_completion.bags.completion import complete_bag
    from gd_completion.bags.reader import iter_raw, open_bag
    from gd_completion.settings import CompletionSettings

    bag = tmp_path / "numbered"
    write_numbered_bag(bag, frame, stamp)
    unmapped = complete_bag(bag, tmp_path / "none", CompletionSettings.offline(num_threads=1), progress=False)
    assert unmapped.vehicles_completed == 0 and unmapped.unmapped_class_ids == cars
    mapped = complete_bag(bag, tmp_path / "done", CompletionSettings.offline(num_threads=1,
                                                                             class_preset="openpcdet_kitti"),
                          progress=False)
    assert mapped.vehicles_completed == cars
    with open_bag(tmp_path / "done") as reader:
        conns = [c for c in reader.connections if c.topic == mapped.output_topic]
        [offline] = [read_points(deserialize(raw, POINTCLOUD2)) for _, _, raw in iter_raw(reader, conns)]
    assert max_centre_error(live, offline) <= 0.01
