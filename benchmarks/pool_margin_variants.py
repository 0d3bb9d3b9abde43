"""Pool-margin variants (`preprocess.crop_vehicles(pool_margin=)`, the node's `pool_margin`) on PandaSet-002's reduced
protocol, with exact and with noisy boxes, through the evaluation itself (`pandaset_eval.evaluate_pandaset`, as
`gd-completion evaluate --max-frames-per-vehicle 8`): per margin, coverage error x1e3 of the published completion
and of the mirror + template prior, overall and per input-size bucket, exact and noisy boxes and the degradation;
the band-kept coverage (the exact box's points in the reference); fidelity; the two-sided precision at 2 % of the
length; and the share of the published points that lie outside the contract's crop of the exact box (what the wider
pool adds beside the vehicle, with exact boxes).

    python benchmarks/pool_margin_variants.py [--model PT] [--pandaset DIR] [--margins M ...] [--max-frames N]
                                              [--box-noise CENTRE_XY CENTRE_Z SIZE YAW_DEG]

0 is the crop's points only (the merge before the pool margin); the node's default is `preprocess.POOL_MARGIN`.
About a minute per margin on one core."""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from gd_completion.evaluation import pandaset_eval as pe
from gd_completion.evaluation.box_noise import BoxNoise
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint
from gd_completion.preprocess import POOL_MARGIN
from gd_completion.tools.evaluate import DEFAULT_PANDASET

BUCKETS = ("50-200", "200-1000", ">1000")
PUBLISHED, PRIOR = "ggd_merge", "mirror_template"


def mean(items: list[pe.PandaSetItem], metric: str, method: str, bucket: str | None = None) -> float:
    """Mean of one metric of one method over the items (of one size bucket), NaN left out."""
    values = [getattr(i, metric)[method] for i in items if bucket is None or i.size_bin == bucket]
    return float(np.nanmean(values)) if values else float("nan")


def row(items: list[pe.PandaSetItem], metric: str, method: str) -> str:
    """`all / bucket / bucket / bucket` of one metric."""
    return " / ".join(f"{mean(items, metric, method, b):.3f}" for b in (None, *BUCKETS))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped weights)")
    parser.add_argument("--pandaset", default=str(DEFAULT_PANDASET))
    parser.add_argument("--margins", type=float, nargs="+", default=[0.0, 0.25, POOL_MARGIN, 0.5])
    parser.add_argument("--max-frames", type=int, default=8, help="observations per vehicle (default 8)")
    parser.add_argument("--box-noise", type=float, nargs=4, default=None,
                        metavar=("CENTRE_XY", "CENTRE_Z", "SIZE", "YAW_DEG"),
                        help="the noisy boxes' standard deviations (default: the evaluation's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, preprocessing = load_checkpoint(args.model or DEFAULT_WEIGHTS)
    noise = BoxNoise(*args.box_noise) if args.box_noise else BoxNoise()
    print(f"PandaSet-002 reduced protocol (<= {args.max_frames} observations per vehicle, both sensors); box noise: "
          f"{noise.describe()}; x1e3, all / {' / '.join(BUCKETS)} points", flush=True)
    for margin in args.margins:
        start = time.perf_counter()
        result = pe.evaluate_pandaset(model, args.pandaset, max_frames_per_vehicle=args.max_frames,
                                      preprocessing=preprocessing, noise=noise, pool_margin=margin, n_examples=0)
        items = [i for i in result.items if i.noisy_coverage]
        print(f"\npool margin {margin:g} m ({len(items)} observations, {time.perf_counter() - start:.0f} s)")
        for title, method in (("published", PUBLISHED), ("mirror + template", PRIOR)):
            exact, noisy = mean(items, "coverage", method), mean(items, "noisy_coverage", method)
            print(f"  {title:18s} exact {row(items, 'coverage', method)} | noisy {row(items, 'noisy_coverage', method)}"
                  f" | degradation {100 * (noisy / exact - 1):+.1f} %")
        print(f"  published          band kept {row(items, 'coverage_band', PUBLISHED)} | fidelity "
              f"{row(items, 'fidelity', PUBLISHED)} | precision {mean(items, 'precision', PUBLISHED):.3f}"
              f" | beside the crop {100 * mean(items, 'outside_crop', PUBLISHED):.2f} % of its points", flush=True)


if __name__ == "__main__":
    main()
