"""Bag completion: copy a bag byte for byte and add the completed vehicles of every cloud (`complete_bag`), as
`gd-completion complete` and the batch engine (`bags/batch`) run it."""
from __future__ import annotations

import sys
import time
from collections import Counter, deque
from concurrent.futures.process import BrokenProcessPool
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gd_completion.bags.messages import pointcloud2_msg
from gd_completion.bags.pairing import BagPairing, RecordedCloud
from gd_completion.bags.provenance import completer_parameters, provenance, set_provenance
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.topics import default_output_topic, pick_topics
from gd_completion.bags.typestore import POINTCLOUD2, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer, copy_connection, has_definition
from gd_completion.errors import BagError, GDCompletionError
from gd_completion.frame_pool import FramePool, InOrder
from gd_completion.pointcloud2 import read_xyz, write_points
from gd_completion.progress import progress_bar
from gd_completion.settings import CompletionSettings
from gd_completion.stamp_sync import SyncCounters
from gd_completion.transforms import TransformBuffer, transforms_pending


@dataclass
class CompletionSummary:
    """What `complete` did; the counters have the names the node reports in /diagnostics."""

    frames: int = 0  # completed clouds written: one per input cloud
    copied_messages: int = 0
    vehicles_completed: int = 0
    skipped: Counter = field(default_factory=Counter)  # vehicles per reason (`skipped_<reason>` in the node)
    ignored_labels: int = 0
    unmapped_class_ids: int = 0
    nonfinite_points: int = 0
    completions_run: int = 0      # vehicles the network completed
    completions_reused: int = 0   # vehicles written from their track's cached completion (--reuse)
    boxes_wrong_frame: int = 0    # boxes in another frame than the cloud's, use_tf off
    boxes_no_transform: int = 0   # boxes in a frame with no transform into the cloud's at its stamp
    boxes_without_header: int = 0
    unsupported_shapes: int = 0   # Autoware objects of boxes messages whose shape is no box (not converted)
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
                  "unmapped_class_ids": self.unmapped_class_ids,
                  **{f"skipped_{reason}": n for reason, n in sorted(self.skipped.items())},
                  "boxes_wrong_frame": self.boxes_wrong_frame, "boxes_no_transform": self.boxes_no_transform,
                  "boxes_without_header": self.boxes_without_header,
                  "skipped_unsupported_shape": self.unsupported_shapes,
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
        self.unmapped_class_ids += stats.unmapped_class_ids
        self.nonfinite_points += stats.nonfinite_points
        self.completions_run += stats.completions_run
        self.completions_reused += stats.completions_reused


