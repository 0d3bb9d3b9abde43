"""`gd-completion complete`: copy a bag byte for byte and add the completed vehicles of every cloud (argument
parsing; the work is `bags.completion.complete_bag` and, for many bags, `tools.complete_many`)."""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from gd_completion.association import TRACK_ID_MODES
from gd_completion.atomic import refuse_existing
from gd_completion.bags.completion import complete_bag
from gd_completion.bags.topics import DEFAULT_CLOUD_TOPICS
from gd_completion.bags.writer import STORAGES
from gd_completion.limits import OFFLINE_LIMITS
from gd_completion.stamp_sync import SYNC_TOLERANCE_S


def _bounded(convert: Callable[[str], float], lo: float, hi: float, what: str, expected: str) -> Callable[[str], Any]:
    """argparse type: `convert(text)` in [lo, hi], else an error naming `what` and what was `expected`."""
    def parse(text: str) -> Any:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {what} {text!r}: expected {expected}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"invalid {what} {value}: expected {expected}")
        return value
    return parse


_workers = _bounded(int, 0, math.inf, "worker count", "an integer >= 0 (0 = one per CPU core)")
_tolerance = _bounded(float, 0.0, 10.0, "tolerance", "seconds in [0, 10]")


def _run(args: argparse.Namespace) -> int:
    from gd_completion.tools import complete_many as many

    options: dict[str, Any] = {"device": args.device}
    if args.threads:
        options["num_threads"] = args.threads
    if args.min_points is not None:
        options["min_points"] = args.min_points
    if args.labels:
        options["labels"] = [label.strip().lower() for label in args.labels.split(",") if label.strip()]
    options["limits"] = replace(OFFLINE_LIMITS, time_budget_s=args.time_budget or math.inf)
    if args.no_measured_merge:
        options["measured_merge"] = False
    options["track_ids"] = args.track_ids
    if args.engine == "local" and many.is_single_bag(args.input):
        workers = args.workers or os.cpu_count() or 1
        summary = complete_bag(args.input[0], args.output, cloud_topic=args.cloud_topic,
                               boxes_topic=args.boxes_topic, output_topic=args.output_topic, model=args.model,
                               storage=args.storage, overwrite=args.overwrite, progress=not args.quiet,
                               workers=workers, sync_tolerance=args.sync_tolerance,
                               skip_unknown_types=args.skip_unknown_types, track_fusion=args.track_fusion,
                               publish_fused_points=args.publish_fused_points,
                               fusion_align=not args.no_fusion_align, reuse=args.reuse, **options)
        print(f"wrote {args.output}: {summary.text()}")
        return 0
    if many.is_single_bag(args.input):  # --engine ray on one bag: OUTPUT is still the output bag
        refuse_existing(args.output, args.overwrite)
        jobs = [many.BagJob(Path(args.input[0]), Path(args.output))]
    else:
        jobs = many.plan_jobs(args.input, args.output)
    workers = args.workers or (1 if args.address else os.cpu_count() or 1)
    start = time.perf_counter()
    outcomes = many.complete_many(
        jobs, engine=args.engine, workers=workers, model=args.model, address=args.address,
        overwrite=args.overwrite, progress=not args.quiet, report=many.print_line, completer_options=options,
        cloud_topic=args.cloud_topic, boxes_topic=args.boxes_topic, output_topic=args.output_topic,
        storage=args.storage, sync_tolerance=args.sync_tolerance, skip_unknown_types=args.skip_unknown_types,
        track_fusion=args.track_fusion, publish_fused_points=args.publish_fused_points,
        fusion_align=not args.no_fusion_align, reuse=args.reuse)
    for outcome in outcomes:
        if outcome.status == "skipped":
            many.print_line(outcome)
    failed = [o for o in outcomes if o.status == "failed"]
    print(many.summary_text(outcomes, time.perf_counter() - start))
    for outcome in failed:
        print(f"gd-completion complete: error: {outcome.detail}", file=sys.stderr)
    return 2 if failed else 0


