"""Soak the completer with track fusion on: tracks appearing and expiring for --minutes, memory sampled.

A synthetic street of --tracks vehicles (points on the two sides a sensor at the origin sees, 300 per vehicle)
is published at --rate Hz; every --turnover s a fifth of the vehicles leave and new ones (new track ids) take
their place, so hundreds of tracks live and expire over the run while at most --tracks are alive. The node
(shipped weights, `track_fusion:=true`, `fusion_expiry` 2 s) runs in a subprocess; its resident memory is
sampled every 10 s. Prints the memory at the start, the end and the peak, and the fusion counters.

    python benchmarks/soak_fusion.py [--minutes 10] [--tracks 50] [--rate 10] [--turnover 5]
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

from kitti_frames import KittiFrame  # noqa: E402
from ros_live import benchmark_session  # noqa: E402

from gd_completion.geometry import Box3D  # noqa: E402

SIZE = (4.5, 1.8, 1.5)


def vehicle_points(box: Box3D, rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """Points on the two sides of `box` facing the origin, above its floor, with an intensity column."""
    length, width, height = box.size
    local = rng.uniform(-0.5, 0.5, (n, 3)) * np.array(box.size)
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    to_sensor = -np.array([c * box.center[0] + s * box.center[1], -s * box.center[0] + c * box.center[1]])
    half = n // 2
    local[:half, 0] = math.copysign(length / 2, to_sensor[0])
    local[half:, 1] = math.copysign(width / 2, to_sensor[1])
    local[:, 2] = np.abs(local[:, 2]) * 0.9
    world = local @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) + np.array(box.center) - [0, 0, height / 2]
    return np.concatenate([world, np.zeros((n, 1))], 1).astype(np.float32)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--tracks", type=int, default=50)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--turnover", type=float, default=5.0, help="seconds between two replacements of a fifth")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    slots = [(rng.uniform(6, 40), rng.uniform(-math.pi, math.pi)) for _ in range(args.tracks)]
    ids = list(range(1, args.tracks + 1))
    next_id = args.tracks + 1
    params = {"boxes_type": "marker", "track_fusion": "true", "fusion_expiry": "2.0"}
    with benchmark_session(params, "soak") as (node, client):
        start = time.monotonic()
        stamp_base = client.next_stamp()
        last_turnover = start
        samples: list[tuple[float, float]] = []
        sent = 0
        while time.monotonic() - start < args.minutes * 60:
            now = time.monotonic()
            if now - last_turnover >= args.turnover:
                for k in rng.choice(args.tracks, max(1, args.tracks // 5), replace=False):
                    ids[k] = next_id
                    next_id += 1
                last_turnover = now
            t = now - start
            boxes = [Box3D((r * math.cos(a + 0.01 * t), r * math.sin(a + 0.01 * t), 0.75), SIZE, a + 0.01 * t,
                           "car", ids[k]) for k, (r, a) in enumerate(slots)]
            points = np.concatenate([vehicle_points(b, rng) for b in boxes])
            client.send(KittiFrame("soak", points, boxes), stamp_base + int(t * 1e9))   # stamps follow the clock
            sent += 1
            if not samples or now - samples[-1][0] >= 10.0:
                samples.append((now, node.peak_rss_mib(), node.rss_mib()))
            time.sleep(max(0.0, start + sent / args.rate - time.monotonic()))
        diag = client.settled_diagnostics(timeout=20.0)
        rss = [r for _, _, r in samples]
        print(f"soak: {args.minutes:.0f} min, {sent} frames of {args.tracks} vehicles, {next_id - 1} track ids in all")
        print(f"node resident memory: start {rss[0]:.0f} MiB, end {rss[-1]:.0f} MiB, max {max(rss):.0f} MiB "
              f"(first half max {max(rss[:len(rss) // 2] or rss):.0f}, second half max "
              f"{max(rss[len(rss) // 2:]):.0f}); peak (VmHWM) {samples[-1][1]:.0f} MiB")
        print("fusion counters: " + ", ".join(f"{k} {int(v)}" for k, v in sorted(diag.items())
                                                if k.startswith("tracks_")))
        print(f"frames published {int(diag.get('frames_published', 0))}, vehicles completed "
              f"{int(diag.get('vehicles_completed', 0))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
