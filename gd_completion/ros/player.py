"""Publishing a bag's topics live with rclpy at the recorded timing (raw CDR bytes), optionally with /clock."""
from __future__ import annotations

import importlib
import math
import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.errors import BagError
from gd_completion.fastdds import use_large_message_profile

CLOCK_TOPIC = "/clock"
DEFAULT_CLOCK_HZ = 40.0  # `ros2 bag play --clock` without a rate
DEFAULT_WAIT_S = 5.0
DEFAULT_DELAY_S = 0.5
STOP_POLL_S = 0.05       # the longest a sleep of the player goes on after a stop request
LAST_MESSAGES_S = 0.2    # after the last message, before the publishers go: let the last messages leave


class StopRequest:
    """A request to stop playing, checked between messages and during every wait.

    Lock-free, so that a signal handler can set it whatever the main thread is doing (a `threading.Event` set
    from a handler can deadlock on its own lock); `request` is also safe from another thread.
    """

    def __init__(self) -> None:
        self.reason: str | None = None

    def request(self, reason: str = "stop requested") -> None:
        """Stop at the next check; the first reason is kept."""
        if self.reason is None:
            self.reason = reason

    def __bool__(self) -> bool:
        return self.reason is not None


@contextmanager
def stop_on_signals(signals: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopRequest]:
    """SIGINT and SIGTERM request a stop (reason: the signal's name) instead of raising KeyboardInterrupt or ending
    the process; further signals change nothing. On leaving, the former handlers come back unless a signal came,
    in which case these signals stay ignored through the interpreter's exit (no traceback from a second Ctrl-C)."""
    stop = StopRequest()

    def handler(signum: int, _frame: Any) -> None:
        stop.request(signal.Signals(signum).name)

    former = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield stop
    finally:
        for sig, previous in former.items():
            signal.signal(sig, signal.SIG_IGN if stop else previous)


def message_class(msgtype: str) -> Any | None:
    """The rclpy message class of 'pkg/msg/Type', or None when the package is not importable here."""
    package, _, name = msgtype.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


def _qos(conn: Any) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    latched = any(getattr(getattr(q, "durability", None), "name", "") == "TRANSIENT_LOCAL"
                  for q in getattr(conn.ext, "offered_qos_profiles", ()) or ())
    if latched or conn.topic == "/tf_static":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)


def _sleep_until(wall: float, stop: StopRequest) -> None:
    """Sleep until monotonic time `wall`, or until a stop is requested (within STOP_POLL_S)."""
    while not stop and (left := wall - time.monotonic()) > 0:
        time.sleep(min(left, STOP_POLL_S))


