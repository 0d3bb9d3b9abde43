"""Completer node end to end: publish -> completed message latency, backlog and peak RSS on a busy frame.

A real KITTI frame (000003, ~113k points) plus 19 copies of its measured car placed around the sensor gives a
~125k-point frame with 20 vehicles; `--pandaset N` replays PandaSet-002 frame N instead (Pandar64, every
annotated cuboid as a box: ~45 vehicles with enough points). The frame is published with fresh stamps at
--rate Hz for --duration s to the node running in a subprocess (shipped weights). Prints latency p50/p95,
how many frames were answered and how the rest were accounted for (superseded by a newer frame = bounded
latency, no backlog), and the node's VmHWM.

    python benchmarks/bench_node.py [--duration 20] [--rate 10] [--vehicles 20] [--pandaset N] [--num-threads 0]
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.append(str(REPO))   # last: a gd_completion on PYTHONPATH (benchmarks/ab_code.sh's worktrees) comes first

from kitti_frames import KittiFrame, cloud_msg, read_frame  # noqa: E402
from ros_live import benchmark_session  # noqa: E402

from gd_completion.geometry import Box3D, crop_boxes  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
KITTI = SHARED / "kitti-object-sample" / "training"


def busy_frame(n_vehicles: int) -> KittiFrame:
    """KITTI frame 000003 with its car copied (points and box) to n_vehicles - 1 more places on a ring."""
    frame = read_frame(KITTI, "000003")
    car = frame.boxes[0]
    idx = crop_boxes(frame.points[:, :3], [car], 0.1)[0]
    local = frame.points[idx].copy()
    local[:, :3] -= np.asarray(car.center, np.float32)
    points, boxes = [frame.points], [car]
    for k in range(1, n_vehicles):
        angle = 2 * math.pi * k / n_vehicles
        rot = angle + 0.3 * k
        c, s = math.cos(rot), math.sin(rot)
        centre = np.array([18 * math.cos(angle), 18 * math.sin(angle), car.center[2]])
        moved = local.copy()
        moved[:, 0] = local[:, 0] * c - local[:, 1] * s + centre[0]
        moved[:, 1] = local[:, 0] * s + local[:, 1] * c + centre[1]
        moved[:, 2] = local[:, 2] + centre[2]
        points.append(moved)
        boxes.append(Box3D(tuple(centre), car.size, car.yaw + rot, "car", 100 + k))
    return KittiFrame("busy", np.concatenate(points), boxes)


def pandaset_frame(index: int) -> KittiFrame:
    """PandaSet-002 frame `index` (Pandar64) with all of its cuboids, labels as a detector would name them."""
    from gd_completion.datasets.pandaset import PandaSetSequence

    frame = PandaSetSequence(SHARED / "pandaset-002").frame(index)[0]
    points = np.concatenate([frame.xyz, frame.intensity[:, None]], 1).astype(np.float32)
    return KittiFrame(f"pandaset-{index:02d}", points, frame.boxes)


def offline(frame: KittiFrame, args: argparse.Namespace) -> None:
    """ms per frame of `VehicleCompleter.complete_frame` on `frame` (min / median of R, after one warm-up): the
    node's processing without transport, publisher or subscriber sharing the cores."""
    import gd_completion
    from gd_completion.pipeline import VehicleCompleter

    completer = VehicleCompleter.from_checkpoint(args.model or None, device=args.device,
                                                 num_threads=args.num_threads or None,
                                                 measured_merge=not args.no_measured_merge)
    threads = completer.threads
    try:
        completer.complete_frame(frame.points[:, :3], frame.boxes)
        times, completed = [], 0
        for _ in range(args.offline):
            start = time.perf_counter()
            done = completer.complete_frame(frame.points[:, :3], frame.boxes)
            times.append(1e3 * (time.perf_counter() - start))
            completed = done.stats.completed
    finally:
        completer.close()
    print(f"frame {frame.index}: {len(frame.points)} points, {len(frame.boxes)} boxes, {completed} vehicles completed; "
          f"complete_frame in this process ({Path(gd_completion.__file__).parent}), {threads} vehicle thread(s), "
          f"measured_merge {not args.no_measured_merge}: "
          f"{min(times):.0f} ms min, {statistics.median(times):.0f} ms median of {len(times)} "
          f"({statistics.median(times) / max(completed, 1):.1f} ms per vehicle)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--vehicles", type=int, default=20)
    ap.add_argument("--pandaset", type=int, default=None, metavar="N", help="replay PandaSet-002 frame N instead")
    ap.add_argument("--num-threads", type=int, default=0, help="node num_threads (0 = one vehicle thread per core)")
    ap.add_argument("--device", default="cpu", help="node device (cpu, cuda or cuda:N)")
    ap.add_argument("--no-measured-merge", action="store_true", help="node parameter measured_merge:=false")
    ap.add_argument("--reuse", action="store_true",
                    help="node parameter reuse:=true (default off here: a repeated frame would be served from the "
                    "cache; benchmarks/bench_live_sequence.py measures reuse on a real sequence)")
    ap.add_argument("--fresh-frame-age", type=float, default=None,
                    help="node parameter fresh_frame_age (default: the node's default)")
    ap.add_argument("--model", default="", help="node parameter model_path (default: the shipped weights)")
    ap.add_argument("--offline", type=int, default=0, metavar="R",
                    help="instead: time the node's core (VehicleCompleter.complete_frame, the node's defaults) on the "
                         "same frame R times in this process, without ROS")
    args = ap.parse_args()

    frame = busy_frame(args.vehicles) if args.pandaset is None else pandaset_frame(args.pandaset)
    if args.offline:
        offline(frame, args)
        return
    params = {"num_threads": str(args.num_threads), "boxes_type": "marker", "device": args.device,
              "measured_merge": "false" if args.no_measured_merge else "true",
              "reuse": "true" if args.reuse else "false",
              **({"model_path": str(Path(args.model).resolve())} if args.model else {}),
              **({"fresh_frame_age": str(args.fresh_frame_age)} if args.fresh_frame_age is not None else {})}
    with benchmark_session(params, "bench") as (node, client):
        client.warm_up(frame, timeout=60)
        time.sleep(3.0)  # let the warm-up frames drain
        base = client.settled_diagnostics()
        sent: dict[int, float] = {}
        period = 1.0 / args.rate
        start = time.monotonic()
        for i in range(int(args.duration * args.rate)):
            target = start + i * period
            time.sleep(max(0.0, target - time.monotonic()))
            stamp = client.next_stamp()
            msg_cloud = cloud_msg(frame.points, stamp)
            sent[stamp] = time.monotonic()
            client.send(frame, stamp, cloud=msg_cloud)
        send_rate = len(sent) / (time.monotonic() - start)
        last = max(sent)
        client.wait_reply(last, timeout=30)
        time.sleep(2.5)
        diag = client.settled_diagnostics()
        hwm = node.peak_rss_mib()
        answered = [s for s in sent if s in client.reply_times]
        lat = np.array([client.reply_times[s] - sent[s] for s in answered]) * 1e3
        thirds = np.array_split(np.array(sorted(answered)), 3)
        third_p50 = [float(np.median([client.reply_times[s] - sent[s] for s in t]) * 1e3) if len(t) else float("nan")
                     for t in thirds]
        delta = {k: int(diag.get(k, 0) - base.get(k, 0)) for k in diag}
        print(f"frame {frame.index}: {len(frame.points)} points, {len(frame.boxes)} boxes; sent {len(sent)} frames at "
              f"{send_rate:.1f} Hz for {args.duration:.0f} s; node num_threads={args.num_threads}, "
              f"device {args.device}, measured_merge {params['measured_merge']}, "
              f"fresh_frame_age {params.get('fresh_frame_age', 'default')}")
        print(f"answered {len(answered)}/{len(sent)} frames ({len(answered) / args.duration:.2f} Hz), "
              f"vehicles completed {delta['vehicles_completed']}")
        if len(lat):
            print(f"end-to-end latency (publish -> completed message received): p50 {np.percentile(lat, 50):.0f} ms, "
                  f"p95 {np.percentile(lat, 95):.0f} ms, max {lat.max():.0f} ms; "
                  f"vehicles completed per answered frame {delta['vehicles_completed'] / len(answered):.1f}")
            print(f"backlog check: p50 latency by thirds of the run {[round(v) for v in third_p50]} ms "
                  "(flat = no backlog growth)")
        print(f"node-side latency (frame paired -> published, recent): p50 {diag['latency_p50_ms']:.0f} ms, "
              f"p95 {diag['latency_p95_ms']:.0f} ms")
        if client.processing_times:
            work = np.array(client.processing_times[-len(answered):])
            print(f"node processing time (~/debug/processing_time_ms, answered frames): p50 {np.median(work):.0f} ms, "
                  f"p95 {np.percentile(work, 95):.0f} ms")
        accounted = delta["frames_published"] + delta["drop_superseded"] + delta["drop_stale"] \
            + delta["drop_cloud_no_boxes"] \
            + delta["drop_boxes_no_cloud"] + delta["drop_cloud_overflow"] + int(diag["pending_clouds"])
        print(f"accounting: published {delta['frames_published']} + superseded {delta['drop_superseded']} + "
              f"stale {delta['drop_stale']} + "
              f"cloud_no_boxes {delta['drop_cloud_no_boxes']} + boxes_no_cloud {delta['drop_boxes_no_cloud']} + "
              f"overflow {delta['drop_cloud_overflow']} + pending {int(diag['pending_clouds'])} = {accounted} "
              f"of {len(sent)} sent")
        print(f"node peak RSS (VmHWM): {hwm:.0f} MiB")


if __name__ == "__main__":
    main()
