"""`gd-completion complete`: copy a bag byte for byte and add the completed vehicles of every cloud."""
from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import sys
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion import bagio
from gd_completion.box_messages import BoxSet
from gd_completion.errors import BagError, GDCompletionError
from gd_completion.geometry import Box3D
from gd_completion.pointcloud2 import read_xyz, write_points

DEFAULT_CLOUD_TOPICS = ("/kitti/points", "/pandar64/points", "/points")


@dataclass
class CompletionSummary:
    """What `complete` did."""

    frames: int = 0
    copied_messages: int = 0
    vehicles_completed: int = 0
    skipped: Counter = field(default_factory=Counter)
    frames_without_boxes: int = 0
    ignored_boxes: int = 0
    seconds: float = 0.0
    output_topic: str = ""

    def text(self) -> str:
        """Human-readable summary."""
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(self.skipped.items())) or "none"
        rate = self.frames / self.seconds if self.seconds > 0 else 0.0
        return (f"{self.frames} frames ({rate:.1f} frames/s, {self.seconds:.1f} s), "
                f"{self.vehicles_completed} vehicles completed, skipped: {reasons}; "
                f"{self.ignored_boxes} boxes of other classes ignored; "
                f"{self.frames_without_boxes} frames without boxes; {self.copied_messages} input messages copied; "
                f"completions on {self.output_topic}")


def default_output_topic(cloud_topic: str) -> str:
    """'/kitti/points' -> '/kitti/completed'; '/points' -> '/completed'."""
    parent = cloud_topic.rstrip("/").rpartition("/")[0]
    return f"{parent}/completed"


def pick_topics(reader: Any, cloud_topic: str | None, boxes_topic: str | None) -> tuple[str, str, str]:
    """(cloud topic, boxes topic, boxes type) of a bag; BagError naming the bag when ambiguous or absent."""
    types = {c.topic: c.msgtype for c in reader.connections}
    clouds = sorted(t for t, ty in types.items() if ty == bagio.POINTCLOUD2)
    if cloud_topic is None:
        preferred = [t for t in DEFAULT_CLOUD_TOPICS if t in clouds]
        if len(clouds) == 1 or preferred:
            cloud_topic = clouds[0] if len(clouds) == 1 else preferred[0]
        elif not clouds:
            raise BagError(f"{reader.path}: no sensor_msgs/msg/PointCloud2 topic")
        else:
            raise BagError(f"{reader.path}: several PointCloud2 topics ({', '.join(clouds)}); choose --cloud-topic")
    elif cloud_topic not in types:
        raise BagError(f"{reader.path}: no topic {cloud_topic}")
    elif types[cloud_topic] != bagio.POINTCLOUD2:
        raise BagError(f"{reader.path}: {cloud_topic} has type {types[cloud_topic]}, not {bagio.POINTCLOUD2}")
    if boxes_topic is None:
        candidates = sorted(t for t, ty in types.items() if ty == bagio.DETECTION3D_ARRAY) + sorted(
            t for t, ty in types.items() if ty == bagio.MARKER_ARRAY)
        if not candidates:
            raise BagError(f"{reader.path}: clouds without boxes: no {bagio.DETECTION3D_ARRAY} or "
                           f"{bagio.MARKER_ARRAY} topic (give --boxes-topic)")
        boxes_topic = candidates[0]
    elif boxes_topic not in types:
        raise BagError(f"{reader.path}: no topic {boxes_topic}")
    if types[boxes_topic] not in (bagio.DETECTION3D_ARRAY, bagio.MARKER_ARRAY):
        raise BagError(f"{reader.path}: {boxes_topic} has type {types[boxes_topic]}; expected "
                       f"{bagio.DETECTION3D_ARRAY} or {bagio.MARKER_ARRAY}")
    return cloud_topic, boxes_topic, types[boxes_topic]


def read_boxes(reader: Any, topic: str, msgtype: str) -> dict[int, BoxSet]:
    """Header stamp (ns) -> BoxSet of every message on the boxes topic (read as the node reads them; an
    empty MarkerArray has no header to pair by and is left out)."""
    out: dict[int, BoxSet] = {}
    conns = [c for c in reader.connections if c.topic == topic]
    for _conn, _t, raw in bagio.iter_raw(reader, conns):
        box_set = bagio.box_set_from_message(bagio.deserialize(raw, msgtype, f"{reader.path} {topic}"), msgtype)
        if box_set.stamp_ns is not None:
            out[box_set.stamp_ns] = box_set
    return out


def copy_connection(writer: Any, conn: Any, src: str | Path) -> Any:
    """Add `conn` (topic, type, definition, hash, QoS) of an input bag to `writer` unchanged."""
    msgdef, digest = conn.msgdef.data, conn.digest
    if not msgdef or not digest:  # bags older than rosbag2 v8 store no definitions
        if conn.msgtype not in bagio.typestore().types:
            raise BagError(f"{src}: topic {conn.topic} has unknown type {conn.msgtype} and no definition")
        msgdef, _ = bagio.typestore().generate_msgdef(conn.msgtype, ros_version=2)
        digest = bagio.typestore().hash_rihs01(conn.msgtype)
    ext = conn.ext
    return writer.add_connection(conn.topic, conn.msgtype, msgdef=msgdef, rihs01=digest,
                                 serialization_format=getattr(ext, "serialization_format", "cdr"),
                                 offered_qos_profiles=getattr(ext, "offered_qos_profiles", ()) or ())