def add_sync_tolerance(parser: argparse.ArgumentParser) -> None:
    """`--sync-tolerance`: the node's `sync_tolerance` (also used by `render`)."""
    parser.add_argument("--sync-tolerance", type=_tolerance, default=SYNC_TOLERANCE_S, metavar="SECONDS",
                        help="largest stamp difference between a cloud and its boxes, as the node's sync_tolerance "
                             f"parameter (default {SYNC_TOLERANCE_S})")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `complete`."""
    parser = subparsers.add_parser("complete", help="complete the vehicles of every frame of a bag",
                                   description=__doc__)
    parser.add_argument("input", nargs="+",
                        help="input rosbag2 (folder, .mcap or .db3); or several, a quoted glob ('bags/*') or a "
                             "manifest (.txt: one bag per line, # comments)")
    parser.add_argument("output", help="output bag (written atomically; must not exist); with several inputs a "
                        "folder that gets one bag per input, named after it (existing ones are skipped: a rerun "
                        "resumes)")
    parser.add_argument("--cloud-topic", default=None, help="PointCloud2 topic (default: the only one, or "
                        + ", ".join(DEFAULT_CLOUD_TOPICS) + ")")
    parser.add_argument("--boxes-topic", default=None,
                        help="Detection3DArray or MarkerArray topic (default: the first Detection3DArray topic)")
    parser.add_argument("--output-topic", default=None, help="completed cloud topic (default: <namespace>/completed)")
    add_sync_tolerance(parser)
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    parser.add_argument("--storage", choices=STORAGES, default="mcap", help="output storage (default mcap)")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--threads", type=int, default=0,
                        help="CPU threads completing a frame's vehicles in parallel, one torch thread each "
                        "(default: one per core in one process, 1 per worker with --workers > 1)")
    parser.add_argument("--workers", type=_workers, default=1, metavar="N",
                        help="complete frames in N processes (default 1: in this process, its vehicles on "
                        "--threads threads); 0 = one per core. The output bag is the same for every N")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help="local: bags one after the other in this process (frames on --workers processes); "
                             "ray: one bag per Ray task on --workers workers (default local)")
    parser.add_argument("--address", default=None,
                        help="with --engine ray: the Ray cluster ('auto', 'HOST:6379' or 'ray://HOST:10001'; "
                             "default: start a local Ray with --workers CPUs)")
    parser.add_argument("--track-fusion", action="store_true",
                        help="complete each tracked vehicle (track ids: --track-ids) from its points of all frames so "
                        "far, as the node's track_fusion (frames in order: --workers 1)")
    parser.add_argument("--publish-fused-points", action="store_true",
                        help="with --track-fusion, write the fused measured points instead of each frame's own")
    parser.add_argument("--no-fusion-align", action="store_true",
                        help="with --track-fusion, store each frame as its box places it, without aligning it to "
                        "its track (as the node's fusion_align:=false)")
    parser.add_argument("--reuse", action="store_true",
                        help="run the network for a tracked vehicle only when it is due (new points, box size change, "
                        "age: the node's reuse, without its frame budget) and write its last completion placed by "
                        "the current box otherwise (frames in order: --workers 1)")
    parser.add_argument("--track-ids", choices=TRACK_ID_MODES, default="associate",
                        help="with --track-fusion or --reuse, the track id of each box: associate (built-in "
                        "association of consecutive frames' boxes), message (the boxes' ids) or off (default "
                        "associate, as the node)")
    parser.add_argument("--no-measured-merge", action="store_true",
                        help="write the network's completions as they are, as the node's measured_merge:=false "
                        "(default: thinned together with the measured points fed to the network and their mirror "
                        "image)")
    parser.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="seconds of completion per frame, as the node's time_budget (default: none offline, so "
                        "the output never depends on the machine's load)")
    parser.add_argument("--min-points", type=int, default=None,
                        help="skip vehicles with fewer measured points (default: the checkpoint's, 20)")
    parser.add_argument("--labels", default=None, help="comma-separated labels to complete (default car,van,truck)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    parser.add_argument("--skip-unknown-types", action="store_true",
                        help="leave out (with a warning) topics whose type is unknown and has no definition stored "
                             "in the bag; without it such a bag is refused, as it cannot be copied whole")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)
