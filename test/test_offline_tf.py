"""Offline, boxes in `map` whose transform was recorded after them: `gd-completion complete` reads the bag up to
`transform_wait` further (bag time) before it moves the boxes, as the node's worker waits for /tf live."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gd_completion.bags.completion import complete_bag
from gd_completion.bags.messages import marker_array_msg, pointcloud2_msg, tf_static_msg
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import MARKER_ARRAY, POINTCLOUD2, TF_MESSAGE, deserialize, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer
from gd_completion.geometry import Box3D
from gd_completion.pointcloud2 import read_points, write_points
from gd_completion.settings import CompletionSettings

STAMP = 1_000 * 10**9
CAR = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)   # in the lidar frame


def lidar_in_map(stamp_ns: int) -> np.ndarray:
    """4x4 lidar -> map at `stamp_ns`: driving along x at 2 m/s."""
    pose = np.eye(4)
    pose[:3, 3] = (5.0 + 2.0 * (stamp_ns - STAMP) * 1e-9, 1.0, 0.0)
    return pose


def car_points(rng: np.random.Generator) -> np.ndarray:
    """The car's left side and front, in the lidar frame."""
    length, width, height = CAR.size
    local = rng.uniform(-0.5, 0.5, (800, 3)) * [length, width, height]
    local[:400, 1], local[400:, 0] = width / 2, length / 2
    c, s = math.cos(CAR.yaw), math.sin(CAR.yaw)
    return (local @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + CAR.center).astype(np.float32)


def write_drive(path, late_ns: tuple[int, ...]) -> None:
    """One cloud and its boxes in `map`; /tf samples 0.2 and 0.1 s before the stamp recorded before them, the ones
    at and after the stamp recorded `late_ns` after the boxes."""
    points = car_points(np.random.default_rng(3))
    table = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    table["x"], table["y"], table["z"] = points[:, 0], points[:, 1], points[:, 2]
    in_map = Box3D(tuple(np.add(CAR.center, lidar_in_map(STAMP)[:3, 3])), CAR.size, CAR.yaw, "car", 7)
    with atomic_bag_writer(path, storage="mcap") as writer:
        tf = add_connection(writer, "/tf", TF_MESSAGE)
        cloud = add_connection(writer, "/points", POINTCLOUD2)
        boxes = add_connection(writer, "/tracks", MARKER_ARRAY)
        for ns in (STAMP - 200_000_000, STAMP - 100_000_000):
            writer.write(tf, ns, serialize(tf_static_msg([("map", "lidar", lidar_in_map(ns))], ns), TF_MESSAGE))
        writer.write(cloud, STAMP + 1, serialize(pointcloud2_msg(write_points(table), "lidar", STAMP), POINTCLOUD2))
        writer.write(boxes, STAMP + 2, serialize(marker_array_msg([in_map], "map", STAMP), MARKER_ARRAY))
        for ns, late in zip((STAMP, STAMP + 50_000_000), late_ns):
            writer.write(tf, STAMP + 2 + late,
                         serialize(tf_static_msg([("map", "lidar", lidar_in_map(ns))], ns), TF_MESSAGE))


@pytest.mark.parametrize(("late_ms", "wait", "completed"), [
    ((20, 60), 0.1, True),      # the transform at the stamp comes 20 ms after the boxes: within the wait
    ((20, 60), 0.0, False),     # no wait: the newest transform is 0.1 s old, beyond transform_tolerance
    ((150, 160), 0.1, False),   # it comes after the wait: skipped, counted
])
def test_offline_waits_for_transforms_recorded_after_the_boxes(tmp_path, late_ms, wait, completed):
    bag, out = tmp_path / "drive", tmp_path / "done"
    write_drive(bag, tuple(ms * 1_000_000 for ms in late_ms))
    settings = CompletionSettings.offline(num_threads=1, transform_wait=wait)
    summary = complete_bag(bag, out, settings, cloud_topic="/points", boxes_topic="/tracks", progress=False)
    assert summary.frames == 1
    assert summary.vehicles_completed == int(completed)
    assert summary.boxes_no_transform == int(not completed)
    with open_bag(out) as reader:
        conns = [c for c in reader.connections if c.topic == summary.output_topic]
        (published,) = [read_points(deserialize(raw, POINTCLOUD2)) for _, _, raw in iter_raw(reader, conns)]
    assert (len(published) > 0) == completed
    if completed:   # the car where it is in the lidar frame: the box moved with the transform at its stamp
        centre = np.mean([published["x"], published["y"]], axis=1)
        assert np.linalg.norm(centre - np.array(CAR.center[:2])) < 0.5
