"""Pure-Python pairing of clouds and boxes by header stamp, with bounded buffers and drop counters."""
from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Generic, TypeVar

C = TypeVar("C")
B = TypeVar("B")
T = TypeVar("T")


def stamp_to_ns(stamp) -> int:
    """`builtin_interfaces/Time` (anything with `.sec`, `.nanosec`) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class SyncCounters:
    """What the synchroniser paired and what it gave up on, cumulative."""

    paired: int = 0
    cloud_no_boxes: int = 0  # a cloud whose boxes never came (stamp passed or waited too long)
    boxes_no_cloud: int = 0  # boxes whose cloud never came
    cloud_overflow: int = 0  # a cloud pushed out of a full buffer
    boxes_overflow: int = 0  # boxes pushed out of a full buffer

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class Pair(Generic[C, B]):
    """A cloud and the boxes with (nearly) the same stamp; `stamp_ns` is the cloud's."""

    stamp_ns: int
    cloud: C
    boxes: B


@dataclass
class _Entry(Generic[T]):
    stamp_ns: int
    item: T
    received_ns: int


class StampSync(Generic[C, B]):
    """Pair each cloud with the boxes message nearest in stamp within `tolerance_ns`.

    Each stream is assumed to arrive in stamp order, so once a message of one stream with stamp T
    arrives, buffered messages of the other stream older than T - tolerance can never be paired and
    are dropped (counted). Each buffer holds at most `queue_size` messages (the oldest is dropped and
    counted on overflow), and `expire(now)` drops messages that waited longer than `max_wait_ns`
    (for a stream that stopped). Not thread-safe: call from one thread or under a lock.
    """

    def __init__(self, tolerance_ns: int, queue_size: int, max_wait_ns: int | None = None) -> None:
        if tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.tolerance_ns = int(tolerance_ns)
        self.queue_size = int(queue_size)
        self.max_wait_ns = max_wait_ns
        self.counters = SyncCounters()
        self._clouds: deque[_Entry[C]] = deque()
        self._boxes: deque[_Entry[B]] = deque()

    @property
    def pending(self) -> tuple[int, int]:
        """(clouds, boxes) waiting for their partner."""
        return len(self._clouds), len(self._boxes)

    def add_cloud(self, stamp_ns: int, cloud: C, now_ns: int = 0) -> Pair[C, B] | None:
        """Offer a cloud; returns the pair when boxes with a matching stamp were waiting."""
        match = self._take_nearest(self._boxes, stamp_ns)
        self.counters.boxes_no_cloud += self._evict(self._boxes, lambda e: e.stamp_ns >= stamp_ns - self.tolerance_ns)
        if match is not None:
            self.counters.paired += 1
            return Pair(stamp_ns, cloud, match.item)
        self.counters.cloud_overflow += self._push(self._clouds, _Entry(stamp_ns, cloud, now_ns))
        return None

    def add_boxes(self, stamp_ns: int, boxes: B, now_ns: int = 0) -> Pair[C, B] | None:
        """Offer a boxes message; returns the pair when a cloud with a matching stamp was waiting."""
        match = self._take_nearest(self._clouds, stamp_ns)
        self.counters.cloud_no_boxes += self._evict(self._clouds, lambda e: e.stamp_ns >= stamp_ns - self.tolerance_ns)
        if match is not None:
            self.counters.paired += 1
            return Pair(match.stamp_ns, match.item, boxes)
        self.counters.boxes_overflow += self._push(self._boxes, _Entry(stamp_ns, boxes, now_ns))
        return None

    def expire(self, now_ns: int) -> int:
        """Drop messages received more than `max_wait_ns` before `now_ns`; returns how many."""
        if self.max_wait_ns is None:
            return 0
        limit = now_ns - self.max_wait_ns
        clouds = self._evict(self._clouds, lambda e: e.received_ns >= limit)
        boxes = self._evict(self._boxes, lambda e: e.received_ns >= limit)
        self.counters.cloud_no_boxes += clouds
        self.counters.boxes_no_cloud += boxes
        return clouds + boxes

    def _take_nearest(self, buffer: deque, stamp_ns: int) -> _Entry | None:
        best, best_gap = None, None
        for entry in buffer:
            gap = abs(entry.stamp_ns - stamp_ns)
            if gap <= self.tolerance_ns and (best_gap is None or gap < best_gap):
                best, best_gap = entry, gap
        if best is not None:
            buffer.remove(best)
        return best

    @staticmethod
    def _evict(buffer: deque, keep: Callable[[_Entry], bool]) -> int:
        kept = [e for e in buffer if keep(e)]
        dropped = len(buffer) - len(kept)
        if dropped:
            buffer.clear()
            buffer.extend(kept)
        return dropped

    def _push(self, buffer: deque, entry: _Entry) -> int:
        buffer.append(entry)
        dropped = 0
        while len(buffer) > self.queue_size:
            buffer.popleft()
            dropped += 1
        return dropped


class LatestSlot(Generic[T]):
    """A size-1 hand-over between threads: a new item replaces one not yet taken (counted in `replaced`)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._full = False
        self._closed = False
        self.replaced = 0

    def put(self, item: T) -> bool:
        """Store `item`; returns True when it replaced an item nobody had taken."""
        with self._cond:
            replaced = self._full
            self.replaced += int(replaced)
            self._item, self._full = item, True
            self._cond.notify()
            return replaced

    def take(self, timeout: float | None = None) -> T | None:
        """Wait for an item (None on timeout or after `close()`)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._full or self._closed, timeout):
                return None
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            return item

    def close(self) -> None:
        """Wake any waiting `take()` for good."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
