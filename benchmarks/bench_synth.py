"""Benchmark of the synthetic data generator: vehicle meshes, single-car scans, demo drive, training pairs/s."""
from __future__ import annotations

import argparse
import functools
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def _best(fn, repeat: int) -> float:
    """Fastest of `repeat` runs, seconds."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=48, help="training pairs for the samples/s figure")
    parser.add_argument("--workers", type=int, default=2, help="processes for the build_dataset figure")
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    from gd_completion.synth.beams import PATTERN_NAMES, BeamPattern
    from gd_completion.synth.dataset import V1_SAMPLING, V2_SAMPLING, build_dataset, make_sample, sample_rng
    from gd_completion.synth.lidar import simulate_scan
    from gd_completion.synth.scene import synthetic_drive
    from gd_completion.synth.vehicles import VEHICLE_KINDS, generate_vehicle

    rng = np.random.default_rng(0)
    t = _best(lambda: [generate_vehicle(rng, k) for k in VEHICLE_KINDS], 3) / len(VEHICLE_KINDS)
    print(f"generate_vehicle: {t * 1e3:.1f} ms per mesh")

    print("single sedan scan (full revolution or field of view, no ground), ms:")
    car = generate_vehicle(np.random.default_rng(1), "sedan")
    for name in PATTERN_NAMES:
        pattern = BeamPattern.named(name)
        row = []
        for dist in (10.0, 15.0, 20.0):
            world = car.transformed(0.6, (dist * np.cos(0.3), dist * np.sin(0.3), car.extent[2] / 2))
            scan = functools.partial(simulate_scan, [world], (0.0, 0.0, 1.8), pattern, rng)
            row.append(f"{dist:.0f} m {_best(scan, 5) * 1e3:5.1f} ({len(scan())} pts)")
        print(f"  {name:10s} " + "   ".join(row))

    t0 = time.perf_counter()
    frames = synthetic_drive(seed=0, n_frames=10)
    dt = time.perf_counter() - t0
    print(f"synthetic_drive(10 frames, 6 vehicles, hdl64e): {dt:.2f} s "
          f"({np.mean([len(f.points) for f in frames]):.0f} points/frame)")

    n = args.samples
    for name, options in (("V1_SAMPLING", V1_SAMPLING), ("V2_SAMPLING", V2_SAMPLING)):
        for i in range(4):  # warm the pattern tables
            make_sample(sample_rng(1, i), options=options)
        t0 = time.perf_counter()
        for i in range(n):
            make_sample(sample_rng(0, i), options=options)
        dt = time.perf_counter() - t0
        print(f"make_sample {name} (1024 / 2048 points, serial): {n / dt:.1f} samples/s")
    for name, options in (("V1_SAMPLING", V1_SAMPLING), ("V2_SAMPLING", V2_SAMPLING)):
        t0 = time.perf_counter()
        build_dataset(n, seed=0, workers=args.workers, options=options)
        dt = time.perf_counter() - t0
        print(f"build_dataset({n}, workers={args.workers}, {name}): {n / dt:.1f} samples/s (incl. process start-up)")


if __name__ == "__main__":
    main()
