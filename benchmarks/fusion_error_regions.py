"""Where the coverage error of the track-fusion evaluation lies after k fused frames (docs/MODEL.md, "Track fusion:
what more frames can give").

The stationary PandaSet-002 vehicles of `gd-completion evaluate`'s fusion table, fed to TrackFusion in time order;
at their k-th frame (those with >= 50 points in it) the reference points are split into "seen" (within --radius of
a fused point or its mirror image) and "unseen", and the coverage error x1e3 of each output is summed over each part
(the parts add up to the mean). Outputs: the published completions of the fused partial (a) and of the frame alone
(c), the network's own output on the fused partial, points filling the box uniformly, the fused partial's
completion with the network fed more of the fused points, the best-fitting other vehicle's shape (retrieval
without the answer) beside the fused points, and 2,048 points of the reference itself (farthest point sampling: the
floor of a 2,048-point output). Unseen points are also counted by region of the box; --plot draws the first
vehicles' reference points coloured by their distance to (a), with the fused points and (a) over them.

    python benchmarks/fusion_error_regions.py [--k 5] [--radius 0.02] [--plot regions.png]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from gd_completion.evaluation.baselines import mirror_symmetry, published_outputs
from gd_completion.evaluation.fusion_eval import fuse_drive, shape_library, stretched
from gd_completion.evaluation.metrics import COVERAGE_SCALE, nearest_sq_distance
from gd_completion.evaluation.pandaset_eval import REFERENCE_POINTS, multi_frame_reference
from gd_completion.evaluation.priors import box_fill, mirror_template, thinned_union
from gd_completion.model.checkpoint import load_checkpoint

PANDASET = Path(__file__).resolve().parents[2] / "shared" / "data" / "pandaset-002"
END_SLAB, ROOF_FLOOR_SLAB = 0.08, 0.05   # normalised depth of the box's end, roof and floor slabs


def squared(reference: np.ndarray, output: np.ndarray) -> np.ndarray:
    return nearest_sq_distance(np.asarray(reference, np.float32), np.asarray(output, np.float32)).numpy()


def regions(reference: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Per reference point: 'end', 'roof', 'floor' (slabs of the box) or 'side' (the rest)."""
    half = np.asarray(size) / size[0] / 2
    x, _, z = reference.T
    return np.where(np.abs(x) > half[0] - END_SLAB, "end", np.where(
        z > half[2] - ROOF_FLOOR_SLAB, "roof", np.where(z < -half[2] + ROOF_FLOOR_SLAB, "floor", "side")))


