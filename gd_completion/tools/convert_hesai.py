"""`gd-completion convert hesai`: raw Hesai packet bags (pandar_msgs/PandarScan) to PointCloud2 scans."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.lib.recfunctions import repack_fields

from gd_completion.bags.messages import pointcloud2_msg
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import POINTCLOUD2, deserialize, serialize
from gd_completion.bags.writer import STORAGES, add_connection, atomic_bag_writer
from gd_completion.errors import BagError
from gd_completion.hesai import ScanAssembler, load_calibration
from gd_completion.hesai.packets import MODELS, packet_time_s, packets_to_array, parse_packets
from gd_completion.pointcloud2 import write_points
from gd_completion.progress import progress_bar
from gd_completion.stamp_sync import stamp_to_ns

PANDAR_SCAN = "pandar_msgs/msg/PandarScan"
DEFAULT_OUTPUT_TOPIC = "/pandar_points"
CLOUD_FIELDS = ("x", "y", "z", "intensity", "ring", "timestamp")


def add_hesai_parser(convert_subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `hesai` parser under `convert` (called by gd_completion/tools/convert.py)."""
    parser = convert_subparsers.add_parser(
        "hesai", help="Hesai Pandar40/40P/64 packet bag (pandar_msgs/PandarScan) to PointCloud2",
        description="Decodes raw Hesai packets into one PointCloud2 per rotation (cut at --scan-phase) with "
                    "fields x,y,z,intensity (float32), ring (uint16), timestamp (float64 s).")
    parser.add_argument("source", help="input rosbag2 (folder, .db3 or .mcap) with pandar_msgs/PandarScan")
    parser.add_argument("output", help="output bag folder (must not exist unless --overwrite)")
    parser.add_argument("--calibration", required=True, help="angle calibration CSV (Laser id,Elevation,Azimuth)")
    parser.add_argument("--model", choices=("auto", *MODELS), default="auto", help="lidar model (default auto)")
    parser.add_argument("--frame-id", default="hesai_lidar", help="frame_id of the clouds (default hesai_lidar)")
    parser.add_argument("--input-topic", default=None, help="PandarScan topic (default: the only one in the bag)")
    parser.add_argument("--output-topic", default=DEFAULT_OUTPUT_TOPIC, help=f"default {DEFAULT_OUTPUT_TOPIC}")
    parser.add_argument("--storage", choices=STORAGES, default="mcap", help="rosbag2 storage (default mcap)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    parser.add_argument("--min-range", type=float, default=0.3, help="metres (default 0.3)")
    parser.add_argument("--max-range", type=float, default=200.0, help="metres (default 200)")
    parser.add_argument("--scan-phase", type=float, default=0.0, help="cut azimuth in degrees (default 0)")
    parser.add_argument("--time", choices=("host", "sensor"), default="host",
                        help="clock of stamps and point timestamps: 'host' maps the lidar clock onto the packets' "
                             "receive stamps (lines up with other topics); 'sensor' keeps the lidar's own clock")
    parser.add_argument("--keep-partial", action="store_true",
                        help="also write the incomplete first and last rotations of the recording")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and summary")
    parser.set_defaults(func=run_convert_hesai)
    return parser


def _input_connections(reader, topic: str | None, source: Path) -> list:
    conns = [c for c in reader.connections if c.msgtype == PANDAR_SCAN and (topic is None or c.topic == topic)]
    if not conns:
        wanted = f"topic {topic} of type {PANDAR_SCAN}" if topic else f"a {PANDAR_SCAN} topic"
        raise BagError(f"{source}: no {wanted} in the bag")
    if topic is None and len({c.topic for c in conns}) > 1:
        raise BagError(f"{source}: several {PANDAR_SCAN} topics ({sorted({c.topic for c in conns})}); "
                       "choose one with --input-topic")
    return conns


def iter_scans(source: Path, assembler: ScanAssembler, *, topic: str | None = None, host_time: bool = True,
               keep_partial: bool = False):
    """Yield (stamp ns, structured scan) for every rotation in the bag (stamp = earliest point time)."""
    offset_s = 0.0
    emitted = 0
    with open_bag(source) as reader:
        conns = _input_connections(reader, topic, source)
        for conn, bag_ns, raw in iter_raw(reader, conns):
            msg = deserialize(raw, PANDAR_SCAN, f"{source} ({conn.topic} at {bag_ns})")
            assembler.source = f"{source} ({conn.topic} at {bag_ns})"
            packets = [bytes(p.data[: int(p.size)]) for p in msg.packets]
            if not packets:
                continue
            scans = assembler.add(packets)
            if host_time:
                fmt, array = packets_to_array(packets, assembler.model_name, f"{source} ({conn.topic} at {bag_ns})")
                sensor = packet_time_s(fmt, parse_packets(fmt, array))
                host = np.array([stamp_to_ns(p.stamp) for p in msg.packets], dtype=np.float64) * 1e-9
                offset_s = float(np.median(host - sensor))
            for scan in scans:
                emitted += 1
                if emitted == 1 and not keep_partial:
                    continue  # the recording starts mid-rotation
                yield _stamped(scan, offset_s)
        if keep_partial:
            for scan in assembler.flush():
                yield _stamped(scan, offset_s)


def _stamped(scan: np.ndarray, offset_s: float) -> tuple[int, np.ndarray]:
    if offset_s:
        scan = scan.copy()
        scan["timestamp"] += offset_s
    start = float(scan["timestamp"].min()) if scan.size else 0.0
    return int(round(start * 1e9)), scan


def run_convert_hesai(args: argparse.Namespace) -> int:
    """Convert one packet bag; the output appears under its final name only when complete."""
    source, out = Path(args.source), Path(args.output)
    calibration = load_calibration(args.calibration)
    assembler = ScanAssembler(calibration, model=args.model, scan_phase=args.scan_phase,
                              min_range=args.min_range, max_range=args.max_range, source=str(source))
    count, points = 0, 0
    with (atomic_bag_writer(out, storage=args.storage, overwrite=args.overwrite) as writer,
          progress_bar(out.name, "scans", quiet=args.quiet) as bar):
        conn = add_connection(writer, args.output_topic, POINTCLOUD2)
        for ns, scan in iter_scans(source, assembler, topic=args.input_topic, host_time=args.time == "host",
                                   keep_partial=args.keep_partial):
            msg = pointcloud2_msg(write_points(repack_fields(scan[list(CLOUD_FIELDS)])), args.frame_id, ns)
            writer.write(conn, ns, serialize(msg, POINTCLOUD2))
            count += 1
            points += scan.size
            bar.update(1)
        if count == 0:
            raise BagError(f"{source}: no complete rotation decoded (use --keep-partial for short recordings)")
    if not args.quiet:
        print(f"{out}: {count} scans, {points} points on {args.output_topic}", file=sys.stderr)
    return 0