class BagClock:
    """/clock (rosgraph_msgs/Clock) with the playback's bag time, as `ros2 bag play --clock`: every 1/hz wall
    seconds between messages and at each message's bag time; it never runs backwards within one pass."""

    def __init__(self, node: Any, hz: float, stop: StopRequest | None = None) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        self._message = Clock
        self.period = 1.0 / hz
        self.stop = stop if stop is not None else StopRequest()
        # reliable matches reliable and best-effort (rclpy's TimeSource) subscribers alike
        self.publisher = node.create_publisher(Clock, CLOCK_TOPIC,
                                               QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.sent_at = -math.inf  # monotonic time of the last message
        self.bag_ns = 0

    def publish(self, bag_ns: int, *, restart: bool = False) -> None:
        """Publish `bag_ns` (at least the last time published, unless `restart`: a new pass of a --loop)."""
        self.bag_ns = bag_ns if restart else max(self.bag_ns, bag_ns)
        msg = self._message()
        msg.clock.sec, msg.clock.nanosec = divmod(self.bag_ns, 1_000_000_000)
        self.publisher.publish(msg)
        self.sent_at = time.monotonic()

    def sleep_until(self, wall: float, bag_ns_at: Callable[[float], int]) -> None:
        """Sleep until monotonic time `wall` (or a stop request), publishing the bag time `bag_ns_at(now)` every
        period meanwhile."""
        while not self.stop and (now := time.monotonic()) < wall:
            if now >= self.sent_at + self.period:
                self.publish(bag_ns_at(now))
            _sleep_until(min(wall, self.sent_at + self.period), self.stop)


def _wait_for_subscribers(publishers: dict[str, Any], seconds: float, log: Callable[..., Any],
                          stop: StopRequest) -> None:
    """Wait up to `seconds` until every topic's publisher has a matched subscription; name those still without."""
    deadline = time.monotonic() + seconds
    while (alone := [t for t, p in publishers.items() if p.get_subscription_count() == 0]) and \
            time.monotonic() < deadline and not stop:
        time.sleep(STOP_POLL_S)
    if alone and seconds > 0 and not stop:
        log(f"play: no subscriber on {', '.join(alone)} after {seconds:g} s; playing anyway", file=sys.stderr)


def play(path: str | Path, *, rate: float = 1.0, loop: bool = False, start_offset: float = 0.0,
         topics: list[str] | None = None, delay: float = DEFAULT_DELAY_S,
         wait_for_subscribers: float = DEFAULT_WAIT_S, clock_hz: float = 0.0, stop: StopRequest | None = None,
         log: Callable[..., Any] = print) -> dict[str, int]:
    """Publish the bag; returns messages published per topic. Topics whose type rclpy lacks are skipped.

    Before the first message it waits up to `wait_for_subscribers` seconds until every played topic has a matched
    subscription (0: no wait), then `delay` seconds more for the subscribers' side of discovery. `clock_hz` > 0
    also publishes /clock with the bag time at that rate. The Fast DDS large-message profile is used unless a
    profile file is set in the environment already.

    `stop` (`stop_on_signals()` for SIGINT and SIGTERM): playing ends between two messages once it is requested,
    and the publishers, the node and the ROS context are taken down in order. rclpy installs no signal handler
    of its own (its SIGINT handler would shut the context down under the publishers). Without `stop`, a
    KeyboardInterrupt ends playing the same way.
    """
    if rate <= 0:
        raise BagError(f"--rate must be positive, got {rate}")
    stop = stop if stop is not None else StopRequest()
    use_large_message_profile()  # before rclpy.init creates this process's DDS participant
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    counts: dict[str, int] = {}
    with open_bag(path) as reader:
        wanted = [c for c in reader.connections if not topics or c.topic in topics]
        missing = sorted(set(topics or ()) - {c.topic for c in reader.connections})
        if missing:
            raise BagError(f"{path}: no topic {', '.join(missing)}")
        if stop:
            return counts
        context = rclpy.Context()
        rclpy.init(args=None, context=context, signal_handler_options=SignalHandlerOptions.NO)
        node = None
        publishers: dict[int, Any] = {}
        clock: BagClock | None = None
        try:
            node = rclpy.create_node("gd_completion_player", context=context)
            for conn in wanted:
                cls = message_class(conn.msgtype)
                if cls is None:
                    log(f"play: skipping {conn.topic}: type {conn.msgtype} is not available to rclpy here",
                        file=sys.stderr)
                    continue
                publishers[conn.id] = node.create_publisher(cls, conn.topic, _qos(conn))
            if not publishers:
                raise BagError(f"{path}: none of the selected topics has a type rclpy can publish")
            conns = [c for c in wanted if c.id in publishers]
            clock = BagClock(node, clock_hz, stop) if clock_hz > 0 else None
            _wait_for_subscribers({c.topic: publishers[c.id] for c in conns}, wait_for_subscribers, log, stop)
            _sleep_until(time.monotonic() + max(0.0, delay), stop)
            first = reader.start_time + int(start_offset * 1e9)
            while not stop:
                wall0 = time.monotonic()
                published = 0
                if clock is not None:
                    clock.publish(first, restart=True)
                for conn, stamp, raw in iter_raw(reader, conns):
                    if stamp < first:
                        continue
                    wall = wall0 + (stamp - first) / 1e9 / rate
                    if clock is None:
                        _sleep_until(wall, stop)
                    else:
                        clock.sleep_until(wall, partial(_bag_time, first, wall0, rate))
                        if not stop:
                            clock.publish(stamp)
                    if stop:
                        break
                    publishers[conn.id].publish(bytes(raw))
                    counts[conn.topic] = counts.get(conn.topic, 0) + 1
                    published += 1
                if not loop or not published:  # a pass with nothing to publish would loop idle for ever
                    break
            if not stop:
                _sleep_until(time.monotonic() + LAST_MESSAGES_S, stop)
        except KeyboardInterrupt:
            stop.request("KeyboardInterrupt")
        finally:
            _take_down(node, [*publishers.values(), *([clock.publisher] if clock is not None else [])], context)
    return counts


def _bag_time(first_ns: int, wall0: float, rate: float, now: float) -> int:
    """The bag time at monotonic time `now` of a pass that started `first_ns` at `wall0`."""
    return first_ns + int((now - wall0) * rate * 1e9)


def _take_down(node: Any, publishers: list[Any], context: Any) -> None:
    """The publishers, then the node, then the context: nothing is published on a context already shut down."""
    if node is not None:
        for publisher in publishers:
            node.destroy_publisher(publisher)
        node.destroy_node()
    context.try_shutdown()
