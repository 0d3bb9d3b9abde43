"""`gd-completion play`: publish a bag's topics live with rclpy at the recorded timing (raw CDR bytes)."""
from __future__ import annotations

import argparse
import importlib
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.errors import BagError
from gd_completion.fastdds import use_large_message_profile

CLOCK_TOPIC = "/clock"
DEFAULT_CLOCK_HZ = 40.0  # `ros2 bag play --clock` without a rate
DEFAULT_WAIT_S = 5.0
DEFAULT_DELAY_S = 0.5


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


class BagClock:
    """/clock (rosgraph_msgs/Clock) with the playback's bag time, as `ros2 bag play --clock`: every 1/hz wall
    seconds between messages and at each message's bag time; it never runs backwards within one pass."""

    def __init__(self, node: Any, hz: float) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        self._message = Clock
        self.period = 1.0 / hz
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
        """Sleep until monotonic time `wall`, publishing the bag time `bag_ns_at(now)` every period meanwhile."""
        while (now := time.monotonic()) < wall:
            if now >= self.sent_at + self.period:
                self.publish(bag_ns_at(now))
            time.sleep(max(0.0, min(wall, self.sent_at + self.period) - time.monotonic()))


def _sleep_until(wall: float) -> None:
    time.sleep(max(0.0, wall - time.monotonic()))


def _wait_for_subscribers(publishers: dict[str, Any], seconds: float, log: Callable[..., Any]) -> None:
    """Wait up to `seconds` until every topic's publisher has a matched subscription; name those still without."""
    deadline = time.monotonic() + seconds
    while (alone := [t for t, p in publishers.items() if p.get_subscription_count() == 0]) and \
            time.monotonic() < deadline:
        time.sleep(0.05)
    if alone and seconds > 0:
        log(f"play: no subscriber on {', '.join(alone)} after {seconds:g} s; playing anyway", file=sys.stderr)


def play(path: str | Path, *, rate: float = 1.0, loop: bool = False, start_offset: float = 0.0,
         topics: list[str] | None = None, delay: float = DEFAULT_DELAY_S,
         wait_for_subscribers: float = DEFAULT_WAIT_S, clock_hz: float = 0.0, log=print) -> dict[str, int]:
    """Publish the bag; returns messages published per topic. Topics whose type rclpy lacks are skipped.

    Before the first message it waits up to `wait_for_subscribers` seconds until every played topic has a matched
    subscription (0: no wait), then `delay` seconds more for the subscribers' side of discovery. `clock_hz` > 0
    also publishes /clock with the bag time at that rate. The Fast DDS large-message profile is used unless a
    profile file is set in the environment already.
    """
    if rate <= 0:
        raise BagError(f"--rate must be positive, got {rate}")
    use_large_message_profile()  # before rclpy.init creates this process's DDS participant
    import rclpy
    from rclpy.executors import ExternalShutdownException

    counts: dict[str, int] = {}
    with open_bag(path) as reader:
        wanted = [c for c in reader.connections if not topics or c.topic in topics]
        missing = sorted(set(topics or ()) - {c.topic for c in reader.connections})
        if missing:
            raise BagError(f"{path}: no topic {', '.join(missing)}")
        rclpy.init(args=None)
        try:
            node = rclpy.create_node("gd_completion_player")
            publishers: dict[int, Any] = {}
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
            clock = BagClock(node, clock_hz) if clock_hz > 0 else None
            _wait_for_subscribers({c.topic: publishers[c.id] for c in conns}, wait_for_subscribers, log)
            time.sleep(max(0.0, delay))
            first = reader.start_time + int(start_offset * 1e9)
            while True:
                wall0 = time.monotonic()
                if clock is not None:
                    clock.publish(first, restart=True)
                for conn, stamp, raw in iter_raw(reader, conns):
                    if stamp < first:
                        continue
                    wall = wall0 + (stamp - first) / 1e9 / rate
                    if clock is None:
                        _sleep_until(wall)
                    else:
                        clock.sleep_until(wall, lambda now, t0=wall0: first + int((now - t0) * rate * 1e9))
                        clock.publish(stamp)
                    publishers[conn.id].publish(bytes(raw))
                    counts[conn.topic] = counts.get(conn.topic, 0) + 1
                if not loop:
                    break
            time.sleep(0.2)  # let the last messages leave
            node.destroy_node()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            if rclpy.ok():
                rclpy.shutdown()
    return counts


def _clock_rate(text: str) -> float:
    """argparse type of --clock: a positive rate in Hz."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0:
        raise argparse.ArgumentTypeError(f"invalid rate {text!r}: expected Hz > 0 (write --clock after the bag, "
                                         "or give it a rate: --clock 40)")
    return value


def _run(args: argparse.Namespace) -> int:
    counts = play(args.bag, rate=args.rate, loop=args.loop, start_offset=args.start_offset,
                  topics=args.topics or None, delay=args.delay, wait_for_subscribers=args.wait_subscribers,
                  clock_hz=args.clock)
    print("published: " + ", ".join(f"{t} {n}" for t, n in counts.items()))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `play`."""
    parser = subparsers.add_parser("play", help="publish a bag live with rclpy at the recorded timing",
                                   description=__doc__)
    parser.add_argument("bag", help="rosbag2 (folder, .mcap or .db3)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument("--start-offset", type=float, default=0.0, help="skip the first seconds of the bag")
    parser.add_argument("--topics", nargs="+", default=None, help="only these topics")
    parser.add_argument("--clock", type=_clock_rate, nargs="?", const=DEFAULT_CLOCK_HZ, default=0.0, metavar="HZ",
                        help="also publish rosgraph_msgs/Clock on /clock with the bag time, HZ times per second "
                             f"(default {DEFAULT_CLOCK_HZ:g}) and at every message, as `ros2 bag play --clock`")
    parser.add_argument("--wait-subscribers", "--wait-for-subscribers", dest="wait_subscribers", type=float,
                        default=DEFAULT_WAIT_S, metavar="SECONDS",
                        help="before the first message, wait up to this long until every played topic has a "
                             f"subscriber (default {DEFAULT_WAIT_S:g}; 0 = no wait)")
    parser.add_argument("--delay", type=float, default=DEFAULT_DELAY_S,
                        help="seconds between that wait and the first message, for the subscribers' side of "
                             f"discovery (default {DEFAULT_DELAY_S:g})")
    parser.set_defaults(func=_run)


def main(argv: list[str] | None = None) -> int:
    """`python -m gd_completion.tools.play BAG ...` (the same as `gd-completion play`)."""
    from gd_completion.cli import main as cli_main

    return cli_main(["play", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