class _Progress:
    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled, self.start, self.last = total, enabled, time.perf_counter(), 0.0

    def update(self, done: int) -> None:
        now = time.perf_counter()
        if not self.enabled or (now - self.last < 0.5 and done < self.total):
            return
        self.last = now
        elapsed = now - self.start
        eta = elapsed / done * (self.total - done) if done else float("nan")
        print(f"\rcomplete: {done}/{self.total} frames, {elapsed:.1f} s, ETA {eta:.1f} s  ", end="",
              file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled:
            print(file=sys.stderr)


@dataclass
class _Frame:
    """One cloud message waiting for its completion: where and how to write it."""

    timestamp: int  # bag timestamp of the input cloud
    frame_id: str
    stamp: int  # header stamp (ns) of the input cloud
    result: Future


class _InlineExecutor:
    """`submit` runs the call at once in this process (workers=1); its errors raise from `submit` itself."""

    @staticmethod
    def submit(fn: Callable[..., Any], *args: Any) -> Future:
        future: Future = Future()
        future.set_result(fn(*args))
        return future


_worker_completer: Any = None
_worker_error: BaseException | None = None


def _init_worker(model: str | None, options: dict[str, Any]) -> None:
    """Process pool initializer: one completer per worker process; a failure is kept and raised by each task."""
    global _worker_completer, _worker_error
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle (it shuts the pool down)
    try:
        from gd_completion.pipeline import VehicleCompleter

        _worker_completer = VehicleCompleter.from_checkpoint(model or None, **options)
    except Exception as error:  # noqa: BLE001 - raised in the main process by every _complete_in_worker
        _worker_error = error


def _complete_in_worker(points: np.ndarray, boxes: list[Box3D]) -> Any:
    if _worker_error is not None:
        raise _worker_error
    return _worker_completer.complete_frame(points, boxes)


def _write_completion(writer: Any, conn: Any, frame: _Frame, summary: CompletionSummary, bar: _Progress) -> None:
    """Count one frame's completion in `summary` and write it with the cloud's bag timestamp and header."""
    from gd_completion.pipeline import completion_to_structured

    result = frame.result.result()
    summary.vehicles_completed += int(result.stats.completed)
    summary.skipped.update(result.stats.skipped)
    summary.ignored_boxes += result.stats.ignored_labels
    msg = bagio.pointcloud2_msg(write_points(completion_to_structured(result)), frame.frame_id, frame.stamp)
    writer.write(conn, frame.timestamp, bagio.serialize(msg, bagio.POINTCLOUD2))
    summary.frames += 1
    bar.update(summary.frames)


def _open_pool(workers: int, model: str | None, options: dict[str, Any]) -> ProcessPoolExecutor:
    """`workers` spawned processes (not forked: torch and its threads), each with its own completer."""
    options = {**options, "num_threads": options.get("num_threads") or 1}
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_init_worker, initargs=(model, options))


