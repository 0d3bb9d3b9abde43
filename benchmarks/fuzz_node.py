"""Fuzz the live completer node: a flood of malformed clouds, hostile boxes and valid frames.

The node runs in a subprocess (shipped weights, marker boxes) and gets --messages messages (default
10,000) as fast as --rate allows, bounded by --max-seconds: malformed PointCloud2 (missing fields, bad
datatypes, short data, NaN/inf points, empty clouds, absurd strides), hostile MarkerArrays (200
duplicates, boxes in millimetres, 10 km boxes, 3,000 car-sized boxes, NaN poses, zero sizes, boxes in
another frame, lonely boxes and clouds) and valid KITTI frames. Before the flood it measures the node's
processing time of a normal frame (~/debug/processing_time_ms); after it, valid frames must still be
answered. Prints: crashes (node exit), valid frames answered after the flood, the costliest message
against a normal frame (target <= 3x), peak RSS (target < 1 GB) and the node's skip counters.

    python benchmarks/fuzz_node.py [--messages 10000] [--rate 400] [--max-seconds 240] [--seed 0]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO))

from kitti_frames import KittiFrame, cloud_msg, read_frame  # noqa: E402
from ros_live import benchmark_session  # noqa: E402
from sensor_msgs.msg import PointField  # noqa: E402

from gd_completion.geometry import Box3D  # noqa: E402

KITTI = REPO.parent / "shared" / "data" / "kitti-object-sample" / "training"


def small_frame() -> KittiFrame:
    """KITTI frame 000003 cut to 12 m around its car: a valid frame with one vehicle."""
    frame = read_frame(KITTI, "000003")
    centre = np.array(frame.boxes[0].center[:2])
    near = ((frame.points[:, :2] - centre) ** 2).sum(1) < 144.0
    return KittiFrame(frame.index, frame.points[near], frame.boxes)


def malformed_cloud(frame: KittiFrame, stamp: int, kind: int, rng: np.random.Generator):
    msg = cloud_msg(frame.points, stamp)
    if kind == 0:
        msg.fields = [PointField(name=n, offset=f.offset, datatype=f.datatype, count=1)
                      for n, f in zip("abcd", msg.fields)]
    elif kind == 1:
        msg.fields[int(rng.integers(len(msg.fields)))].datatype = int(rng.integers(9, 255))
    elif kind == 2:
        msg.data = msg.data[: int(rng.integers(0, len(msg.data)))]
    elif kind == 3:
        pts = frame.points.copy()
        pts[rng.random(len(pts)) < 0.3, int(rng.integers(3))] = rng.choice([np.nan, np.inf, -np.inf])
        msg = cloud_msg(pts, stamp)
    elif kind == 4:
        msg = cloud_msg(np.zeros((0, 4), np.float32), stamp)
    elif kind == 5:
        msg.point_step = int(rng.choice([0, 1, 10**6]))
    else:
        msg.width, msg.height = int(rng.integers(0, 10**7)), int(rng.integers(0, 4))
    return msg


HOSTILE_KINDS = ("200 duplicates", "box in millimetres", "20 boxes of 10 km", "3000 car boxes", "NaN and zero boxes",
                 "boxes in another frame", "int32-max id, huge yaw", "negative id")


def hostile_boxes(frame: KittiFrame, rng: np.random.Generator, kind: int | None = None) -> tuple[list[Box3D], str]:
    car = frame.boxes[0]
    kind = int(rng.integers(8)) if kind is None else kind
    if kind == 0:
        return [Box3D(car.center, car.size, car.yaw, "car", 1000 + i) for i in range(200)], "velodyne"
    if kind == 1:
        return [Box3D(car.center, tuple(s * 1000 for s in car.size), car.yaw, "car", 7)], "velodyne"
    if kind == 2:
        return [Box3D(car.center, (1e4, 1e4, 1e4), 0.0, "car", 8) for _ in range(20)], "velodyne"
    if kind == 3:
        xy = rng.uniform(-60, 60, (3000, 2))
        return [Box3D((float(x), float(y), -0.9), car.size, float(rng.uniform(-3, 3)), "car", i)
                for i, (x, y) in enumerate(xy)], "velodyne"
    if kind == 4:
        return [Box3D((math.nan, 0.0, 0.0), car.size, 0.0, "car", 9), Box3D(car.center, (0.0, 0.0, 0.0), 0.0,
                                                                            "car", 10)], "velodyne"
    if kind == 5:
        return frame.boxes, "map"
    if kind == 6:
        return [Box3D(car.center, car.size, float(rng.uniform(-1e6, 1e6)), "car", 2**31 - 1)], "velodyne"
    return [Box3D(car.center, car.size, car.yaw, "truck", -5)], "velodyne"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=10_000)
    ap.add_argument("--rate", type=float, default=400.0, help="messages per second at most")
    ap.add_argument("--max-seconds", type=float, default=240.0, help="stop the flood after this long")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE",
                    help="extra node parameter (repeatable), e.g. time_budget:=0.05")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    frame = small_frame()
    extra = dict(p.split(":=", 1) for p in args.param)
    print(f"node parameters beyond the defaults: {extra or 'none'}")
    crashed = False
    params = {"num_threads": "0", "boxes_type": "marker", "sync_max_wait": "0.5", **extra}
    with benchmark_session(params, "fuzz") as (node, client):
        client.warm_up(frame, timeout=60)
        for _ in range(10):                       # a normal frame's cost, before the flood
            assert client.send_until_reply(frame) is not None
        time.sleep(1.0)
        normal = float(np.median(client.processing_times))
        before = len(client.processing_times)
        base = client.settled_diagnostics()
        sent = {"malformed cloud": 0, "hostile boxes": 0, "valid frame": 0, "lonely": 0}
        start = time.monotonic()
        for i in range(args.messages):
            if time.monotonic() - start > args.max_seconds:
                break
            time.sleep(max(0.0, start + i / args.rate - time.monotonic()))
            if node.proc.poll() is not None:
                crashed = True
                break
            stamp = client.next_stamp()
            roll = rng.random()
            if roll < 0.4:
                client.send(frame, stamp, cloud=malformed_cloud(frame, stamp, int(rng.integers(7)), rng))
                sent["malformed cloud"] += 1
            elif roll < 0.8:
                boxes, frame_id = hostile_boxes(frame, rng)
                client.cloud_pub.publish(cloud_msg(frame.points, stamp))
                client.boxes_pub.publish(client.boxes_msg(boxes, stamp, frame_id))
                sent["hostile boxes"] += 1
            elif roll < 0.9:
                client.send(frame, stamp)
                sent["valid frame"] += 1
            else:
                pub = client.cloud_pub if rng.random() < 0.5 else client.boxes_pub
                pub.publish(cloud_msg(frame.points, stamp) if pub is client.cloud_pub
                            else client.boxes_msg(frame.boxes, stamp, "velodyne"))
                sent["lonely"] += 1
        flood_s = time.monotonic() - start
        crashed = crashed or node.proc.poll() is not None
        answered_after = sum(client.send_until_reply(frame, timeout=30.0) is not None for _ in range(5))
        alone = {}                                 # each hostile kind again, alone: its own cost
        for kind, name in enumerate(HOSTILE_KINDS):
            boxes, frame_id = hostile_boxes(frame, rng, kind)
            stamp = client.next_stamp()
            seen = len(client.processing_times)
            client.cloud_pub.publish(cloud_msg(frame.points, stamp))
            client.boxes_pub.publish(client.boxes_msg(boxes, stamp, frame_id))
            if client.wait_reply(stamp, timeout=30.0) is not None:
                end = time.monotonic() + 2.0
                while len(client.processing_times) == seen and time.monotonic() < end:
                    time.sleep(0.02)
                alone[name] = client.processing_times[-1]
        time.sleep(2.0)
        diag = client.settled_diagnostics() if not crashed else client.diag
        costs = np.array(client.processing_times[before:]) if len(client.processing_times) > before else np.zeros(1)
        rss = node.peak_rss_mib()
        print(f"flood: {sum(sent.values())} messages in {flood_s:.0f} s ({sent})")
        print(f"crashes: {int(crashed)}; valid frames answered after the flood: {answered_after}/5")
        print(f"processing time: normal frame {normal:.0f} ms; during the flood max {costs.max():.0f} ms "
              f"({costs.max() / normal:.1f}x, target <= 3x), p95 {np.percentile(costs, 95):.0f} ms, "
              f"{len(costs)} frames completed")
        worst = max(alone, key=alone.get) if alone else None
        print("each hostile message alone, processing time: " + ", ".join(f"{k} {v:.0f} ms" for k, v in alone.items()))
        if worst:
            print(f"costliest message alone: {worst}, {alone[worst]:.0f} ms = {alone[worst] / normal:.1f}x a normal "
                  "frame (target <= 3x)")
        print(f"node peak RSS (VmHWM): {rss:.0f} MiB (target < 1024)")
        counters = {k: int(diag.get(k, 0) - base.get(k, 0)) for k in sorted(diag)
                    if (k.startswith(("skipped_", "drop_", "bad_", "boxes_", "errors", "nonfinite"))
                        and diag.get(k, 0) - base.get(k, 0))}
        print(f"counted skips and drops during the flood: {counters}")
    ok = not crashed and answered_after == 5 and node.exit_code == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
