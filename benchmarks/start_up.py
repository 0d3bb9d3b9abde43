"""Start-up of the `completer` node: seconds from process start to "completer ready", and a SIGINT/SIGTERM at
moments of start-up (while torch is imported, the model loads, after ready): exit code and seconds to exit.

    python benchmarks/start_up.py [--runs 3]
"""
from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))

from ros_live import ros_env  # noqa: E402

COMMAND = [sys.executable, "-m", "gd_completion.ros.completer_main", "--ros-args", "-p", "boxes_type:=marker"]


def start(tmp: Path) -> tuple[subprocess.Popen, Path]:
    err = tmp / f"start_{time.monotonic_ns()}.stderr"
    proc = subprocess.Popen(COMMAND, cwd=REPO, env={**__import__("os").environ, **ros_env(tmp)},
                            stdout=subprocess.DEVNULL, stderr=err.open("w"))
    return proc, err


def time_to_ready(tmp: Path) -> float:
    began = time.monotonic()
    proc, err = start(tmp)
    while "completer ready" not in err.read_text():
        if proc.poll() is not None or time.monotonic() - began > 180:
            raise SystemExit(f"completer did not get ready:\n{err.read_text()[-2000:]}")
        time.sleep(0.02)
    ready = time.monotonic() - began
    proc.send_signal(signal.SIGINT)
    proc.wait(30)
    return ready


def signal_at(tmp: Path, delay: float, sig: int) -> tuple[int, float, bool]:
    """(exit code, seconds from the signal to the exit, traceback printed)."""
    proc, err = start(tmp)
    time.sleep(delay)
    sent = time.monotonic()
    proc.send_signal(sig)
    code = proc.wait(30)
    return code, time.monotonic() - sent, "Traceback" in err.read_text()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        ready = [time_to_ready(tmp) for _ in range(args.runs)]
        print("process start -> 'completer ready': " + ", ".join(f"{t:.1f}" for t in ready) + " s")
        for delay in (0.05, 0.5, 1.0, 2.0, 3.0, 4.0, max(ready) + 1.0):
            for sig in (signal.SIGINT, signal.SIGTERM):
                code, took, trace = signal_at(tmp, delay, sig)
                print(f"{signal.Signals(sig).name} {delay:.2f} s after start: exit {code} in {took:.2f} s"
                      f"{', TRACEBACK' if trace else ''}")


if __name__ == "__main__":
    main()
