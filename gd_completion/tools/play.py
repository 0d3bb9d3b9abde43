"""`gd-completion play`: publish a bag's topics live with rclpy at the recorded timing (raw CDR bytes)."""
from __future__ import annotations

import argparse
import math
import sys

from gd_completion.ros.player import DEFAULT_CLOCK_HZ, DEFAULT_DELAY_S, DEFAULT_WAIT_S, play, stop_on_signals


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
    """Play until the end (or, with --loop, until SIGINT/SIGTERM); a signal stops it cleanly with exit code 0."""
    with stop_on_signals() as stop:
        counts = play(args.bag, rate=args.rate, loop=args.loop, start_offset=args.start_offset,
                      topics=args.topics or None, delay=args.delay, wait_for_subscribers=args.wait_subscribers,
                      clock_hz=args.clock, stop=stop)
    stopped = f"; stopped by {stop.reason}" if stop else ""
    print("published: " + (", ".join(f"{t} {n}" for t, n in counts.items()) or "nothing") + stopped)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `play`."""
    parser = subparsers.add_parser("play", help="publish a bag live with rclpy at the recorded timing",
                                   description=__doc__ + " SIGINT or SIGTERM (Ctrl-C) stops it, with exit code 0.")
    parser.add_argument("bag", help="rosbag2 (folder, .mcap or .db3)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument("--loop", action="store_true", help="start again at the end (until Ctrl-C)")
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
