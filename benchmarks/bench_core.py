"""Core timings: PointCloud2 decode and box cropping on a realistic 120k-point frame (median of repeats)."""
from __future__ import annotations

import array
import os
import statistics
import time
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np

from gd_completion.geometry import Box3D, crop_boxes
from gd_completion.pointcloud2 import read_xyz, write_points, xyz_array_to_structured

N_POINTS = 120_000
N_BOXES = 30


def _median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def synthetic_scan(n: int = N_POINTS, seed: int = 0) -> np.ndarray:
    """Lidar-like (n, 3) float32 points: dense near the sensor, thinning with range, ground and clutter."""
    rng = np.random.default_rng(seed)
    r = 2.0 + rng.exponential(18.0, n)
    theta = rng.uniform(-np.pi, np.pi, n)
    z = rng.uniform(-1.9, 1.5, n)
    return np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1).astype(np.float32)


def synthetic_boxes(k: int = N_BOXES, seed: int = 0) -> list[Box3D]:
    """k car-sized boxes scattered within 50 m of the sensor."""
    rng = np.random.default_rng(seed + 1)
    boxes = []
    for i in range(k):
        r, t = rng.uniform(4.0, 50.0), rng.uniform(-np.pi, np.pi)
        boxes.append(Box3D(center=(r * np.cos(t), r * np.sin(t), -0.9),
                           size=(rng.uniform(3.8, 5.2), rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.8)),
                           yaw=float(rng.uniform(-np.pi, np.pi)), instance_id=i))
    return boxes


def hesai_message(points: np.ndarray) -> SimpleNamespace:
    """A PointCloud2-like message in the Hesai driver layout (x y z intensity f32, ring u16, timestamp f64,
    packed, point_step 26), with `data` an array.array('B') as in rclpy messages."""
    n = len(points)
    layout = write_points(xyz_array_to_structured(
        points, intensity=np.linspace(0, 255, n, dtype=np.float32), ring=(np.arange(n) % 64).astype(np.uint16),
        timestamp=1.7e9 + np.arange(n) * 1e-6))
    return SimpleNamespace(height=1, width=n, fields=layout.fields, is_bigendian=False, point_step=layout.point_step,
                           row_step=layout.row_step, is_dense=True, data=array.array("B", layout.data.tobytes()))


def bench_decode(repeats: int = 50) -> float:
    """Median seconds of `read_xyz` on a 120k-point Hesai-layout cloud."""
    msg = hesai_message(synthetic_scan())
    return _median_seconds(lambda: read_xyz(msg), repeats)


def bench_crop(repeats: int = 30) -> float:
    """Median seconds of `crop_boxes` for 120k points and 30 boxes with a 0.2 m margin."""
    points, boxes = synthetic_scan(), synthetic_boxes()
    return _median_seconds(lambda: crop_boxes(points, boxes, margin=0.2), repeats)


def main() -> None:
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"# {os.cpu_count()} cores, load average {load} (wall-clock medians; timings inflate under load)")
    print(f"decode read_xyz  {N_POINTS} pts (Hesai layout, 26 B/pt): {bench_decode() * 1e3:7.3f} ms")
    print(f"crop_boxes       {N_POINTS} pts, {N_BOXES} boxes:           {bench_crop() * 1e3:7.3f} ms")


if __name__ == "__main__":
    main()
