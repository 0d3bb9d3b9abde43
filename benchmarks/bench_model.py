"""Benchmark GGD-Net inference: the torch path against the compiled fast path, in one run, same weights.

Usage: python benchmarks/bench_model.py [--repeats R] [--stages] [--train] [--profile] [--model PATH]

Rows (ms per vehicle, eval + inference_mode, simulated lidar scans cropped and normalised as the node does):
batch 1 with 1 and 2 torch threads, and a 16-vehicle frame over both cores (`VehicleCompleter` with one
vehicle thread per core, one torch thread each; with the measured merge, and the fast path without it). The
paths are timed interleaved (A, B, A, B, ...) so machine noise hits them alike; the min and the median over
repeats are printed, and the fast/torch ratio of the medians. The model's own dense GEMMs (every addmm/mm of
one forward, shapes recorded by the profiler) are replayed and timed in the same run: the floor that no
neighbour-search work can go under.
"""
from __future__ import annotations

import argparse
import copy
import functools
import json
import statistics
import time
from collections import Counter
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch

from gd_completion.merge import merge_with_pool
from gd_completion.model import GGDConfig, GGDNet, ggd_loss
from gd_completion.model.box_refiner import from_frame
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.network import box_shape
from gd_completion.model.ops import farthest_point_sample, gather_points, knn_graph, torch_kernels
from gd_completion.pipeline import VehicleCompleter, default_threads

PATHS = {"torch": torch_kernels, "fast": nullcontext}


def _vehicles(b: int, n: int) -> tuple[torch.Tensor, np.ndarray]:
    """`b` simulated lidar scans of procedural vehicles, cropped and normalised as the node does, and their
    box sizes (length, width, height)."""
    from gd_completion.synth.dataset import build_dataset
    data = build_dataset(b, seed=424242, n_input=n)
    return torch.from_numpy(data["partial"]), data["size"]


def _interleaved(fns: dict[str, Callable[[], object]], repeats: int, per: int) -> dict[str, list[float]]:
    """ms per vehicle of each function over `repeats` rounds, one call of each per round (after a warm-up; the
    order reversed every other round)."""
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    order = list(fns.items())
    for round_ in range(repeats):
        for name, fn in order if round_ % 2 == 0 else order[::-1]:   # alternate who runs first
            start = time.perf_counter()
            fn()
            times[name].append(1e3 * (time.perf_counter() - start) / per)
    return times


def _forward(model: GGDNet, x: torch.Tensor, shape: torch.Tensor, path: str) -> Callable[[], object]:
    def run() -> object:
        with torch.inference_mode(), PATHS[path]():
            return model(x, shape)
    return run


def _frame(completer: VehicleCompleter, partials: list[np.ndarray], sizes: np.ndarray, path: str
           ) -> Callable[[], object]:
    def run() -> object:
        with PATHS[path]():
            return completer.complete_normalized(partials, sizes)
    return run


def gemm_shapes(model: GGDNet, x: torch.Tensor, shape: torch.Tensor) -> Counter:
    """(M, K, N, has bias) -> count for every dense addmm / mm of one forward."""
    from torch.profiler import ProfilerActivity, profile
    with torch.inference_mode(), profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        model(x, shape)
    shapes: Counter = Counter()
    for event in prof.events():
        dims = [s for s in event.input_shapes if s]
        if event.name == "aten::addmm":
            (_, (m, k), (_, n)) = dims[:3]
            shapes[(m, k, n, True)] += 1
        elif event.name == "aten::mm":
            ((m, k), (_, n)) = dims[:2]
            shapes[(m, k, n, False)] += 1
    return shapes


def gemm_time_ms(shapes: Counter, repeats: int) -> float:
    """Time of the recorded GEMMs replayed on random operands (min over repeats), ms."""
    g = torch.Generator().manual_seed(0)
    operands = [(torch.randn(m, k, generator=g), torch.randn(k, n, generator=g), torch.randn(n, generator=g),
                 bias, count) for (m, k, n, bias), count in shapes.items()]

    def replay() -> None:
        for a, b, c, bias, count in operands:
            for _ in range(count):
                torch.addmm(c, a, b) if bias else torch.mm(a, b)
    replay()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        replay()
        best = min(best, time.perf_counter() - start)
    return best * 1e3


def _synchronized(model: GGDNet, x: torch.Tensor, shape: torch.Tensor) -> None:
    with torch.inference_mode():
        model(x, shape)
    torch.cuda.synchronize()


