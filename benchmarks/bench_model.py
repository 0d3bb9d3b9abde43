"""Benchmark GGDNet inference (eval, inference_mode) per vehicle at batch 1 and 16, and a training step.

Usage: python benchmarks/bench_model.py [--threads N] [--repeats R] [--train] [--stages] [--profile]
Reports the minimum over repeats (the machine is shared; the minimum is the least disturbed run).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from gd_completion.model import GGDConfig, GGDNet, ggd_loss
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.ops import farthest_point_sample, gather_points, knn_graph


CLOCK = time.perf_counter


def _times(fn, repeats: int, warmup: int = 2) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t = CLOCK()
        fn()
        out.append(CLOCK() - t)
    return out


def _cloud(b: int, n: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(b, n, 3, generator=g)
    x = x / x.norm(dim=-1, keepdim=True)          # points on an ellipsoid surface, vehicle-sized
    return x * torch.tensor([0.5, 0.22, 0.2])


def _vehicles(b: int, n: int) -> torch.Tensor:
    """`b` simulated lidar scans of procedural vehicles, cropped and normalised as the node does."""
    from gd_completion.synth.dataset import build_dataset
    return torch.from_numpy(build_dataset(b, seed=424242, n_input=n)["partial"])


def stages(model: GGDNet, b: int, repeats: int) -> None:
    """Per-stage latency (ms per vehicle)."""
    cfg = model.config
    x = _vehicles(b, cfg.num_input)
    with torch.inference_mode():
        n = cfg.num_input
        longest = min(n, max([cfg.num_control, n // 2, n // 8] + [n // (s * s) for s in cfg.ball_scales if s > 1]))
        order = farthest_point_sample(x, longest)
        code = model.encoder(x, order)
        coarse = model.decoder(code)
        pg = torch.cat([gather_points(x, order[:, :cfg.num_control]), coarse], 1)
        margin = cfg.knn_margin if cfg.window_search else None
        knn = knn_graph(pg, cfg.knn_k, margin)
        loc = model.local(pg, x, order)
        feat = torch.cat([loc, pg, torch.zeros(b, pg.shape[1], 2)], -1)
        parts = {
            "fps": lambda: farthest_point_sample(x, longest),
            "encoder": lambda: model.encoder(x, order),
            "decoder": lambda: model.decoder(code),
            "knn graph": lambda: knn_graph(pg, cfg.knn_k, margin),
            "local features": lambda: model.local(pg, x, order),
            "G-ResNet": lambda: model.deform(feat, code, knn),
            "total": lambda: model(x),
        }
        for name, fn in parts.items():
            print(f"  batch {b:2d} {name:15s} {1000 * min(_times(fn, repeats)) / b:7.2f} ms/vehicle")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch default)")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--train", action="store_true", help="also time a training step at batch 16")
    ap.add_argument("--stages", action="store_true", help="per-stage breakdown")
    ap.add_argument("--profile", action="store_true", help="torch.profiler table at batch 16")
    ap.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    ap.add_argument("--untrained", action="store_true",
                    help="a randomly initialised model (its P_s collapses to a blob: worst case for the x-window "
                         "neighbour search) instead of the checkpoint")
    ap.add_argument("--cpu-time", action="store_true",
                    help="report process CPU time instead of wall time (with --threads 1: the latency without "
                         "waiting for a core on a shared machine)")
    args = ap.parse_args()
    global CLOCK
    if args.cpu_time:
        CLOCK = time.process_time
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.untrained:
        model = GGDNet(GGDConfig()).eval()
    else:
        model = load_model(args.model or DEFAULT_WEIGHTS)
    cfg = model.config
    print(f"GGDNet {model.num_parameters():,} parameters, torch {torch.__version__}, {torch.get_num_threads()} threads")
    for b, reps in ((1, args.repeats), (16, max(3, args.repeats // 3))):  # stages: batch 16 unchunked
        x = _vehicles(b, cfg.num_input)
        with torch.inference_mode():
            ts = _times(lambda: model(x), reps)
        print(f"batch {b:2d}: {1000 * min(ts) / b:7.2f} ms/vehicle (min), {1000 * statistics.median(ts) / b:7.2f} (median)")
        if args.stages:
            stages(model, b, reps)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile
        x = _vehicles(16, cfg.num_input)
        with torch.inference_mode(), profile(activities=[ProfilerActivity.CPU]) as prof:
            model(x)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
    if args.train:
        model.train()
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        x, gt = _cloud(16, cfg.num_input), _cloud(16, cfg.num_output) * 1.02

        def step() -> None:
            loss = ggd_loss(model(x), gt, lam=3.0)["total"]
            opt.zero_grad()
            loss.backward()
            opt.step()
        ts = _times(step, 3, warmup=1)
        print(f"training step, batch 16: {min(ts):.2f} s (min), {statistics.median(ts):.2f} s (median)")


if __name__ == "__main__":
    main()
