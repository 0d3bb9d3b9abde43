"""`complete` on many PandaSet bags: frames/s with 1 and 2 Ray workers, and Ray against `--engine local`.

Usage: python benchmarks/bench_ray.py [--bags 3] [--frames 4] [--min-points 200] [--model PATH]
Reads ../shared/data/pandaset-002 (or $GD_SHARED_DATA); writes only to a temporary folder. Every Ray run starts
and stops its own local Ray (num_cpus = workers), as `gd-completion complete --engine ray` does; that start is
part of its time. The per-frame time budget (2 s, a real-time limit) is lifted: under CPU contention it skips
vehicles, and then outputs depend on timing. Outputs of every run are checked to be byte-identical to the
first local run's.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from gd_completion.bags.batch import complete_many, plan_jobs  # noqa: E402
from gd_completion.bags.dataset_conversion import convert_pandaset  # noqa: E402
from gd_completion.settings import CompletionSettings  # noqa: E402

SHARED = Path(os.environ.get("GD_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--bags", type=int, default=3)
    parser.add_argument("--frames", type=int, default=4, help="frames per bag")
    parser.add_argument("--min-points", type=int, default=200,
                        help="vehicles with fewer points are skipped (keeps the run short on a CPU)")
    parser.add_argument("--model", default=None)
    args = parser.parse_args()
    src = SHARED / "pandaset-002"
    if not src.is_dir():
        print(f"bench_ray: {src} not found", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for k in range(args.bags):
            convert_pandaset(src, root / "bags" / f"pandaset_{k}", limit=args.frames, start=k * args.frames,
                             sensors=(0,), quiet=True)
        frames = args.bags * args.frames
        print(f"{args.bags} PandaSet bags x {args.frames} frames (Pandar64), --min-points {args.min_points}, "
              f"{os.cpu_count()} CPUs")
        times: dict[tuple[str, int], float] = {}
        reference = None
        for engine, workers in (("local", 1), ("ray", 1), ("local", 2), ("ray", 2)):
            out = root / f"{engine}{workers}"
            jobs = plan_jobs([str(root / "bags" / "*")], out)
            start = time.perf_counter()
            outcomes = complete_many(jobs, CompletionSettings.offline(
                model_path=args.model or "", num_threads=1, min_points=args.min_points or 0), engine=engine,
                workers=workers, progress=False)
            times[engine, workers] = seconds = time.perf_counter() - start
            assert all(o.status == "done" for o in outcomes), [o.detail for o in outcomes]
            files = _files(out)
            reference = reference or files
            same = "identical to local 1" if files == reference else "DIFFERENT from local 1"
            print(f"  --engine {engine:5s} --workers {workers}: {seconds:6.1f} s, {frames / seconds:.3f} frames/s "
                  f"({same})")
        print(f"Ray scaling 1 -> 2 workers: x{times['ray', 1] / times['ray', 2]:.2f} "
              f"(local engine: x{times['local', 1] / times['local', 2]:.2f})")
        for workers in (1, 2):
            overhead = times["ray", workers] - times["local", workers]
            print(f"Ray overhead against local, {workers} worker(s): {overhead:+.1f} s "
                  f"({100 * overhead / times['local', workers]:+.0f} %, Ray start and stop included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
