"""The completer live on a real street: PandaSet-002 played at 10 Hz in time order, with and without reuse and load.

PandaSet-002 (Pandar64, 42-47 vehicles per frame) is converted with `gd-completion convert pandaset` to a bag;
its clouds and box markers are published at --rate Hz in time order with fresh stamps into the node (a
subprocess, the shipped weights, the node's defaults but for the parameters named). The 76 frames loop as
long as --duration asks; at each wrap the marker ids are offset, so the tracks start afresh (the built-in
association restarts them anyway: every vehicle jumps back). Each configuration starts a fresh node:
reuse on (the default) and off, alternating, each without and with one busy core of other load (a
`while True` process beside the node: the shared-robot case). Printed per run: frames answered, end-to-end
latency (publish -> completed cloud received) p50/p95, network completions run and reused per answered
frame, and the node's peak RSS; then each round's ratio of reuse-on to reuse-off p95 under the same load.

    python benchmarks/bench_live_sequence.py [--duration 15] [--rounds 2] [--loads none,core] [--reuse on,off]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.append(str(REPO))

from ros_live import benchmark_session  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
CLOUD_TOPIC, MARKER_TOPIC = "/pandar64/points", "/pandar64/markers"
ID_OFFSET = 1_000_000   # added to the marker ids at every wrap of the sequence


def load_sequence(bag_dir: Path) -> list[tuple[object, object]]:
    """(PointCloud2, MarkerArray) per frame of the converted PandaSet bag, in time order."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from gd_completion.bags.dataset_conversion import convert_pandaset
    from gd_completion.bags.reader import iter_raw, open_bag

    convert_pandaset(SHARED / "pandaset-002", bag_dir, sensors=(0,), quiet=True)
    clouds: list[object] = []
    markers: list[object] = []
    with open_bag(bag_dir) as reader:
        wanted = [c for c in reader.connections if c.topic in (CLOUD_TOPIC, MARKER_TOPIC)]
        for conn, _, raw in iter_raw(reader, wanted):
            if conn.topic == CLOUD_TOPIC:
                clouds.append(deserialize_message(bytes(raw), PointCloud2))
            else:
                markers.append(deserialize_message(bytes(raw), MarkerArray))
    if len(clouds) != len(markers) or not clouds:
        raise SystemExit(f"{bag_dir}: {len(clouds)} clouds and {len(markers)} marker arrays")
    return list(zip(clouds, markers))


def stamp(msg_header: object, stamp_ns: int) -> None:
    msg_header.stamp.sec, msg_header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)


