"""Pure-Python pairing of clouds and boxes by header stamp, with bounded buffers and drop counters."""
from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Generic, TypeVar

C = TypeVar("C")
B = TypeVar("B")
T = TypeVar("T")

# Pairing defaults, shared by the node's parameters and the offline tools (`complete`, `render`).
SYNC_TOLERANCE_S = 0.05  # largest stamp difference between a cloud and its boxes
SYNC_MAX_WAIT_S = 1.0  # how long a cloud (or boxes message) waits for its partner
SYNC_QUEUE_SIZE = 10  # messages buffered per stream while waiting
FRESH_FRAME_AGE_S = 0.05  # the node holds a frame that waited longer for the next one due within it too


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
    (for a stream that stopped). `on_cloud_dropped` is called with every cloud given up on. Not
    thread-safe: call from one thread or under a lock.
    """

    def __init__(self, tolerance_ns: int, queue_size: int, max_wait_ns: int | None = None,
                 on_cloud_dropped: Callable[[C], None] | None = None) -> None:
        if tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.tolerance_ns = int(tolerance_ns)
        self.queue_size = int(queue_size)
        self.max_wait_ns = max_wait_ns
        self.on_cloud_dropped = on_cloud_dropped
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
        self.counters.boxes_no_cloud += len(self._evict(self._boxes,
                                                        lambda e: e.stamp_ns >= stamp_ns - self.tolerance_ns))
        if match is not None:
            self.counters.paired += 1
            return Pair(stamp_ns, cloud, match.item)
        self.counters.cloud_overflow += self._drop_clouds(self._push(self._clouds, _Entry(stamp_ns, cloud, now_ns)))
        return None

    def add_boxes(self, stamp_ns: int, boxes: B, now_ns: int = 0) -> Pair[C, B] | None:
        """Offer a boxes message; returns the pair when a cloud with a matching stamp was waiting."""
        match = self._take_nearest(self._clouds, stamp_ns)
        self.counters.cloud_no_boxes += self._drop_clouds(self._evict(
            self._clouds, lambda e: e.stamp_ns >= stamp_ns - self.tolerance_ns))
        if match is not None:
            self.counters.paired += 1
            return Pair(match.stamp_ns, match.item, boxes)
        self.counters.boxes_overflow += len(self._push(self._boxes, _Entry(stamp_ns, boxes, now_ns)))
        return None

    def expire(self, now_ns: int) -> int:
        """Drop messages received more than `max_wait_ns` before `now_ns`; returns how many."""
        if self.max_wait_ns is None:
            return 0
        limit = now_ns - self.max_wait_ns
        return self._give_up(lambda e: e.received_ns >= limit)

    def close(self) -> int:
        """The streams ended: drop everything still waiting (counted as never paired); returns how many."""
        return self._give_up(lambda e: False)

    def _give_up(self, keep: Callable[[_Entry], bool]) -> int:
        clouds = self._drop_clouds(self._evict(self._clouds, keep))
        boxes = len(self._evict(self._boxes, keep))
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
    def _evict(buffer: deque, keep: Callable[[_Entry], bool]) -> list[_Entry]:
        kept: list[_Entry] = []
        dropped: list[_Entry] = []
        for e in buffer:
            (kept if keep(e) else dropped).append(e)
        if dropped:
            buffer.clear()
            buffer.extend(kept)
        return dropped

    def _push(self, buffer: deque, entry: _Entry) -> list[_Entry]:
        buffer.append(entry)
        dropped = []
        while len(buffer) > self.queue_size:
            dropped.append(buffer.popleft())
        return dropped

    def _drop_clouds(self, entries: list[_Entry[C]]) -> int:
        if self.on_cloud_dropped is not None:
            for entry in entries:
                self.on_cloud_dropped(entry.item)
        return len(entries)


class RecordingSync(Generic[C, B]):
    """`StampSync` over a recording: the bag timestamp of a message stands in for its arrival time, and every
    cloud comes out once, with the boxes the node pairs it with live or with None where the node gives up on it.

    `add_cloud`, `add_boxes` and `close` return the clouds they decided, as (cloud, boxes or None).
    """

    def __init__(self, tolerance_ns: int, queue_size: int = SYNC_QUEUE_SIZE,
                 max_wait_ns: int = int(SYNC_MAX_WAIT_S * 1e9)) -> None:
        self._decided: list[tuple[C, B | None]] = []
        self.sync: StampSync[C, B] = StampSync(tolerance_ns, queue_size, max_wait_ns,
                                               on_cloud_dropped=lambda cloud: self._decided.append((cloud, None)))

    def add_cloud(self, stamp_ns: int, cloud: C, bag_ns: int) -> list[tuple[C, B | None]]:
        """Offer the cloud recorded at `bag_ns`."""
        self.sync.expire(bag_ns)
        return self._decide(self.sync.add_cloud(stamp_ns, cloud, bag_ns))

    def add_boxes(self, stamp_ns: int, boxes: B, bag_ns: int) -> list[tuple[C, B | None]]:
        """Offer the boxes message recorded at `bag_ns`."""
        self.sync.expire(bag_ns)
        return self._decide(self.sync.add_boxes(stamp_ns, boxes, bag_ns))

    def close(self) -> list[tuple[C, B | None]]:
        """The recording ended: the clouds still waiting get no boxes."""
        self.sync.close()
        return self._decide(None)

    def _decide(self, pair: Pair[C, B] | None) -> list[tuple[C, B | None]]:
        if pair is not None:
            self._decided.append((pair.cloud, pair.boxes))
        decided, self._decided = self._decided, []
        return decided


class LatestSlot(Generic[T]):
    """A size-1 hand-over between threads: a new item replaces one not yet taken (counted in `replaced`).

    `take(fresh_age=...)` trades a few items for freshness when the taker is slower than the producer: an item
    that has waited longer than `fresh_age` is held back for the next one when that is due (by the median
    interval of the recent puts) within `fresh_age` too, and replaced by it if it comes in time (counted in
    `stale`)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, period_window: int = 16) -> None:
        self._cond = threading.Condition()
        self._clock = clock
        self._item: T | None = None
        self._full = False
        self._closed = False
        self._put_times: deque[float] = deque(maxlen=period_window)
        self.replaced = 0
        self.stale = 0

    def put(self, item: T) -> bool:
        """Store `item`; returns True when it replaced an item nobody had taken."""
        with self._cond:
            replaced = self._full
            self.replaced += int(replaced)
            self._item, self._full = item, True
            self._put_times.append(self._clock())
            self._cond.notify()
            return replaced

    def period(self) -> float | None:
        """Median interval (s) between the recent puts; None before the third."""
        with self._cond:
            times = list(self._put_times)
        return statistics.median(b - a for a, b in zip(times, times[1:])) if len(times) >= 3 else None

    def take(self, timeout: float | None = None, fresh_age: float = 0.0) -> T | None:
        """Wait for an item (None on timeout or after `close()`); with `fresh_age` > 0 a stale one may be held
        back for the next (see the class)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._full or self._closed, timeout):
                return None
            if not self._full:
                return None
            item, self._item, self._full = self._item, None, False
            if fresh_age <= 0:
                return item
            now, put_at = self._clock(), self._put_times[-1]
        period = self.period()
        if period is None or now - put_at <= fresh_age:
            return item
        due = put_at + period - now
        if not 0.0 < due <= fresh_age:
            return item
        with self._cond:   # the next item may be a little late: a quarter period of slack
            if not self._cond.wait_for(lambda: self._full or self._closed, due + period / 4):
                return item
            if not self._full:   # closed while holding
                return None
            newer, self._item, self._full = self._item, None, False
            self.stale += 1
            return newer

    def close(self) -> None:
        """Wake any waiting `take()` for good."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
