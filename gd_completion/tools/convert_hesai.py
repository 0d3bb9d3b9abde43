"""`gd-completion convert hesai`: raw Hesai packet bags (pandar_msgs/PandarScan) to PointCloud2 scans."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gd_completion.bags.hesai_conversion import DEFAULT_FRAME_ID, DEFAULT_OUTPUT_TOPIC, convert_hesai
from gd_completion.bags.writer import STORAGES
from gd_completion.hesai import load_calibration
from gd_completion.hesai.packets import MODELS


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
    parser.add_argument("--frame-id", default=DEFAULT_FRAME_ID,
                        help=f"frame_id of the clouds (default {DEFAULT_FRAME_ID})")
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


def run_convert_hesai(args: argparse.Namespace) -> int:
    """Convert one packet bag (`gd_completion.bags.hesai_conversion.convert_hesai`); a summary line on stderr."""
    done = convert_hesai(args.source, args.output, load_calibration(args.calibration), model=args.model,
                         frame_id=args.frame_id, input_topic=args.input_topic, output_topic=args.output_topic,
                         storage=args.storage, overwrite=args.overwrite, min_range=args.min_range,
                         max_range=args.max_range, scan_phase=args.scan_phase, host_time=args.time == "host",
                         keep_partial=args.keep_partial, quiet=args.quiet)
    if not args.quiet:
        print(f"{Path(args.output)}: {done.scans} scans, {done.points} points on {args.output_topic}", file=sys.stderr)
    return 0
