"""`gd-completion complete`: copy a bag byte for byte and add the completed vehicles of every cloud."""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from gd_completion.association import TRACK_ID_MODES
from gd_completion.atomic import refuse_existing
from gd_completion.bags.messages import pointcloud2_msg
from gd_completion.bags.pairing import BagPairing, RecordedCloud
from gd_completion.bags.provenance import completer_parameters, provenance, set_provenance
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.topics import DEFAULT_CLOUD_TOPICS, default_output_topic, pick_topics
from gd_completion.bags.typestore import POINTCLOUD2, serialize
from gd_completion.bags.writer import STORAGES, add_connection, atomic_bag_writer, copy_connection, has_definition
from gd_completion.errors import BagError, GDCompletionError
from gd_completion.frame_pool import FramePool, InOrder
from gd_completion.limits import OFFLINE_LIMITS
from gd_completion.pointcloud2 import read_xyz, write_points
from gd_completion.progress import progress_bar
from gd_completion.stamp_sync import SYNC_TOLERANCE_S, SyncCounters


@dataclass
class CompletionSummary:
    """What `complete` did; the counters have the names the node reports in /diagnostics."""

    frames: int = 0  # completed clouds written: one per input cloud
    copied_messages: int = 0
    vehicles_completed: int = 0
    skipped: Counter = field(default_factory=Counter)  # vehicles per reason (`skipped_<reason>` in the node)
    ignored_labels: int = 0
    nonfinite_points: int = 0
    completions_run: int = 0      # vehicles the network completed
    completions_reused: int = 0   # vehicles written from their track's cached completion (--reuse)
    boxes_wrong_frame: int = 0
    boxes_without_header: int = 0
    sync: SyncCounters = field(default_factory=SyncCounters)
    seconds: float = 0.0
    output_topic: str = ""
    not_copied: dict[str, int] = field(default_factory=dict)  # topic -> messages left out (--skip-unknown-types)

    @property
    def frames_without_boxes(self) -> int:
        """Clouds the node would not have paired with boxes (their completion is empty)."""
        return self.frames - self.sync.paired

    def counters(self) -> dict[str, int]:
        """Every counter under the node's diagnostics key."""
        values = {"vehicles_completed": self.vehicles_completed, "ignored_labels": self.ignored_labels,
                  **{f"skipped_{reason}": n for reason, n in sorted(self.skipped.items())},
                  "boxes_wrong_frame": self.boxes_wrong_frame, "boxes_without_header": self.boxes_without_header,
                  "nonfinite_points": self.nonfinite_points, "completions_run": self.completions_run,
                  "completions_reused": self.completions_reused}
        for key, n in self.sync.as_dict().items():
            values["frames_paired" if key == "paired" else f"drop_{key}"] = n
        return values

    def text(self) -> str:
        """Human-readable summary: the frames, then every non-zero counter."""
        rate = self.frames / self.seconds if self.seconds > 0 else 0.0
        counts = ", ".join(f"{k} {v}" for k, v in self.counters().items() if v and k != "vehicles_completed")
        left_out = "".join(f"; {n} message{'s' if n != 1 else ''} of {topic} not copied (unknown type)"
                           for topic, n in self.not_copied.items())
        return (f"{self.frames} frames ({rate:.1f} frames/s, {self.seconds:.1f} s), "
                f"{self.vehicles_completed} vehicles completed, {self.frames_without_boxes} frames without boxes; "
                f"{counts or 'no other counts'}; {self.copied_messages} input messages copied{left_out}; "
                f"completions on {self.output_topic}")

    def add(self, stats: Any) -> None:
        """Count one frame's FrameStats."""
        self.frames += 1
        self.vehicles_completed += int(stats.completed)
        self.skipped.update(stats.skipped)
        self.ignored_labels += stats.ignored_labels
        self.nonfinite_points += stats.nonfinite_points
        self.completions_run += stats.completions_run
        self.completions_reused += stats.completions_reused


