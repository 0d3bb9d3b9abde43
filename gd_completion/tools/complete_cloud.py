"""`gd-completion complete-cloud`: complete the vehicles of one point file (PLY, PCD, NPY/NPZ, KITTI .bin)."""
from __future__ import annotations

import argparse
import sys

from gd_completion.settings import add_flags

BOXES_HELP = """boxes (at least one source; they add up):
  --box cx,cy,cz,length,width,height,yaw[,label]   metres and radians in the cloud's frame; label car (default),
                                                   van or truck; instance ids 1, 2, ... in the order given
  --boxes FILE.json   a list of {"center": [x, y, z], "size": [length, width, height], "yaw": 0.0,
                      "label": "car", "id": 7} (yaw, label, id optional; id default: the 1-based position)
  --kitti-label FILE --kitti-calib FILE   KITTI object label_2 + calib: the Car/Van/Truck rows, in the lidar
                      frame; instance id = the 1-based row (DontCare rows not counted)

output: one row per point, fields x y z (float32), instance_id (int32), label (uint8: 1 car, 2 van, 3 truck),
generated (uint8: 0 measured, 1 generated); .ply and .pcd binary little-endian, .npy a structured array.
exit codes: 0 written (boxes with too few points are skipped and listed on stderr, even when that leaves none
completed); 2 bad input (unknown extension, unreadable file, malformed box, no box holding any point) or an
output that exists already (without --overwrite) or cannot be written."""


# The settings that make sense for one cloud (no tracks, no frame budget).
CLOUD_SETTINGS = ("model_path", "device", "num_threads", "min_points", "crop_margin", "pool_margin", "labels",
                  "include_input_points", "measured_merge", "mirror_plane", "even_spacing", "max_points_per_vehicle")


def _run(args: argparse.Namespace) -> int:
    from gd_completion.atomic import refuse_existing
    from gd_completion.cloud_files import READ_SUFFIXES, WRITE_SUFFIXES, read_xyz, suffix_of, write_points_file
    from gd_completion.errors import BoxError
    from gd_completion.settings import from_args
    from gd_completion.single_cloud import (
        complete_cloud_report,
        describe,
        kitti_boxes,
        parse_box,
        points_in_boxes,
        read_boxes_json,
    )

    suffix_of(args.input, READ_SUFFIXES, "point")
    suffix_of(args.output, WRITE_SUFFIXES, "output")
    refuse_existing(args.output, args.overwrite)
    if not (args.box or args.boxes or args.kitti_label or args.kitti_calib):
        raise BoxError("no boxes: give --box, --boxes or --kitti-label with --kitti-calib")
    if (args.kitti_label is None) != (args.kitti_calib is None):
        raise BoxError("--kitti-label and --kitti-calib go together")
    boxes = [parse_box(text, k + 1) for k, text in enumerate(args.box)]
    if args.boxes:
        boxes += read_boxes_json(args.boxes)
    if args.kitti_label:
        boxes += kitti_boxes(args.kitti_label, args.kitti_calib)
    points = read_xyz(args.input)
    counts = points_in_boxes(points, boxes)
    if boxes and not any(counts):
        raise BoxError(f"{args.input}: no point of the cloud ({len(points)} points) lies in any of the "
                       f"{len(boxes)} box(es): {', '.join(describe(b) for b in boxes)} (wrong frame or wrong boxes?)")
    report = complete_cloud_report(points, boxes, from_args(args))
    write_points_file(args.output, report.points, overwrite=args.overwrite)
    for box, reason in report.skipped:
        print(f"gd-completion complete-cloud: skipped {describe(box)}: {reason}", file=sys.stderr)
    if boxes and not report.completed:
        print("gd-completion complete-cloud: warning: no vehicle completed; the output is empty", file=sys.stderr)
    generated = int(report.points["generated"].sum())
    print(f"wrote {args.output}: {len(report.points)} points ({generated} generated), {report.completed} of "
          f"{len(boxes)} vehicles completed, {len(report.skipped)} skipped")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `complete-cloud`."""
    parser = subparsers.add_parser("complete-cloud", help="complete the vehicles of one point file (no bag)",
                                   description=__doc__, epilog=BOXES_HELP,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", help="input points: .ply, .pcd (ascii or binary), .npy/.npz ((N, 3+) array or "
                        "structured with x, y, z; npz: the array 'points' or the first), .bin (KITTI velodyne)")
    parser.add_argument("output", help="output: .ply, .pcd or .npy (written atomically)")
    parser.add_argument("--box", action="append", default=[], metavar="CX,CY,CZ,L,W,H,YAW[,LABEL]",
                        help="a box in the cloud's frame (repeatable)")
    parser.add_argument("--boxes", default=None, metavar="FILE", help="JSON list of boxes (schema below)")
    parser.add_argument("--kitti-label", default=None, metavar="FILE", help="KITTI object label_2 file")
    parser.add_argument("--kitti-calib", default=None, metavar="FILE", help="KITTI object calib file")
    add_flags(parser, CLOUD_SETTINGS)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.set_defaults(func=_run)
