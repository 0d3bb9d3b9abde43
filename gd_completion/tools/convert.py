"""`gd-completion convert`: KITTI and PandaSet recordings to rosbag2 (PointCloud2, boxes, /tf_static)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gd_completion.bags.dataset_conversion import ConversionCounts, convert_kitti, convert_pandaset
from gd_completion.bags.writer import STORAGES
from gd_completion.tools.convert_hesai import add_hesai_parser


def _report(args: argparse.Namespace, counts: ConversionCounts) -> int:
    """One warning line on stderr per kind of lacking frame (also with --quiet), then the summary."""
    for line in counts.problems():
        print(f"gd-completion convert: warning: {args.source}: {line}", file=sys.stderr)
    print(f"wrote {args.output}: {counts.text()}")
    return 0


def _run_kitti(args: argparse.Namespace) -> int:
    return _report(args, convert_kitti(Path(args.source), Path(args.output), storage=args.storage,
                                       limit=args.frames, sequence=args.sequence, overwrite=args.overwrite,
                                       quiet=args.quiet))


def _run_pandaset(args: argparse.Namespace) -> int:
    sensors = [int(s) for s in args.sensors.split(",") if s.strip()]
    return _report(args, convert_pandaset(Path(args.source), Path(args.output), storage=args.storage,
                                          limit=args.frames, sensors=sensors, start=args.start,
                                          overwrite=args.overwrite, quiet=args.quiet))


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="dataset folder")
    parser.add_argument("output", help="output bag folder (must not exist)")
    parser.add_argument("--storage", choices=STORAGES, default="mcap", help="rosbag2 storage (default mcap)")
    parser.add_argument("--frames", type=int, default=None, help="convert at most this many frames")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and notes")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `convert kitti`, `convert pandaset` and `convert hesai`."""
    parser = subparsers.add_parser("convert", help="convert a dataset to a rosbag2 recording",
                                   description=__doc__)
    sub = parser.add_subparsers(dest="dataset", required=True)
    kitti_parser = sub.add_parser("kitti", help="KITTI object split, tracking split or raw drive",
                                  description="Boxes are transformed to the lidar frame (velo_link); the object "
                                              "split has no timestamps and gets 10 Hz synthetic stamps.")
    _common(kitti_parser)
    kitti_parser.add_argument("--sequence", default=None, help="tracking sequence (default: the first)")
    kitti_parser.set_defaults(func=_run_kitti)
    panda_parser = sub.add_parser("pandaset", help="PandaSet sequence (lidar/*.npz + cuboids/*.json, or the "
                                                   "devkit's lidar/*.pkl.gz + annotations/cuboids/*.pkl.gz)",
                                  description="Points and cuboids move from the world frame into the lidar frame "
                                              "using lidar/poses.json. Reads the npz/json layout or the official "
                                              "devkit layout (gzip-compressed pandas pickles; needs pandas, and "
                                              "unpickling runs code: convert only trusted folders).")
    _common(panda_parser)
    panda_parser.add_argument("--sensors", default="0,1", help="sensor ids: 0 Pandar64, 1 PandarGT (default 0,1)")
    panda_parser.add_argument("--start", type=int, default=0, help="first frame index (default 0)")
    panda_parser.set_defaults(func=_run_pandaset)
    add_hesai_parser(sub)
