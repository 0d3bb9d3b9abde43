"""Stress the completer's shutdown as `ros2 launch` does it: SIGINT, then a second SIGINT, mid-frame.

Each trial starts the node (shipped weights), feeds it the busy 20-vehicle frame of bench_node.py at 10 Hz,
and after a random 0.5-1.5 s sends SIGINT and, --gap s later, another SIGINT (or SIGTERM with --signal
term). A trial passes when the node exits with 0 within --limit s and prints no traceback and no
"terminate called". Prints every trial and the pass count.

    python benchmarks/stress_shutdown.py [--trials 20] [--gap 0.05] [--limit 2.0] [--signal int|term]
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402
from bench_node import busy_frame  # noqa: E402
from ros_live import DOMAIN_ID, Client, NodeProcess, ros_env  # noqa: E402


def trial(index: int, context, env: dict[str, str], tmp: Path, frame, args, rng) -> tuple[bool, str]:
    name = f"stress{index}"
    topics = {"cloud_topic": f"{name}_points", "boxes_topic": f"{name}_detections",
              "output_topic": f"{name}_completed_vehicles"}
    node = NodeProcess(tmp, {"boxes_type": "marker", **topics}, env, name)
    client = None
    stop_feed = threading.Event()
    try:
        node.wait_ready()
        client = Client(context, prefix=f"{name}_", node_name=name)
        client.warm_up(frame, timeout=60)

        def feed() -> None:
            while not stop_feed.is_set():
                client.send(frame)
                time.sleep(0.1)
        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        time.sleep(float(rng.uniform(0.5, 1.5)))
        sig = signal.SIGINT if args.signal == "int" else signal.SIGTERM
        start = time.monotonic()
        node.proc.send_signal(sig)
        time.sleep(args.gap)
        if node.proc.poll() is None:
            node.proc.send_signal(sig)
        try:
            code = node.proc.wait(timeout=30)
        except Exception:   # noqa: BLE001 - a hung node is a failed trial
            code = None
        seconds = time.monotonic() - start
        stop_feed.set()
        feeder.join()
        text = node.stderr
        ok = code == 0 and seconds <= args.limit and "Traceback" not in text and "terminate called" not in text
        return ok, f"exit {code} after {seconds:.2f} s{'' if ok else ': ' + text[-400:]!r}"
    finally:
        stop_feed.set()
        if client is not None:
            client.close()
        node.stop(signal.SIGKILL)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--gap", type=float, default=0.05, help="seconds between the two signals")
    ap.add_argument("--limit", type=float, default=2.0, help="seconds the node may take to exit")
    ap.add_argument("--signal", choices=("int", "term"), default="int")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    frame = busy_frame(20)
    tmp = Path(tempfile.mkdtemp(prefix="stress_shutdown_"))
    env = ros_env(tmp)
    os.environ.update(env)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    passed = 0
    try:
        for i in range(args.trials):
            ok, text = trial(i, context, env, tmp, frame, args, rng)
            passed += ok
            print(f"trial {i + 1:2d}: {'pass' if ok else 'FAIL'}: {text}", flush=True)
    finally:
        rclpy.try_shutdown(context=context)
    print(f"{passed} of {args.trials} trials exited with 0 within {args.limit} s of two SIG{args.signal.upper()}s, "
          "with no traceback")
    return 0 if passed == args.trials else 1


if __name__ == "__main__":
    sys.exit(main())
