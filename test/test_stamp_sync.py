"""StampSync pairing, eviction and overflow counters; LatestSlot hand-over (pure Python, no rclpy)."""
from __future__ import annotations

import threading
import time

import pytest

from gd_completion.stamp_sync import LatestSlot, RecordingSync, StampSync, stamp_to_ns

MS = 1_000_000


def make(tolerance_ms: int = 10, queue: int = 3, max_wait_ms: int | None = None) -> StampSync:
    return StampSync(tolerance_ms * MS, queue, None if max_wait_ms is None else max_wait_ms * MS)


def test_stamp_to_ns():
    class T:
        sec, nanosec = 12, 345
    assert stamp_to_ns(T) == 12_000_000_345


def test_pairs_cloud_then_boxes_within_tolerance():
    s = make()
    assert s.add_cloud(100 * MS, "c100") is None
    pair = s.add_boxes(108 * MS, "b108")
    assert (pair.stamp_ns, pair.cloud, pair.boxes) == (100 * MS, "c100", "b108")
    assert s.pending == (0, 0) and s.counters.paired == 1


def test_pairs_boxes_then_cloud_and_keeps_cloud_stamp():
    s = make()
    assert s.add_boxes(205 * MS, "b") is None
    pair = s.add_cloud(200 * MS, "c")
    assert (pair.stamp_ns, pair.cloud, pair.boxes) == (200 * MS, "c", "b")


def test_outside_tolerance_does_not_pair():
    s = make(tolerance_ms=10)
    assert s.add_cloud(100 * MS, "c") is None
    assert s.add_boxes(111 * MS, "b") is None
    assert s.counters.paired == 0
    # the boxes are newer than cloud + tolerance, so that cloud can never get boxes: dropped and counted
    assert s.counters.cloud_no_boxes == 1 and s.pending == (0, 1)


def test_nearest_stamp_wins():
    s = make(tolerance_ms=50, queue=5)
    s.add_cloud(100 * MS, "c100")
    s.add_cloud(130 * MS, "c130")
    pair = s.add_boxes(125 * MS, "b125")
    assert pair.cloud == "c130"
    # c100 is older than 125 - 50 = 75? no: 100 >= 75, so it still waits
    assert s.pending == (1, 0) and s.counters.cloud_no_boxes == 0


def test_boxes_that_never_get_a_cloud_are_counted_when_a_newer_cloud_arrives():
    s = make()
    s.add_boxes(100 * MS, "lost")
    s.add_boxes(200 * MS, "b200")
    pair = s.add_cloud(200 * MS, "c200")
    assert pair.boxes == "b200"
    assert s.counters.boxes_no_cloud == 1 and s.pending == (0, 0)


def test_late_boxes_still_pair_with_a_waiting_cloud():
    """Detector latency: clouds 1 and 2 arrive before the boxes of cloud 1."""
    s = make(tolerance_ms=10, queue=5)
    s.add_cloud(100 * MS, "c100")
    s.add_cloud(200 * MS, "c200")
    assert s.add_boxes(100 * MS, "b100").cloud == "c100"
    assert s.add_boxes(200 * MS, "b200").cloud == "c200"
    assert s.counters.as_dict() == {"paired": 2, "cloud_no_boxes": 0, "boxes_no_cloud": 0,
                                    "cloud_overflow": 0, "boxes_overflow": 0}


def test_overflow_drops_oldest_and_counts():
    s = make(queue=2)
    for i in range(5):
        s.add_cloud(i * 100 * MS, f"c{i}")
    assert s.pending == (2, 0) and s.counters.cloud_overflow == 3
    assert s.add_boxes(400 * MS, "b").cloud == "c4"
    for i in range(4):
        s.add_boxes((1000 + i * 100) * MS, f"b{i}")
    assert s.counters.boxes_overflow == 2


def test_expire_drops_messages_that_waited_too_long():
    s = make(max_wait_ms=500)
    s.add_cloud(100 * MS, "c", now_ns=0)
    s.add_boxes(900 * MS, "b", now_ns=400 * MS)  # not pairable (and evicts the cloud by stamp)
    assert s.counters.cloud_no_boxes == 1
    assert s.expire(800 * MS) == 0  # boxes received at 400 ms: waited 400 ms < 500 ms
    assert s.expire(901 * MS) == 1
    assert s.counters.boxes_no_cloud == 1 and s.pending == (0, 0)


def test_expire_without_max_wait_is_noop():
    s = make()
    s.add_cloud(0, "c")
    assert s.expire(10**18) == 0 and s.pending == (1, 0)


@pytest.mark.parametrize("tol, queue", [(-1, 3), (0, 0)])
def test_rejects_bad_settings(tol, queue):
    with pytest.raises(ValueError):
        StampSync(tol, queue)


def test_latest_slot_newest_wins_and_counts_replaced():
    slot: LatestSlot[int] = LatestSlot()
    assert slot.put(1) is False
    assert slot.put(2) is True
    assert slot.put(3) is True
    assert slot.take(timeout=0) == 3 and slot.replaced == 2
    assert slot.take(timeout=0.01) is None