def cuda_rows(model: GGDNet, frame: torch.Tensor, shapes: torch.Tensor, device: str, repeats: int) -> None:
    """The torch path on a CUDA device: ms per vehicle at batch 1 and for the 16-vehicle batch."""
    if not torch.cuda.is_available():
        print(f"--device {device}: no CUDA device on this machine, CUDA rows skipped")
        return
    gpu = copy.deepcopy(model).to(device)
    for b in (1, len(frame)):
        times = _interleaved({"cuda": functools.partial(_synchronized, gpu, frame[:b].to(device),
                                                        shapes[:b].to(device))}, repeats, b)["cuda"]
        print(f"{device} ({torch.cuda.get_device_name(device)}), batch {b:2d}: "
              f"{min(times):6.2f} / {statistics.median(times):6.2f} ms per vehicle (min / median)")


def stages(model: GGDNet, x: torch.Tensor, shape: torch.Tensor, repeats: int) -> None:
    """Per-stage latency of the fast path, ms per vehicle at batch 1, one thread."""
    from gd_completion.spacing import even_spacing  # here: the A/B runs this script with older code too
    cfg = model.config
    shape = shape if cfg.box_conditioning else None
    with torch.inference_mode():
        n = cfg.num_input
        order = model._order(x)
        code = model.encoder(x, order, shape)
        coarse = model.decoder(code)
        pg = torch.cat([gather_points(x, order[:, :cfg.num_control]), coarse], 1)
        margin = cfg.knn_margin if cfg.window_search else None
        knn = knn_graph(pg, cfg.knn_k, margin)
        idx = model.local.group(pg, x, order)
        feat = torch.cat([model.local(pg, x, order), pg, torch.zeros(1, pg.shape[1], 2)], -1)
        out = model(x, shape)
        completion, graph = out.completion[0].numpy(), out.neighbours[0].numpy()
        parts = {
            "fps": lambda: farthest_point_sample(x, order.shape[1]),
            "encoder": lambda: model.encoder(x, order, shape),
            "decoder": lambda: model.decoder(code),
            "knn graph": lambda: knn_graph(pg, cfg.knn_k, margin),
            "ball groups": lambda: model.local.group(pg, x, order),
            "local MLP": lambda: torch.cat([model.local._features(pg[:, s:s + 1024], x, idx[:, s:s + 1024])
                                            for s in range(0, pg.shape[1], 1024)], 1),
            "G-ResNet": lambda: model.deform(feat, code, knn),
            "even spacing": lambda: even_spacing(completion, graph=graph),
            "merge": lambda: merge_with_pool(completion, x[0].numpy()),
        }
        if model.refiner is not None:   # its PointNet, the input into its frame and P_g, P_o back (GGDNet.forward)
            def refine() -> None:
                frame = model._refine(x, shape)[2]
                from_frame(pg, frame), from_frame(pg, frame)
            parts["box refiner"] = refine
        times = _interleaved(parts, repeats, 1)
    for name, ts in times.items():
        print(f"  stage {name:12s} {min(ts):7.2f} ms (min) {statistics.median(ts):7.2f} (median)  [n={n}]")


