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


def write_drive(path, early_ms: tuple[int, ...] = (-200, -100), late: tuple[tuple[int, int], ...] = ()) -> None:
    """One cloud and its boxes in `map`; /tf samples at `early_ms` from the stamp recorded before them, and the
    samples (ms from the stamp, ms recorded after the boxes) of `late`."""
    points = car_points(np.random.default_rng(3))
    table = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    table["x"], table["y"], table["z"] = points[:, 0], points[:, 1], points[:, 2]
    in_map = Box3D(tuple(np.add(CAR.center, lidar_in_map(STAMP)[:3, 3])), CAR.size, CAR.yaw, "car", 7)
    with atomic_bag_writer(path, storage="mcap") as writer:
        tf = add_connection(writer, "/tf", TF_MESSAGE)
        cloud = add_connection(writer, "/points", POINTCLOUD2)
        boxes = add_connection(writer, "/tracks", MARKER_ARRAY)

        def sample(at_ms: int, recorded_ns: int) -> None:
            ns = STAMP + at_ms * 1_000_000
            msg = tf_static_msg([("map", "lidar", lidar_in_map(ns))], ns)
            writer.write(tf, recorded_ns, serialize(msg, TF_MESSAGE))

        for at_ms in early_ms:
            sample(at_ms, STAMP + min(at_ms * 1_000_000, 0))
        writer.write(cloud, STAMP + 1, serialize(pointcloud2_msg(write_points(table), "lidar", STAMP), POINTCLOUD2))
        writer.write(boxes, STAMP + 2, serialize(marker_array_msg([in_map], "map", STAMP), MARKER_ARRAY))
        for at_ms, after_ms in late:
            sample(at_ms, STAMP + 2 + after_ms * 1_000_000)


def complete(bag, out, wait: float):
    """(summary, published points) of `gd-completion complete` on the drive with `transform_wait` = `wait`."""
    settings = CompletionSettings.offline(num_threads=1, transform_wait=wait)
    summary = complete_bag(bag, out, settings, cloud_topic="/points", boxes_topic="/tracks", progress=False)
    with open_bag(out) as reader:
        conns = [c for c in reader.connections if c.topic == summary.output_topic]
        (published,) = [read_points(deserialize(raw, POINTCLOUD2)) for _, _, raw in iter_raw(reader, conns)]
    return summary, published


@pytest.mark.parametrize(("late_ms", "wait", "completed"), [
    ((20, 60), 0.1, True),      # the transform at the stamp comes 20 ms after the boxes: within the wait
    ((20, 60), 0.0, False),     # no wait: the newest transform is 0.1 s old, beyond transform_tolerance
    ((150, 160), 0.1, False),   # it comes after the wait: skipped, counted
])
def test_offline_waits_for_transforms_recorded_after_the_boxes(tmp_path, late_ms, wait, completed):
    bag = tmp_path / "drive"
    write_drive(bag, late=((0, late_ms[0]), (50, late_ms[1])))
    summary, published = complete(bag, tmp_path / "done", wait)
    assert summary.frames == 1
    assert summary.vehicles_completed == int(completed)
    assert summary.boxes_no_transform == int(not completed)
    assert (len(published) > 0) == completed
    if completed:   # the car where it is in the lidar frame: the box moved with the transform at its stamp
        centre = np.mean([published["x"], published["y"]], axis=1)
        assert np.linalg.norm(centre - np.array(CAR.center[:2])) < 0.5


def test_offline_waits_to_interpolate_when_the_newest_transform_is_within_tolerance(tmp_path):
    """The newest transform recorded before the boxes is 30 ms old (within transform_tolerance): the node waits for
    the next one and interpolates, and so does the offline tool (the same output as when it was recorded in time);
    without the wait it holds the 30 ms old one (the same output as when the next one never comes)."""
    in_time, late, never = tmp_path / "in_time", tmp_path / "late", tmp_path / "never"
    write_drive(in_time, early_ms=(-200, -30, 50))
    write_drive(late, early_ms=(-200, -30), late=((50, 20),))
    write_drive(never, early_ms=(-200, -30))
    _, reference = complete(in_time, tmp_path / "a", 0.1)
    _, waited = complete(late, tmp_path / "b", 0.1)
    _, held = complete(late, tmp_path / "c", 0.0)
    _, old = complete(never, tmp_path / "d", 0.1)
    assert len(reference) > 0 and waited.tobytes() == reference.tobytes()
    assert held.tobytes() == old.tobytes() != reference.tobytes()
