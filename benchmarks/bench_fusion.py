"""Track fusion's cost per vehicle and frame on PandaSet-002, with and without the alignment of each frame, and
the cost of the measured merge of a fused partial (its voxel pool) against that of a single frame (the fed points).

Every vehicle track of the first --frames Pandar64 frames (cropped once, beforehand) is fed to a fresh
`TrackFusion` frame after frame; the time of each `update` is divided by the vehicles it got. Alignment on
and off alternate over --rounds rounds on the same data (ratios within one run: the machine is noisy).

    python benchmarks/bench_fusion.py [--frames 20] [--rounds 3]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.evaluation.baselines import network_outputs
from gd_completion.evaluation.fusion_eval import load_frames, vehicle_tracks
from gd_completion.fusion import FusionLimits, TrackFusion
from gd_completion.merge import merge_with_pool
from gd_completion.model.checkpoint import load_model
from gd_completion.preprocess import Preprocessing
from gd_completion.registration import align_planar
from gd_completion.sampling import resample_indices

PANDASET = Path(__file__).resolve().parents[2] / "shared" / "data" / "pandaset-002"


def run(frames: list, limits: FusionLimits) -> tuple[np.ndarray, dict[str, int]]:
    """Milliseconds per vehicle of each frame's update, and the fusion's counters at the end."""
    fusion = TrackFusion(limits)
    per_vehicle = []
    for stamp, vehicles in frames:
        start = time.perf_counter()
        fusion.update(stamp, vehicles)
        per_vehicle.append((time.perf_counter() - start) * 1e3 / max(len(vehicles), 1))
    return np.array(per_vehicle), fusion.counters


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    sequence = PandaSetSequence(PANDASET)
    indices = sequence.frame_indices()[:args.frames]
    loaded = load_frames(sequence, set(vehicle_tracks(sequence)), replace(Preprocessing(), min_points=1),
                         frames=indices)
    frames = [(sequence.stamp_ns(i), vehicles) for i, vehicles, _ in loaded]
    n_vehicles = sum(len(v) for _, v in frames)
    align_planar(np.random.default_rng(0).random((64, 3)), np.random.default_rng(1).random((64, 3)))  # compile
    print(f"PandaSet-002, Pandar64, {len(frames)} frames, {n_vehicles} vehicle-frames "
          f"({n_vehicles / len(frames):.0f} vehicles per frame); ms per vehicle and frame, mean / p95 per round")
    for r in range(args.rounds):
        on, counters = run(frames, FusionLimits())
        off, _ = run(frames, FusionLimits(align=None))
        print(f"round {r + 1}: aligned {on.mean():.3f} / {np.percentile(on, 95):.3f}   "
              f"unaligned {off.mean():.3f} / {np.percentile(off, 95):.3f}   "
              f"alignment adds {on.mean() - off.mean():.3f} ms")
    print(f"frames aligned {counters['frames_aligned']}, alignments refused {counters['alignments_refused']} "
          "(fewer than 30 points or half of the frame matched, or beyond 0.3 m / 5 degrees)")
    merge_costs(frames, args.rounds)


def merge_costs(frames: list, rounds: int) -> None:
    """The measured merge (`merge_with_pool`) of each fused partial of the last frame, ms per vehicle."""
    fusion = TrackFusion()
    for stamp, vehicles in frames:
        fused = fusion.update(stamp, vehicles)
    model = load_model()
    partials = [np.asarray(v.normalized, np.float32) for v in fused]
    _, completions = network_outputs(model, np.stack([p[resample_indices(len(p), p, model.config.num_input)]
                                                      for p in partials]),
                                     [v.box.size for v in fused])
    merge_with_pool(completions[0], partials[0])   # compile
    sizes = np.array([len(p) for p in partials])
    print(f"measured merge of the {len(partials)} fused partials of the last frame ({np.median(sizes):.0f} points "
          f"median, {sizes.max()} max), ms per vehicle:")
    for r in range(rounds):
        start = time.perf_counter()
        for partial, completion in zip(partials, completions):
            merge_with_pool(completion, partial)
        pool = (time.perf_counter() - start) * 1e3 / len(partials)
        print(f"round {r + 1}: {pool:.3f}")


if __name__ == "__main__":
    main()
