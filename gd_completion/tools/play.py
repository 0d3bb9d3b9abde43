"""`gd-completion play`: publish a bag's topics live with rclpy at the recorded timing (raw CDR bytes)."""
from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path
from typing import Any

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.errors import BagError


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


def play(path: str | Path, *, rate: float = 1.0, loop: bool = False, start_offset: float = 0.0,
         topics: list[str] | None = None, delay: float = 0.5, wait_for_subscribers: float = 0.0,
         log=print) -> dict[str, int]:
    """Publish the bag; returns messages published per topic. Topics whose type rclpy lacks are skipped.

    Waits `delay` seconds after creating the publishers, and up to `wait_for_subscribers` seconds until every
    publisher has a matched subscription.
    """
    if rate <= 0:
        raise BagError(f"--rate must be positive, got {rate}")
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
            time.sleep(max(0.0, delay))  # let subscribers discover the publishers
            deadline = time.monotonic() + wait_for_subscribers
            while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in publishers.values()):
                time.sleep(0.05)
            first = reader.start_time + int(start_offset * 1e9)
            while True:
                wall0 = time.monotonic()
                for conn, stamp, raw in iter_raw(reader, conns):
                    if stamp < first:
                        continue
                    wait = wall0 + (stamp - first) / 1e9 / rate - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
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


def _run(args: argparse.Namespace) -> int:
    counts = play(args.bag, rate=args.rate, loop=args.loop, start_offset=args.start_offset,
                  topics=args.topics or None, delay=args.delay, wait_for_subscribers=args.wait_for_subscribers)
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
    parser.add_argument("--delay", type=float, default=0.5,
                        help="seconds between creating publishers and the first message (discovery)")
    parser.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="SECONDS",
                        help="wait up to this long until every topic has a subscriber (default 0)")
    parser.set_defaults(func=_run)


def main(argv: list[str] | None = None) -> int:
    """`python -m gd_completion.tools.play BAG ...` (the same as `gd-completion play`)."""
    parser = argparse.ArgumentParser(prog="gd-completion")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["play", *(sys.argv[1:] if argv is None else argv)])
    try:
        return _run(args)
    except BagError as error:
        print(f"gd-completion play: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
