"""Offline completion reuse: `gd-completion complete BAG OUT --track-fusion` with and without `--reuse` on the
PandaSet-002 bag (converted with `gd-completion convert pandaset`, Pandar64 only), alternating, whole processes.

Prints each run's wall seconds and its summary line (network completions run and reused), then each round's
ratio with / without reuse.

    python benchmarks/bench_offline_reuse.py [--rounds 3] [--extra "--track-ids message"]
"""
from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
CLI = [sys.executable, "-m", "gd_completion.cli"]


def run(bag: Path, out: Path, reuse: bool, extra: list[str]) -> tuple[float, str]:
    args = [*CLI, "complete", str(bag), str(out), "--track-fusion", "--workers", "1", "--quiet", "--overwrite",
            *(["--reuse"] if reuse else []), *extra]
    start = time.perf_counter()
    done = subprocess.run(args, cwd=REPO, capture_output=True, text=True, check=True)
    return time.perf_counter() - start, done.stdout.strip().splitlines()[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--extra", default="", help="more arguments for both commands")
    args = ap.parse_args()
    extra = shlex.split(args.extra)
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "pandaset"
        subprocess.run([*CLI, "convert", "pandaset", str(SHARED / "pandaset-002"), str(bag), "--sensors", "0"],
                       cwd=REPO, check=True, capture_output=True)
        for round_ in range(args.rounds):
            with_reuse, line_on = run(bag, Path(tmp) / "on", True, extra)
            without, line_off = run(bag, Path(tmp) / "off", False, extra)
            print(f"round {round_ + 1}: --reuse {with_reuse:.1f} s ({line_on})\n"
                  f"         without {without:.1f} s ({line_off})\n"
                  f"         ratio {with_reuse / without:.2f}", flush=True)


if __name__ == "__main__":
    main()