def compare_models(models: dict[str, GGDNet], frame: torch.Tensor, sizes: np.ndarray, cores: int,
                   repeats: int) -> None:
    """Fast path of several checkpoints (same input size) interleaved: batch 1 on 1 thread, 16-vehicle frame."""
    torch.set_num_threads(1)
    shapes = box_shape(sizes)
    one = _interleaved({n: _forward(m, frame[:1], shapes[:1], "fast") for n, m in models.items()}, repeats, 1)
    completers = {n: VehicleCompleter(m, threads=cores) for n, m in models.items()}
    try:
        partials = list(frame.numpy())
        many = _interleaved({n: _frame(c, partials, sizes, "fast") for n, c in completers.items()},
                            max(3, repeats // 2), len(partials))
    finally:
        for c in completers.values():
            c.close()
    print(", ".join(f"{n}: {m.num_parameters():,} parameters" for n, m in models.items()))
    for name, times in (("batch 1, 1 thread", one), (f"16-vehicle frame, {cores} vehicle threads", many)):
        cells = "  ".join(f"{n} {min(t):6.2f} / {statistics.median(t):6.2f}" for n, t in times.items())
        first, *rest = times.values()
        ratios = ", ".join(f"{statistics.median(t) / statistics.median(first):.3f}" for t in rest)
        print(f"{name:34s} fast path, {cells}  median ratio to model: {ratios}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=12)
    ap.add_argument("--stages", action="store_true", help="per-stage breakdown of the fast path")
    ap.add_argument("--train", action="store_true", help="also time a training step at batch 16 (both paths)")
    ap.add_argument("--profile", action="store_true", help="torch.profiler table of the fast path at batch 1")
    ap.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    ap.add_argument("--compare", default=None,
                    help="only time the fast path of --model against this checkpoint, interleaved (batch 1 on "
                    "1 thread and the 16-vehicle frame)")
    ap.add_argument("--device", default="cpu", help="also time the torch path on this CUDA device (e.g. cuda)")
    ap.add_argument("--untrained", action="store_true",
                    help="randomly initialised weights (a collapsed P_s: the worst case for the x-window searches)")
    ap.add_argument("--config", default=None,
                    help="with --untrained: JSON file of GGDConfig fields (e.g. recipes/ggd_v2_config.json)")
    args = ap.parse_args()
    if args.compare and (args.stages or args.train or args.profile or args.untrained or args.device != "cpu"):
        ap.error("--compare times the CPU fast path of two checkpoints only: without --stages, --train, --profile, "
                 "--untrained and --device")
    torch.manual_seed(0)
    if args.untrained:
        fields = json.loads(Path(args.config).read_text()) if args.config else {}
        model = GGDNet(GGDConfig.from_dict(fields)).eval()
    else:
        model = load_model(args.model or DEFAULT_WEIGHTS)
    cfg = model.config
    cores = default_threads()
    print(f"GGDNet {model.num_parameters():,} parameters, torch {torch.__version__}, {cores} cores; "
          f"ms per vehicle, min / median of {args.repeats} interleaved rounds")
    frame, sizes = _vehicles(16, cfg.num_input)
    shapes = box_shape(sizes)
    one, one_shape = frame[:1], shapes[:1]
    if args.compare:
        compare_models({"model": model, "compare": load_model(args.compare)}, frame, sizes, cores, args.repeats)
        return
    rows: dict[str, dict[str, list[float]]] = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        rows[f"batch 1, {threads} thread{'s' if threads > 1 else ''}"] = _interleaved(
            {p: _forward(model, one, one_shape, p) for p in PATHS}, args.repeats, 1)
    torch.set_num_threads(1)
    completer = VehicleCompleter(model, threads=cores)
    unmerged = VehicleCompleter(model, threads=cores, measured_merge=False)
    partials = list(frame.numpy())
    rows[f"16-vehicle frame, {cores} vehicle threads"] = _interleaved(
        {**{p: _frame(completer, partials, sizes, p) for p in PATHS},
         "fast without merge": _frame(unmerged, partials, sizes, "fast")}, max(3, args.repeats // 2), len(partials))
    completer.close()
    unmerged.close()
    for name, times in rows.items():
        ratio = statistics.median(times["fast"]) / statistics.median(times["torch"])
        cells = "  ".join(f"{p} {min(t):6.2f} / {statistics.median(t):6.2f}" for p, t in times.items())
        print(f"{name:34s} {cells}  fast/torch {ratio:.2f}")
    gemm = gemm_time_ms(gemm_shapes(model, one, one_shape), args.repeats)
    print(f"dense GEMMs of one vehicle (the model's addmm/mm shapes replayed, 1 thread): {gemm:.2f} ms")
    if args.device != "cpu":
        cuda_rows(model, frame, shapes, args.device, args.repeats)
    if args.stages:
        stages(model, one, one_shape, args.repeats)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile
        with torch.inference_mode(), profile(activities=[ProfilerActivity.CPU]) as prof:
            model(one, one_shape)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))
    if args.train:
        model.train()
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        x, x_sizes = _vehicles(16, cfg.num_input)
        x_shapes = box_shape(x_sizes)
        gt = x.repeat(1, cfg.num_output // cfg.num_input + 1, 1)[:, :cfg.num_output] * 1.02

        def step(path: str) -> Callable[[], None]:
            def run() -> None:
                with PATHS[path]():
                    loss = ggd_loss(model(x, x_shapes), gt, lam=3.0)["total"]
                opt.zero_grad()
                loss.backward()
                opt.step()
            return run
        times = _interleaved({p: step(p) for p in PATHS}, 3, 1)
        print("training step, batch 16, 1 thread: " + ", ".join(
            f"{p} {min(t) / 1e3:.2f} s (min)" for p, t in times.items()))


if __name__ == "__main__":
    main()