def retrieved(fused: np.ndarray, size: np.ndarray, library: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The fused points, their mirror and the library shape (stretched to `size`) nearest the fused points."""
    shapes = [stretched(shape, shape_size, size) for shape, shape_size in library]
    return mirror_template(fused, size, template=min(shapes, key=lambda shape: float(squared(fused, shape).mean())))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--k", type=int, default=5, help="fused frames")
    parser.add_argument("--radius", type=float, default=0.02, help="'seen' radius, normalised (length = 1)")
    parser.add_argument("--root", type=Path, default=PANDASET)
    parser.add_argument("--plot", type=Path, help="PNG of the first --plot-vehicles vehicles")
    parser.add_argument("--plot-vehicles", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, preprocessing = load_checkpoint()
    drive = fuse_drive(args.root, preprocessing=preprocessing)
    stationary = [t for t in drive.tracks.values() if t.stationary]
    references = {t.instance_id: multi_frame_reference(t, REFERENCE_POINTS) for t in stationary}
    library = shape_library(drive.tracks, references)
    chosen = [t for t in stationary if t.instance_id in library and len(t.frames) >= args.k
              and t.usable(args.k - 1)]
    p = args.k - 1
    sizes = np.array([t.sizes[p] for t in chosen], np.float64)
    fused, single = [t.fused[p] for t in chosen], [t.single[p] for t in chosen]
    outputs = {"(a) fused completion": published_outputs(model, fused, sizes),
               "(c) single-frame completion": published_outputs(model, single, sizes)}
    outputs["network output on the fused partial"] = outputs["(a) fused completion"].completion
    outputs = {name: getattr(o, "published", o) for name, o in outputs.items()}
    for count in (1024, 2048):
        wider = load_checkpoint()[0]
        wider.config = replace(model.config, num_input=count)
        outputs[f"(a) with {count} fused points fed"] = published_outputs(wider, fused, sizes).published
    outputs["box fill"] = box_fill(sizes)
    outputs["retrieval (nearest other shape) + fused + mirror"] = np.stack(
        [retrieved(f, s, [e for j, e in library.items() if j != t.instance_id])
         for t, f, s in zip(chosen, fused, sizes)])
    outputs["2,048 reference points (the floor)"] = np.stack(
        [thinned_union([references[t.instance_id]]) for t in chosen])

    unseen, share = [], {}
    for t, f, s in zip(chosen, fused, sizes):
        reference = references[t.instance_id]
        hidden = squared(reference, mirror_symmetry(f)) > args.radius ** 2
        unseen.append(hidden)
        for region in ("end", "roof", "floor", "side"):
            share[region] = share.get(region, 0) + (hidden & (regions(reference, s) == region)).sum()
    n_unseen = sum(int(h.sum()) for h in unseen)
    print(f"{len(chosen)} stationary vehicles at their fused frame {args.k}; reference {REFERENCE_POINTS} points "
          f"each; unseen (> {args.radius} from the fused points and their mirror): "
          f"{np.mean([h.mean() for h in unseen]):.3f} of the reference")
    print("unseen by region: " + ", ".join(f"{r} {v / n_unseen:.2f}" for r, v in share.items()))
    print(f"{'output':52s} {'mean':>7s} {'seen':>7s} {'unseen':>7s}  (coverage error x1e3, parts sum to the mean)")
    table = {}
    for name, clouds in outputs.items():
        errors = [squared(references[t.instance_id], c) for t, c in zip(chosen, clouds)]
        mean = np.mean([e.mean() for e in errors]) * COVERAGE_SCALE
        table[name] = mean, np.mean([e[h].sum() / len(e) for e, h in zip(errors, unseen)]) * COVERAGE_SCALE
    single = table["(c) single-frame completion"][0]
    for name, (mean, part) in table.items():
        print(f"{name:52s} {mean:7.3f} {mean - part:7.3f} {part:7.3f}  {mean / single:.3f} of (c)")
    if args.plot:
        plot(args.plot, [(t.instance_id, references[t.instance_id], f, a) for t, f, a in zip(
            chosen, fused, outputs["(a) fused completion"])][:args.plot_vehicles])


def plot(path: Path, vehicles: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """Per vehicle (id, reference, fused points, (a)): side, top and rear views of the reference coloured by the
    distance to (a) (0 to 4 % of the length), the fused points (black) and (a) (magenta) over them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(vehicles), 3, figsize=(18, 4 * len(vehicles)), squeeze=False)
    for row, (ident, reference, fused, done) in enumerate(vehicles):
        distance = np.sqrt(squared(reference, done))
        error = float(np.mean(distance ** 2)) * COVERAGE_SCALE
        for ax, (a, b, view) in zip(axes[row], [(0, 2, "side (x-z)"), (0, 1, "top (x-y)"), (1, 2, "rear (y-z)")]):
            ax.scatter(reference[:, a], reference[:, b], s=2, c=distance, cmap="jet", vmin=0, vmax=0.04)
            ax.scatter(fused[:, a], fused[:, b], s=0.3, c="k", alpha=0.3)
            ax.scatter(done[:, a], done[:, b], s=0.3, c="m", alpha=0.3)
            ax.set_aspect("equal")
            ax.set_title(f"vehicle {ident}, {view}: coverage error x1e3 {error:.3f}")
    fig.tight_layout()
    fig.savefig(path, dpi=60)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
