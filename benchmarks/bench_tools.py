"""Offline tool throughput: KITTI and PandaSet conversion (frames/s) and `complete` on a PandaSet bag.

Usage: python benchmarks/bench_tools.py [--complete-frames N] [--model PATH] [--threads N] [--workers N]
Reads ../shared/data (or $GD_SHARED_DATA); writes only to a temporary folder.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from gd_completion.bags.completion import complete_bag  # noqa: E402
from gd_completion.bags.dataset_conversion import convert_kitti, convert_pandaset  # noqa: E402
from gd_completion.pipeline import default_threads  # noqa: E402
from gd_completion.settings import CompletionSettings  # noqa: E402

SHARED = Path(os.environ.get("GD_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def _timed(fn):
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


class _CropOnly:
    """The pipeline minus the forward pass: crops and returns each vehicle's measured points."""

    def __init__(self, settings: CompletionSettings) -> None:
        from gd_completion.pipeline import VehicleCompleter

        self.inner = VehicleCompleter.from_settings(settings)

    def __getattr__(self, name: str):
        """The inner completer's settings (labels, preprocessing, ...), e.g. for the bag's provenance."""
        return getattr(self.inner, name)

    def complete_frame(self, points, boxes):
        import numpy as np

        from gd_completion.pipeline import FrameCompletion, FrameStats

        stats = FrameStats()
        vehicles = self.inner.prepare(points, boxes, stats)
        stats.completed = len(vehicles)
        pts = np.concatenate([v.measured for v in vehicles]) if vehicles else np.zeros((0, 3), np.float32)
        ids = np.concatenate([np.full(len(v.measured), v.box.instance_id, np.int32) for v in vehicles]) \
            if vehicles else np.zeros(0, np.int32)
        zeros = np.zeros(len(pts), np.uint8)
        return FrameCompletion(pts.astype(np.float32), ids, zeros, zeros, stats)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pandaset-frames", type=int, default=20)
    parser.add_argument("--complete-frames", type=int, default=6)
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    parser.add_argument("--threads", type=int, default=0,
                        help="vehicle threads per process (default: complete's own, one per core in one process, "
                             "1 per worker process)")
    parser.add_argument("--min-points", type=int, default=None)
    parser.add_argument("--workers", type=int, default=2, help="also time `complete --workers N` (default 2)")
    args = parser.parse_args()
    if not SHARED.is_dir():
        print(f"shared data folder {SHARED} not found (set GD_SHARED_DATA)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="gd_bench_") as tmp:
        tmp = Path(tmp)
        counts, seconds = _timed(lambda: convert_kitti(SHARED / "kitti-object-sample", tmp / "kitti", quiet=True))
        n = counts["/kitti/points"]
        print(f"convert kitti:    {n} frames in {seconds:.2f} s = {n / seconds:.1f} frames/s (MCAP, ~120k points)")
        counts, seconds = _timed(lambda: convert_pandaset(SHARED / "pandaset-002", tmp / "panda", quiet=True,
                                                          limit=args.pandaset_frames))
        n = counts["/pandar64/points"]
        print(f"convert pandaset: {n} frames in {seconds:.2f} s = {n / seconds:.1f} frames/s "
              f"(both sensors, ~170k points per frame)")
        convert_pandaset(SHARED / "pandaset-002", tmp / "panda_small", quiet=True, limit=args.complete_frames,
                         sensors=(0,))
        settings = CompletionSettings.offline(model_path=args.model or "", num_threads=args.threads or 0,
                                              min_points=args.min_points or 0)
        for workers in sorted({1, args.workers}):
            summary = complete_bag(tmp / "panda_small", tmp / f"panda_done_{workers}", settings, progress=False,
                                   workers=workers)
            rate = summary.frames / summary.seconds
            per_frame = summary.vehicles_completed / max(summary.frames, 1)
            threads = args.threads or (1 if workers > 1 else default_threads())
            print(f"complete pandaset: {summary.frames} frames in {summary.seconds:.1f} s = {rate:.2f} frames/s "
                  f"({per_frame:.0f} vehicles completed per frame, --workers {workers}, {threads} vehicle thread(s) "
                  f"each; target >= 1 frame/s {'met' if rate >= 1 else 'NOT met'})")
            print(f"  {summary.text()}")
        summary = complete_bag(tmp / "panda_small", tmp / "panda_plumbing", progress=False,
                               completer=_CropOnly(settings))
        print(f"complete pandaset without the network (decode, crop, encode, copy): "
              f"{summary.frames / summary.seconds:.1f} frames/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
