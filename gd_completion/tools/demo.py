"""`gd-completion demo`: complete a built-in synthetic drive and write an MCAP bag and PNG renders."""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.atomic import make_folder
from gd_completion.bags.messages import detection3d_array_msg, marker_array_msg, pointcloud2_msg
from gd_completion.bags.typestore import DETECTION3D_ARRAY, MARKER_ARRAY, POINTCLOUD2, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer
from gd_completion.geometry import Box3D, normalize
from gd_completion.pointcloud2 import write_points, xyz_array_to_structured
from gd_completion.render import render_birdseye, render_vehicles
from gd_completion.synth.scene import synthetic_drive

FRAME_ID = "lidar"
TOPICS = {
    "points": ("/points", POINTCLOUD2),
    "markers": ("/boxes/markers", MARKER_ARRAY),
    "detections": ("/boxes/detections", DETECTION3D_ARRAY),
    "completed": ("/completed_vehicles", POINTCLOUD2),
}


@dataclass
class BestView:
    """The frame in which a vehicle had the most measured points, in its normalised box frame."""

    box: Box3D
    measured: np.ndarray
    completion: np.ndarray


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="complete a built-in synthetic drive (no data needed)",
                                   description=__doc__)
    parser.add_argument("--output", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    parser.add_argument("--frames", type=int, default=10, help="frames of the synthetic drive (default 10)")
    parser.add_argument("--vehicles", type=int, default=6, help="vehicles in the scene (default 6)")
    parser.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    parser.add_argument("--model", default="", help="checkpoint (default: the shipped weights)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gd_completion.pipeline import VehicleCompleter, completion_to_structured  # torch: only when running
    started = time.perf_counter()
    make_folder(args.output)  # an unwritable output fails before any work
    frames = synthetic_drive(seed=args.seed, n_frames=args.frames, n_vehicles=args.vehicles)
    completer = VehicleCompleter.from_checkpoint(args.model or None)
    bag_path = args.output / "demo_drive"
    best: dict[int, BestView] = {}
    completed = skipped = 0
    with atomic_bag_writer(bag_path, storage="mcap", overwrite=True) as writer:
        connections = {key: add_connection(writer, topic, msgtype) for key, (topic, msgtype) in TOPICS.items()}

        def put(key: str, msg, stamp_ns: int) -> None:
            writer.write(connections[key], stamp_ns, serialize(msg, TOPICS[key][1]))

        for frame in frames:
            stamp = frame.stamp_ns
            result = completer.complete_frame(frame.points, frame.boxes)
            completed += result.stats.completed
            skipped += result.stats.skipped_total
            cloud = xyz_array_to_structured(np.asarray(frame.points, np.float32),
                                            intensity=np.asarray(frame.intensity, np.float32))
            put("points", pointcloud2_msg(write_points(cloud), FRAME_ID, stamp), stamp)
            put("markers", marker_array_msg(frame.boxes, FRAME_ID, stamp), stamp)
            put("detections", detection3d_array_msg(frame.boxes, FRAME_ID, stamp), stamp)
            put("completed", pointcloud2_msg(write_points(completion_to_structured(result)), FRAME_ID, stamp), stamp)
            for box in frame.boxes:
                rows = result.instance_id == box.instance_id
                measured = result.points[rows & (result.generated == 0)]
                if rows.any() and (box.instance_id not in best or len(measured) > len(best[box.instance_id].measured)):
                    best[box.instance_id] = BestView(box, measured, result.points[rows & (result.generated == 1)])
    items = [(f"{view.box.label} #{key}", normalize(view.measured, view.box),
              normalize(view.completion, view.box), None)
             for key, view in sorted(best.items())]
    vehicles_png = render_vehicles(args.output / "demo_vehicles.png", items) if items else None
    last = frames[-1]
    last_result = completer.complete_frame(last.points, last.boxes)
    frame_png = render_birdseye(args.output / "demo_frame.png", last.points, last.boxes, last_result.points,
                                title="last demo frame: input (blue), boxes, completion (red)")
    print(f"demo: {len(frames)} frames, {completed} vehicle completions, {skipped} skipped, "
          f"{time.perf_counter() - started:.1f} s")
    print(f"  bag (MCAP): {bag_path}")
    if vehicles_png:
        print(f"  vehicles:   {vehicles_png}")
    print(f"  frame:      {frame_png}")
    return 0
