"""Decode throughput of the Hesai decoder (packets/s, points/s) on the shared Pandar40P / Pandar64 recordings."""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import deserialize
from gd_completion.hesai import ScanAssembler, decode_packets, load_calibration
from gd_completion.hesai.packets import packets_to_array

DEFAULT_DATA = Path(os.environ.get("GD_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
BAGS = {
    "pandar40p": ("hesai-nebula/40p/1673400149412331409", "hesai-nebula/calibration/Pandar40P.csv"),
    "pandar64": ("hesai-nebula/64/1673403880599376836", "hesai-nebula/calibration/Pandar64.csv"),
}


def load_packets(bag: Path) -> list[list[bytes]]:
    """Packets of each PandarScan message of a bag."""
    out = []
    with open_bag(bag) as reader:
        for conn, _, raw in iter_raw(reader):
            msg = deserialize(raw, conn.msgtype)
            out.append([bytes(p.data[: int(p.size)]) for p in msg.packets])
    return out


def bench(model: str, data: Path, repeat: int) -> None:
    """Print decode and scan-assembly throughput for one model."""
    bag, csv = BAGS[model]
    messages = load_packets(data / bag)
    calibration = load_calibration(data / csv)
    packets = [p for m in messages for p in m]
    _, array = packets_to_array(packets)

    def best_of(fn) -> tuple[float, int]:
        times, n = [], 0
        for _ in range(repeat):
            start = time.perf_counter()
            n = fn()
            times.append(time.perf_counter() - start)
        return min(times), n

    t_array, n_points = best_of(lambda: len(decode_packets(array, calibration)))
    t_bytes, _ = best_of(lambda: len(decode_packets(packets, calibration)))

    def assemble() -> int:
        assembler = ScanAssembler(calibration)
        return sum(len(s) for m in messages for s in assembler.add(m)) + sum(len(s) for s in assembler.flush())

    t_asm, _ = best_of(assemble)
    n = len(packets)
    print(f"{model}: {n} packets of {array.shape[1]} bytes, {n_points} points (dual return, 0.3-200 m)")
    for label, t in (("decode (uint8 array)", t_array), ("decode (list of bytes)", t_bytes),
                     ("ScanAssembler per message", t_asm)):
        print(f"  {label:28s} {t * 1e3:8.1f} ms  {n / t:10,.0f} packets/s  {n_points / t:12,.0f} points/s  "
              f"({n / t / (n / len(messages) * 10):.1f}x real time at 10 Hz)")


def main() -> None:
    """Command line: `python benchmarks/bench_hesai.py [--data DIR] [--repeat N] [--model ...]`."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--model", choices=(*BAGS, "all"), default="all")
    args = parser.parse_args()
    for model in (BAGS if args.model == "all" else (args.model,)):
        bench(model, args.data, args.repeat)


if __name__ == "__main__":
    main()
