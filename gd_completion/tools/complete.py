"""`gd-completion complete`: copy a bag byte for byte and add the completed vehicles of every cloud (argument
parsing; the work is `bags.completion.complete_bag` and, for many bags, `bags.batch`). The completion's flags are
generated from the settings table the node's parameters come from (`gd_completion.settings`)."""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gd_completion import settings as completion_settings
from gd_completion.atomic import refuse_existing
from gd_completion.bags import batch
from gd_completion.bags.completion import complete_bag
from gd_completion.bags.topics import DEFAULT_CLOUD_TOPICS
from gd_completion.bags.writer import STORAGES


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


def print_line(outcome: batch.BagOutcome) -> None:
    """Per-bag line: done and skipped on stdout, failed on stderr."""
    print(outcome.line(), file=sys.stderr if outcome.status == "failed" else sys.stdout, flush=True)


def _run(args: argparse.Namespace) -> int:
    settings = completion_settings.from_args(args)
    topics = {"cloud_topic": args.cloud_topic, "boxes_topic": args.boxes_topic, "output_topic": args.output_topic,
              "storage": args.storage, "skip_unknown_types": args.skip_unknown_types}
    if args.engine == "local" and batch.is_single_bag(args.input):
        summary = complete_bag(args.input[0], args.output, settings, overwrite=args.overwrite,
                               progress=not args.quiet, workers=args.workers or os.cpu_count() or 1, **topics)
        print(f"wrote {args.output}: {summary.text()}")
        return 0
    if batch.is_single_bag(args.input):  # --engine ray on one bag: OUTPUT is still the output bag
        refuse_existing(args.output, args.overwrite)
        jobs = [batch.BagJob(Path(args.input[0]), Path(args.output))]
    else:
        jobs = batch.plan_jobs(args.input, args.output)
    workers = args.workers or (1 if args.address else os.cpu_count() or 1)
    start = time.perf_counter()
    outcomes = batch.complete_many(jobs, settings, engine=args.engine, workers=workers, address=args.address,
                                   overwrite=args.overwrite, progress=not args.quiet, report=print_line, **topics)
    for outcome in outcomes:
        if outcome.status == "skipped":
            print_line(outcome)
    failed = [o for o in outcomes if o.status == "failed"]
    print(batch.summary_text(outcomes, time.perf_counter() - start))
    for outcome in failed:
        print(f"gd-completion complete: error: {outcome.detail}", file=sys.stderr)
    return 2 if failed else 0


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
                        help="Detection3DArray, Autoware DetectedObjects or TrackedObjects, or MarkerArray topic "
                             "(default: the first topic of the first of these types in the bag)")
    parser.add_argument("--output-topic", default=None, help="completed cloud topic (default: <namespace>/completed)")
    parser.add_argument("--storage", choices=STORAGES, default="mcap", help="output storage (default mcap)")
    parser.add_argument("--workers", type=_workers, default=1, metavar="N",
                        help="complete frames in N processes (default 1: in this process, its vehicles on "
                        "--threads threads); 0 = one per core. The output bag is the same for every N")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help="local: bags one after the other in this process (frames on --workers processes); "
                             "ray: one bag per Ray task on --workers workers (default local)")
    parser.add_argument("--address", default=None,
                        help="with --engine ray: the Ray cluster ('auto', 'HOST:6379' or 'ray://HOST:10001'; "
                             "default: start a local Ray with --workers CPUs)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    parser.add_argument("--skip-unknown-types", action="store_true",
                        help="leave out (with a warning) topics whose type is unknown and has no definition stored "
                             "in the bag; without it such a bag is refused, as it cannot be copied whole")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    completion_settings.add_flags(parser)
    parser.set_defaults(func=_run)