def complete_bag(src: str | Path, out: str | Path, settings: CompletionSettings | None = None, *,
                 cloud_topic: str | None = None, boxes_topic: str | None = None, output_topic: str | None = None,
                 storage: str = "mcap", completer: Any = None, overwrite: bool = False, progress: bool = True,
                 workers: int = 1, skip_unknown_types: bool = False, pool: FramePool | None = None
                 ) -> CompletionSummary:
    """Copy every message of `src` into a new bag `out` and add one completed cloud per cloud message.

    `settings`: what the node's parameters of the same names do live (default `CompletionSettings.offline()`:
    no time budget, so the output never depends on the machine's load; no reuse). Clouds and boxes are paired as
    the node pairs them (stamps within `settings.sync_tolerance`), their classes mapped by the same class preset
    and map; a cloud the node would leave unpaired gets an empty completion. Completions carry the cloud's header
    and bag timestamp. `workers` > 1 completes frames in that many spawned processes; the output bag is the same
    as with `workers=1`, message for message and in the same write order. An injected `completer` works only with
    `workers=1`. A `pool` given is used (and left open) instead of one made from `workers`, `settings` and
    `completer`, so many bags can share it (its completer's settings then decide the completions). The bag's
    metadata records the package version, the model's SHA-256 and the parameters.
    With `settings.track_fusion` or `settings.reuse`, frames are completed in order in this process and the
    completer's tracks start afresh for each bag (`VehicleCompleter.reset_tracks`); the boxes get the track ids
    of `settings.track_ids`.
    A topic of a type with no stored definition and unknown here cannot be copied: BagError, unless
    `skip_unknown_types`, which leaves it out with a warning on stderr (counted in `summary.not_copied`).
    """
    from gd_completion.model.checkpoint import DEFAULT_WEIGHTS
    from gd_completion.pipeline import completion_to_structured

    settings = settings or CompletionSettings.offline()
    summary = CompletionSummary()
    start = time.perf_counter()
    with open_bag(src) as reader:
        cloud_topic, boxes_topic, boxes_type = pick_topics(reader, cloud_topic, boxes_topic)
        output_topic = output_topic or default_output_topic(cloud_topic)
        summary.output_topic = output_topic
        if output_topic in {c.topic for c in reader.connections}:
            raise BagError(f"{src}: output topic {output_topic} exists in the input bag; choose --output-topic")
        transforms = TransformBuffer(extrapolation_s=settings.transform_tolerance) if settings.use_tf else None
        pairing = BagPairing(cloud_topic, boxes_topic, boxes_type, tolerance_s=settings.sync_tolerance,
                             class_map=settings.classes, transforms=transforms, source=str(src))
        copied = [c for c in reader.connections if has_definition(c) or not skip_unknown_types]
        for conn in (c for c in reader.connections if c not in copied):
            print(f"gd-completion complete: warning: {src}: skipping {conn.topic}: type {conn.msgtype} is unknown and "
                  "the bag stores no definition; not copied", file=sys.stderr)
            summary.not_copied[conn.topic] = summary.not_copied.get(conn.topic, 0) + conn.msgcount
        total = sum(c.msgcount for c in reader.connections if c.topic == cloud_topic)
        in_flight = 2 * (pool.workers if pool is not None else workers)
        queue: InOrder[Any] = InOrder(max_in_flight=in_flight)  # memory stays flat on long bags
        waiting: dict[int, Any] = {}  # cloud index -> its slot in the queue, until its pairing is decided
        try:
            frames = nullcontext(pool) if pool is not None else FramePool(workers, settings, completer)
            with (frames as pool,
                  atomic_bag_writer(out, storage=storage, overwrite=overwrite) as writer,
                  progress_bar("complete", "frames", total=total, quiet=not progress) as bar):
                conns = {conn.id: copy_connection(writer, conn, src) for conn in copied}
                out_conn = add_connection(writer, output_topic, POINTCLOUD2)
                stamped = settings.track_fusion or settings.reuse is not None
                if stamped:
                    if pool.completer is None:
                        raise BagError("track fusion and reuse need every frame of a bag in order in one process: "
                                       "use --workers 1")
                    pool.completer.reset_tracks()

                wait_ns = round(settings.transform_wait * 1e9) if transforms is not None else 0
                decided_clouds: deque[tuple[int, RecordedCloud, Any]] = deque()   # (wait until, cloud, boxes)

                def submit(decided: list[tuple[RecordedCloud, Any]], now_ns: int | None) -> None:
                    """Submit, in order, the clouds whose boxes are known (or known to be none). A cloud with boxes
                    whose transforms have not reached its stamp yet waits, and the clouds behind it, until they do
                    or the bag's time `now_ns` is `transform_wait` past its pairing (the node's worker waits as long
                    for /tf); None: the bag ended, no more waiting."""
                    decided_clouds.extend((now_ns + wait_ns if now_ns is not None else 0, c, b) for c, b in decided)
                    while decided_clouds:
                        until, cloud, box_set = decided_clouds[0]
                        if (now_ns is not None and now_ns < until and transforms is not None and box_set is not None
                                and transforms_pending(box_set, cloud.msg.header.frame_id, cloud.stamp_ns, transforms)):
                            return
                        boxes, missing = cloud.boxes_in_frame(box_set, transforms)
                        decided_clouds.popleft()
                        if transforms is None:
                            summary.boxes_wrong_frame += missing
                        else:
                            summary.boxes_no_transform += missing
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
                    submit([], timestamp)   # the clouds whose wait ended before this message
                    queue.put((conns[conn.id], timestamp, raw))
                    cloud, decided = pairing.feed(conn.topic, timestamp, raw)
                    if cloud is not None:
                        waiting[cloud.index] = queue.hold(cloud)
                    submit(decided, timestamp)
                    write(queue.ready())
                submit(pairing.close(), None)
                write(queue.rest())
                parameters = {"completer": pool.run(completer_parameters).result(), "cloud_topic": cloud_topic,
                              "boxes_topic": boxes_topic, "output_topic": output_topic,
                              "sync_tolerance": settings.sync_tolerance, "class_preset": settings.class_preset,
                              "class_map": list(settings.class_map)}
                set_provenance(writer, provenance("complete", settings.model_path or DEFAULT_WEIGHTS, parameters))
        except BrokenProcessPool as error:
            raise GDCompletionError(f"{src}: a completion worker process died ({error}); no output written "
                                    "(out of memory? try fewer --workers)") from error
    summary.sync = pairing.counters
    summary.boxes_without_header = pairing.boxes_without_header
    summary.unsupported_shapes = pairing.unsupported_shapes
    summary.seconds = time.perf_counter() - start
    return summary