def complete_bag(src: str | Path, out: str | Path, *, cloud_topic: str | None = None,
                 boxes_topic: str | None = None, output_topic: str | None = None, model: str | None = None,
                 storage: str = "mcap", completer: Any = None, overwrite: bool = False,
                 progress: bool = True, workers: int = 1, **completer_options: Any) -> CompletionSummary:
    """Copy every message of `src` into a new bag `out` and add one completed cloud per cloud message.

    `completer_options` go to `VehicleCompleter.from_checkpoint` (device, num_threads, min_points, labels, ...).
    `workers` > 1 completes frames in that many spawned processes, each with its own completer and
    `num_threads` vehicle threads (default 1); the output bag is the same as with `workers=1`, message for
    message and in the same write order. An injected `completer` works only with `workers=1`.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if completer is not None and workers > 1:
        raise ValueError("an injected completer runs in this process: use workers=1 with completer=")
    summary = CompletionSummary()
    start = time.perf_counter()
    with bagio.open_bag(src) as reader:
        cloud_topic, boxes_topic, boxes_type = pick_topics(reader, cloud_topic, boxes_topic)
        output_topic = output_topic or default_output_topic(cloud_topic)
        summary.output_topic = output_topic
        if output_topic in {c.topic for c in reader.connections}:
            raise BagError(f"{src}: output topic {output_topic} exists in the input bag; choose --output-topic")
        boxes = read_boxes(reader, boxes_topic, boxes_type)
        if workers == 1 and completer is None:
            from gd_completion.pipeline import VehicleCompleter

            completer = VehicleCompleter.from_checkpoint(model or None, **completer_options)
        max_in_flight = 2 * workers  # frames submitted and not yet written: memory stays flat on long bags
        total = sum(c.msgcount for c in reader.connections if c.topic == cloud_topic)
        bar = _Progress(total, progress)
        pool: ProcessPoolExecutor | None = None
        try:
            if workers > 1:
                pool = _open_pool(workers, model, completer_options)
                executor: Any = pool
                complete_frame: Callable[..., Any] = _complete_in_worker
            else:
                executor, complete_frame = _InlineExecutor(), completer.complete_frame
            with bagio.atomic_bag_writer(out, storage=storage, overwrite=overwrite) as writer:
                conns = {}
                for conn in reader.connections:
                    conns[conn.id] = copy_connection(writer, conn, src)
                out_conn = bagio.add_connection(writer, output_topic, bagio.POINTCLOUD2)
                # Writes in input order; a completion goes right after its cloud, as soon as it is done.
                queue: deque[_Frame | tuple[Any, int, bytes]] = deque()
                in_flight = 0

                def drain(limit: int) -> None:
                    """Write the queue's head while it is ready; wait while more than `limit` frames are pending."""
                    nonlocal in_flight
                    while queue:
                        head = queue[0]
                        if isinstance(head, _Frame):
                            if in_flight <= limit and not head.result.done():
                                return
                            _write_completion(writer, out_conn, head, summary, bar)
                            in_flight -= 1
                        else:
                            writer.write(*head)
                            summary.copied_messages += 1
                        queue.popleft()

                for conn, timestamp, raw in bagio.iter_raw(reader, reader.connections):
                    queue.append((conns[conn.id], timestamp, raw))
                    if conn.topic == cloud_topic:
                        cloud = bagio.deserialize(raw, bagio.POINTCLOUD2, f"{src} {cloud_topic}")
                        stamp = bagio.stamp_ns(cloud.header.stamp)
                        frame_boxes: list[Box3D] = []
                        if stamp not in boxes:
                            summary.frames_without_boxes += 1
                        else:
                            frame_boxes, wrong_frame = boxes[stamp].split_by_frame(cloud.header.frame_id)
                            if wrong_frame:
                                summary.skipped["boxes_in_other_frame"] += wrong_frame
                        future = executor.submit(complete_frame, read_xyz(cloud), frame_boxes)
                        queue.append(_Frame(timestamp, cloud.header.frame_id, stamp, future))
                        in_flight += 1
                    drain(max_in_flight - 1)
                drain(-1)
        except BrokenProcessPool as error:
            raise GDCompletionError(f"{src}: a completion worker process died ({error}); no output written "
                                    "(out of memory? try fewer --workers)") from error
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
            bar.close()
    summary.seconds = time.perf_counter() - start
    return summary


def _workers(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid worker count {text!r}: expected an integer >= 0") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"invalid worker count {value}: expected an integer >= 0 "
                                         "(0 = one per CPU core)")
    return value


def _run(args: argparse.Namespace) -> int:
    options: dict[str, Any] = {"device": args.device}
    if args.threads:
        options["num_threads"] = args.threads
    if args.min_points is not None:
        options["min_points"] = args.min_points
    if args.labels:
        options["labels"] = [label.strip().lower() for label in args.labels.split(",") if label.strip()]
    workers = args.workers or os.cpu_count() or 1
    summary = complete_bag(args.input, args.output, cloud_topic=args.cloud_topic, boxes_topic=args.boxes_topic,
                           output_topic=args.output_topic, model=args.model, storage=args.storage,
                           overwrite=args.overwrite, progress=not args.quiet, workers=workers, **options)
    print(f"wrote {args.output}: {summary.text()}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `complete`."""
    parser = subparsers.add_parser("complete", help="complete the vehicles of every frame of a bag",
                                   description=__doc__)
    parser.add_argument("input", help="input rosbag2 (folder, .mcap or .db3)")
    parser.add_argument("output", help="output bag folder (written atomically; must not exist)")
    parser.add_argument("--cloud-topic", default=None, help="PointCloud2 topic (default: the only one, or "
                        + ", ".join(DEFAULT_CLOUD_TOPICS) + ")")
    parser.add_argument("--boxes-topic", default=None,
                        help="Detection3DArray or MarkerArray topic (default: the first Detection3DArray topic)")
    parser.add_argument("--output-topic", default=None, help="completed cloud topic (default: <namespace>/completed)")
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    parser.add_argument("--storage", choices=bagio.STORAGES, default="mcap", help="output storage (default mcap)")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--threads", type=int, default=0,
                        help="CPU threads completing a frame's vehicles in parallel, one torch thread each "
                        "(default: one per core in one process, 1 per worker with --workers > 1)")
    parser.add_argument("--workers", type=_workers, default=1, metavar="N",
                        help="complete frames in N processes (default 1: in this process, its vehicles on "
                        "--threads threads); 0 = one per core. The output bag is the same for every N")
    parser.add_argument("--min-points", type=int, default=None,
                        help="skip vehicles with fewer measured points (default: the pipeline's, 20)")
    parser.add_argument("--labels", default=None, help="comma-separated labels to complete (default car,van,truck)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    parser.set_defaults(func=_run)