def run_once(frames: list[tuple[object, object]], reuse: bool, load: bool, args: argparse.Namespace) -> dict:
    """One fresh node, the sequence played for args.duration s; returns the figures."""
    params = {"boxes_type": "marker", "cloud_topic": "points", "boxes_topic": "detections",
              "reuse": "true" if reuse else "false", **dict(p.split(":=", 1) for p in args.param)}
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if load else None
    try:
        with benchmark_session(params, "bench_live") as (node, client):
            first_cloud, first_markers = frames[0]
            warm = 1_000_000_000_000
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not client.replies:   # discovery, both directions
                warm += 100_000_000
                publish(client, first_cloud, first_markers, warm, 0)
                with client._cond:
                    client._cond.wait_for(lambda: client.replies, timeout=1.0)
            if not client.replies:
                raise RuntimeError("the completer never answered")
            time.sleep(2.0)
            base = client.settled_diagnostics()
            client.replies.clear()
            client.reply_times.clear()
            start_ns = warm + 10_000_000_000   # past every warm-up track's expiry
            sent: dict[int, float] = {}
            period = 1.0 / args.rate
            count = int(args.duration * args.rate)
            start = time.monotonic()
            for k in range(count):
                time.sleep(max(0.0, start + k * period - time.monotonic()))
                cloud, markers = frames[k % len(frames)]
                stamp_ns = start_ns + int(k * period * 1e9)
                sent[stamp_ns] = time.monotonic()
                publish(client, cloud, markers, stamp_ns, (k // len(frames)) * ID_OFFSET)
            client.wait_reply(max(sent), timeout=10)
            time.sleep(2.5)
            diag = client.settled_diagnostics()
            answered = [s for s in sent if s in client.reply_times]
            latency = np.array([client.reply_times[s] - sent[s] for s in answered]) * 1e3
            delta = {k: diag.get(k, 0) - base.get(k, 0) for k in diag}
            work = np.array(client.processing_times[-len(answered):] or [float("nan")])
            published = max(delta.get("frames_published", 0), 1)
            return {"reuse": reuse, "load": load, "sent": len(sent), "answered": len(answered),
                    "p50": float(np.percentile(latency, 50)) if len(latency) else float("nan"),
                    "p95": float(np.percentile(latency, 95)) if len(latency) else float("nan"),
                    "run": delta.get("completions_run", 0) / published,
                    "reused": delta.get("completions_reused", 0) / published,
                    "vehicles": delta.get("vehicles_completed", 0) / published,
                    "deferred": delta.get("skipped_deferred", 0) / published,
                    "rss": node.peak_rss_mib(), "work_p50": float(np.median(work)),
                    "work_p95": float(np.percentile(work, 95))}
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()


def publish(client: object, cloud: object, markers: object, stamp_ns: int, id_offset: int) -> None:
    """Publish one frame with `stamp_ns`; marker ids offset by `id_offset` (ids restored afterwards)."""
    stamp(cloud.header, stamp_ns)
    for m in markers.markers:
        stamp(m.header, stamp_ns)
        m.id += id_offset
    client.cloud_pub.publish(cloud)
    client.boxes_pub.publish(markers)
    for m in markers.markers:
        m.id -= id_offset


def describe(r: dict) -> str:
    return (f"reuse {'on ' if r['reuse'] else 'off'}, {'one busy core' if r['load'] else 'no load     '}: answered "
            f"{r['answered']}/{r['sent']} ({100 * r['answered'] / r['sent']:.0f} %), end-to-end p50 {r['p50']:.0f} ms, "
            f"p95 {r['p95']:.0f} ms (node processing p50 {r['work_p50']:.0f}, p95 {r['work_p95']:.0f} ms); "
            f"per published frame: vehicles {r['vehicles']:.1f}, network runs {r['run']:.1f}, "
            f"reused {r['reused']:.1f}, never-completed deferred {r['deferred']:.1f}; peak RSS {r['rss']:.0f} MiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=15.0, help="seconds played per run (default 15: 2 loops)")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--loads", default="none,core", help="comma-separated: none, core (default both)")
    ap.add_argument("--reuse", default="on,off", help="comma-separated: on, off (alternated within a round)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE", help="extra node parameter")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        frames = load_sequence(Path(tmp) / "pandaset")
    print(f"PandaSet-002, Pandar64: {len(frames)} frames, {args.rate:g} Hz, {args.duration:g} s per run, "
          f"extra parameters {args.param or 'none'}", flush=True)
    loads = [x == "core" for x in args.loads.split(",")]
    reuses = [x == "on" for x in args.reuse.split(",")]
    results = []
    for round_ in range(args.rounds):
        for load in loads:
            for reuse in reuses:
                r = run_once(frames, reuse, load, args)
                results.append((round_, r))
                print(f"round {round_ + 1}: {describe(r)}", flush=True)
    for round_ in range(args.rounds):
        for load in loads:
            pair = {r["reuse"]: r for k, r in results if k == round_ and r["load"] == load}
            if True in pair and False in pair:
                print(f"round {round_ + 1}, {'one busy core' if load else 'no load'}: reuse-on / reuse-off p95 "
                      f"{pair[True]['p95'] / pair[False]['p95']:.2f}")


if __name__ == "__main__":
    main()