def test_latest_slot_wakes_waiting_taker_and_close():
    slot: LatestSlot[str] = LatestSlot()
    got: list = []
    t = threading.Thread(target=lambda: got.append(slot.take(timeout=5)))
    t.start()
    slot.put("x")
    t.join(2)
    assert got == ["x"]
    t = threading.Thread(target=lambda: got.append(slot.take(timeout=5)))
    t.start()
    slot.close()
    t.join(2)
    assert not t.is_alive() and got == ["x", None]


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _slot_fed_every(period: float, puts: int) -> tuple[LatestSlot[str], FakeClock]:
    clock = FakeClock()
    slot: LatestSlot[str] = LatestSlot(clock=clock)
    for i in range(puts):
        clock.now = i * period
        slot.put(f"item{i}")
    return slot, clock


def test_latest_slot_period_is_the_median_put_interval():
    slot, _ = _slot_fed_every(0.1, 2)
    assert slot.period() is None
    slot, _ = _slot_fed_every(0.1, 5)
    assert slot.period() == pytest.approx(0.1)


def test_latest_slot_swaps_a_stale_item_for_the_next_when_it_comes():
    # puts every 10 s (fake clock); taken 6 s after the last put with fresh_age 5: the next is due in 4 s <= 5
    slot, clock = _slot_fed_every(10.0, 4)
    clock.now = 36.0
    got: list = []
    taker = threading.Thread(target=lambda: got.append(slot.take(timeout=1, fresh_age=5.0)))
    taker.start()
    for _ in range(500):   # until the taker holds the stale item
        if not slot._full:
            break
        time.sleep(0.01)
    time.sleep(0.05)
    slot.put("fresh")
    taker.join(10)
    assert got == ["fresh"] and slot.stale == 1 and slot.replaced == 3   # 3: the puts before the take


def test_latest_slot_completes_a_stale_item_when_nothing_newer_comes():
    slot, clock = _slot_fed_every(0.1, 4)
    clock.now = 0.36   # 60 ms old, next due in 40 ms: held, then given back when nothing comes
    assert slot.take(timeout=1, fresh_age=0.05) == "item3" and slot.stale == 0


@pytest.mark.parametrize("taken_at, fresh_age", [(330.0, 50.0),   # 30 s old: fresh enough
                                                 (360.0, 0.0),    # holding disabled
                                                 (450.0, 50.0)])  # older than a period: the next is late
def test_latest_slot_does_not_hold_without_cause(taken_at, fresh_age):
    # puts every 100 s (fake clock): a hold would last tens of seconds and return the item put meanwhile
    slot, clock = _slot_fed_every(100.0, 4)
    clock.now = taken_at
    got: list = []
    taker = threading.Thread(target=lambda: got.append(slot.take(timeout=1, fresh_age=fresh_age)))
    taker.start()
    time.sleep(0.2)
    slot.put("newer")
    taker.join(30)
    assert got == ["item3"] and slot.stale == 0


def test_latest_slot_close_while_holding_returns_nothing():
    slot, clock = _slot_fed_every(10.0, 4)
    clock.now = 36.0   # held for up to 6.5 s
    got: list = []
    taker = threading.Thread(target=lambda: got.append(slot.take(timeout=1, fresh_age=5.0)))
    taker.start()
    time.sleep(0.2)
    slot.close()
    taker.join(10)
    assert got == [None]


def test_latest_slot_does_not_hold_when_the_next_is_due_later_than_fresh_age():
    slot, clock = _slot_fed_every(100.0, 4)   # slow input: taken 0.1 s after a put, the next due in 99.9 s
    clock.now = 300.1
    done = threading.Event()
    got: list = []

    def take() -> None:
        got.append(slot.take(timeout=1, fresh_age=0.05))
        done.set()
    threading.Thread(target=take).start()
    assert done.wait(30) and got == ["item3"]   # a hold would last 100 s


def test_recording_sync_decides_every_cloud_once():
    """Over a recording each cloud comes out once: paired, or with None when the node would give up on it
    (boxes passed its stamp, buffer overflow, waited longer than max_wait in bag time, end of the recording)."""
    r = RecordingSync(10 * MS, queue_size=2, max_wait_ns=1000 * MS)
    assert r.add_cloud(0, "c0", 0) == []
    assert r.add_boxes(3 * MS, "b0", 3 * MS) == [("c0", "b0")]   # 3 ms apart: paired
    assert r.add_cloud(100 * MS, "c1", 100 * MS) == []
    assert r.add_boxes(150 * MS, "b1", 150 * MS) == [("c1", None)]  # its boxes passed it
    assert r.add_cloud(200 * MS, "c2", 200 * MS) == []
    assert r.add_cloud(300 * MS, "c3", 300 * MS) == []
    assert r.add_cloud(400 * MS, "c4", 400 * MS) == [("c2", None)]  # buffer of 2 overflowed
    assert r.add_boxes(398 * MS, "b4", 1350 * MS) == [("c3", None), ("c4", "b4")]  # c3 waited > 1 s
    assert r.add_cloud(500 * MS, "c5", 1400 * MS) == []
    assert r.close() == [("c5", None)]
    assert r.sync.counters.as_dict() == {"paired": 2, "cloud_no_boxes": 3, "boxes_no_cloud": 1,
                                         "cloud_overflow": 1, "boxes_overflow": 0}