def start_fusion(pool: FramePool, publish_fused_points: bool, align: bool = True) -> None:
    """Give the pool's in-process completer a fresh track accumulator (one per bag); `align` False stores the
    frames as their boxes place them (`FusionLimits.align` None)."""
    from gd_completion.fusion import FusionLimits, TrackFusion

    if pool.completer is None:
        raise BagError("track fusion needs every frame of a bag in order in one process: use --workers 1")
    pool.completer.fusion = TrackFusion(FusionLimits() if align else FusionLimits(align=None))
    pool.completer.publish_fused_points = publish_fused_points


def start_tracks(pool: FramePool, reuse: bool) -> None:
    """Give the pool's in-process completer a fresh association of box ids (one per bag) and, with `reuse`, a fresh
    completion cache (no frame budget: what is written never depends on the machine's load)."""
    from gd_completion.association import BoxAssociator
    from gd_completion.reuse import CompletionCache, ReuseSettings

    if pool.completer is None:
        raise BagError("track fusion and reuse need every frame of a bag in order in one process: use --workers 1")
    pool.completer.associator = BoxAssociator()
    pool.completer.cache = CompletionCache(ReuseSettings()) if reuse else None


def complete_bag(src: str | Path, out: str | Path, *, cloud_topic: str | None = None,
                 boxes_topic: str | None = None, output_topic: str | None = None, model: str | None = None,
                 storage: str = "mcap", completer: Any = None, overwrite: bool = False,
                 progress: bool = True, workers: int = 1, sync_tolerance: float = SYNC_TOLERANCE_S,
                 skip_unknown_types: bool = False, pool: FramePool | None = None, track_fusion: bool = False,
                 publish_fused_points: bool = False, fusion_align: bool = True, reuse: bool = False,
                 **completer_options: Any) -> CompletionSummary:
    """Copy every message of `src` into a new bag `out` and add one completed cloud per cloud message.

    Clouds and boxes are paired as the node pairs them (stamps within `sync_tolerance` seconds); a cloud the
    node would leave unpaired gets an empty completion. Completions carry the cloud's header and bag timestamp.
    `completer_options` go to `VehicleCompleter.from_checkpoint` (device, num_threads, min_points, labels,
    limits: default `OFFLINE_LIMITS`, no time budget, so the output never depends on the machine's load).
    `workers` > 1 completes frames in that many spawned processes; the output bag is the same as with
    `workers=1`, message for message and in the same write order. An injected `completer` works only with
    `workers=1`. A `pool` given is used (and left open) instead of one made from `workers`, `model`,
    `completer_options` and `completer`, so many bags can share it. The bag's metadata records the package
    version, the model's SHA-256 and the parameters.
    `track_fusion`: each tracked vehicle (box id = track id) is completed from its points of all the bag's
    frames so far (a fresh `fusion.TrackFusion` per bag; frames in order, so in this process only);
    `publish_fused_points` writes the fused measured points instead of each frame's own; `fusion_align` False
    turns off the alignment of each frame to its track (box jitter). `reuse`: a tracked vehicle's network
    completion runs only when due (`reuse.CompletionCache`, default settings, no frame budget), as the node's
    reuse. With either, the boxes get the track ids of the completer's `track_ids` (completer option; default
    "message", the command's --track-ids associate) from a fresh association per bag.
    A topic of a type with no stored definition and unknown here cannot be copied: BagError, unless
    `skip_unknown_types`, which leaves it out with a warning on stderr (counted in `summary.not_copied`).
    """
    from gd_completion.model.checkpoint import DEFAULT_WEIGHTS
    from gd_completion.pipeline import completion_to_structured

    completer_options.setdefault("limits", OFFLINE_LIMITS)
    summary = CompletionSummary()
    start = time.perf_counter()
    with open_bag(src) as reader:
        cloud_topic, boxes_topic, boxes_type = pick_topics(reader, cloud_topic, boxes_topic)
        output_topic = output_topic or default_output_topic(cloud_topic)
        summary.output_topic = output_topic
        if output_topic in {c.topic for c in reader.connections}:
            raise BagError(f"{src}: output topic {output_topic} exists in the input bag; choose --output-topic")
        pairing = BagPairing(cloud_topic, boxes_topic, boxes_type, tolerance_s=sync_tolerance, source=str(src))
        copied = [c for c in reader.connections if has_definition(c) or not skip_unknown_types]
        for conn in (c for c in reader.connections if c not in copied):
            print(f"gd-completion complete: warning: {src}: skipping {conn.topic}: type {conn.msgtype} is unknown and "
                  "the bag stores no definition; not copied", file=sys.stderr)
            summary.not_copied[conn.topic] = summary.not_copied.get(conn.topic, 0) + conn.msgcount
        total = sum(c.msgcount for c in reader.connections if c.topic == cloud_topic)
        in_flight = 2 * (pool.workers if pool is not None else workers)
        queue: InOrder[Any] = InOrder(max_in_flight=in_flight)  # memory stays flat on long bags
        waiting = {}  # cloud index -> its slot in the queue, until its pairing is decided
        try:
            frames = nullcontext(pool) if pool is not None else FramePool(workers, model, completer_options, completer)
            with (frames as pool,
                  atomic_bag_writer(out, storage=storage, overwrite=overwrite) as writer,
                  progress_bar("complete", "frames", total=total, quiet=not progress) as bar):
                conns = {conn.id: copy_connection(writer, conn, src) for conn in copied}
                out_conn = add_connection(writer, output_topic, POINTCLOUD2)
                stamped = track_fusion or reuse
                if stamped:
                    start_tracks(pool, reuse)
                if track_fusion:
                    start_fusion(pool, publish_fused_points, fusion_align)

                def submit(decided: list[tuple[RecordedCloud, Any]]) -> None:
                    """Submit the clouds whose boxes are known (or known to be none)."""
                    for cloud, box_set in decided:
                        boxes, wrong_frame = cloud.boxes_in_frame(box_set)
                        summary.boxes_wrong_frame += wrong_frame
                        queue.start(waiting.pop(cloud.index), pool.submit(read_xyz(cloud.msg), boxes,
                                                                          cloud.stamp_ns if stamped else None))

                def write(ready: Any) -> None:
                    """Copies as they are; a completion right after its cloud, with its header and bag time."""
                    for item, result in ready:
                        if isinstance(item, RecordedCloud):
                            summary.add(result.stats)
                            msg = pointcloud2_msg(write_points(completion_to_structured(result)),
                                                  item.msg.header.frame_id, item.stamp_ns)
                            writer.write(out_conn, item.bag_ns, serialize(msg, POINTCLOUD2))
                            bar.update(1)
                        else:
                            writer.write(*item)
                            summary.copied_messages += 1

                for conn, timestamp, raw in iter_raw(reader, copied):
                    queue.put((conns[conn.id], timestamp, raw))
                    cloud, decided = pairing.feed(conn.topic, timestamp, raw)
                    if cloud is not None:
                        waiting[cloud.index] = queue.hold(cloud)
                    submit(decided)
                    write(queue.ready())
                submit(pairing.close())
                write(queue.rest())
                parameters = {"completer": pool.run(completer_parameters).result(), "cloud_topic": cloud_topic,
                              "boxes_topic": boxes_topic, "output_topic": output_topic,
                              "sync_tolerance": sync_tolerance}
                set_provenance(writer, provenance("complete", model or DEFAULT_WEIGHTS, parameters))
        except BrokenProcessPool as error:
            raise GDCompletionError(f"{src}: a completion worker process died ({error}); no output written "
                                    "(out of memory? try fewer --workers)") from error
    summary.sync = pairing.counters
    summary.boxes_without_header = pairing.boxes_without_header
    summary.seconds = time.perf_counter() - start
    return summary


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
