"""`gd-completion render`: bird's-eye PNG (and per-vehicle views) of one frame of a bag."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from gd_completion.atomic import refuse_existing
from gd_completion.bags.frames import read_frame
from gd_completion.geometry import normalize
from gd_completion.pointcloud2 import read_points, read_xyz
from gd_completion.render import render_birdseye, render_vehicles
from gd_completion.settings import add_flags, from_args
from gd_completion.stamp_sync import SYNC_TOLERANCE_S


def render_bag_frame(bag: str | Path, out: str | Path, *, frame: int = 0, cloud_topic: str | None = None,
                     boxes_topic: str | None = None, completed_topic: str | None = None,
                     vehicles_out: str | Path | None = None, max_vehicles: int = 12,
                     sync_tolerance: float = SYNC_TOLERANCE_S, overwrite: bool = False) -> list[Path]:
    """Render frame `frame` (index among the cloud messages) of `bag`; returns the written PNG paths.

    The per-vehicle image shows the `max_vehicles` completed vehicles with the most measured points. An existing
    PNG is replaced only with `overwrite` (OutputError before any work otherwise).
    """
    for path in (out, vehicles_out):
        if path is not None:
            refuse_existing(path, overwrite)
    cloud_topic, cloud, boxes, completed = read_frame(bag, frame, cloud_topic=cloud_topic, boxes_topic=boxes_topic,
                                                      completed_topic=completed_topic,
                                                      sync_tolerance=sync_tolerance)
    points = read_xyz(cloud)
    comp = read_points(completed) if completed is not None else None
    generated = comp[comp["generated"] == 1] if comp is not None and "generated" in comp.dtype.names else comp
    written = [render_birdseye(out, points, boxes, generated,
                               title=f"{Path(bag).name} {cloud_topic} frame {frame}: input (blue), boxes, "
                                     f"completion (red)")]
    if vehicles_out is not None and comp is not None and "instance_id" in comp.dtype.names:
        xyz = np.stack([comp["x"], comp["y"], comp["z"]], axis=1).astype(np.float32)
        items = []
        for box in boxes:
            rows = comp["instance_id"] == box.instance_id
            if not rows.any():
                continue
            measured = normalize(xyz[rows & (comp["generated"] == 0)], box)
            gen = normalize(xyz[rows & (comp["generated"] == 1)], box)
            items.append((f"{box.label} #{box.instance_id}", measured, gen, None))
        items.sort(key=lambda item: -len(item[1]))
        if items:
            written.append(render_vehicles(vehicles_out, items[:max_vehicles]))
    return written


def _run(args: argparse.Namespace) -> int:
    paths = render_bag_frame(args.bag, args.output, frame=args.frame, cloud_topic=args.cloud_topic,
                             boxes_topic=args.boxes_topic, completed_topic=args.completed_topic,
                             vehicles_out=args.vehicles, max_vehicles=args.max_vehicles,
                             sync_tolerance=from_args(args).sync_tolerance, overwrite=args.overwrite)
    for path in paths:
        print(f"wrote {path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `render`."""
    parser = subparsers.add_parser("render", help="bird's-eye PNG of one frame of a bag", description=__doc__)
    parser.add_argument("bag", help="rosbag2 (e.g. the output of `complete`)")
    parser.add_argument("output", help="PNG path (written atomically; must not exist unless --overwrite)")
    parser.add_argument("--frame", type=int, default=0, help="index of the cloud message (default 0)")
    parser.add_argument("--cloud-topic", default=None)
    parser.add_argument("--boxes-topic", default=None)
    parser.add_argument("--completed-topic", default=None, help="default: <namespace>/completed")
    add_flags(parser, ["sync_tolerance"])
    parser.add_argument("--vehicles", default=None, help="also write per-vehicle side/top views to this PNG")
    parser.add_argument("--max-vehicles", type=int, default=12,
                        help="vehicles in the --vehicles image, most measured points first (default 12)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing PNGs")
    parser.set_defaults(func=_run)
