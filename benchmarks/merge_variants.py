"""Measured-merge variants on PandaSet-002's reduced protocol (at most 8 observations per vehicle, both sensors,
exact boxes): coverage error and fidelity x1e3, overall and per input-size bucket, of the network's completions
merged in several ways, beside the network alone and the mirror + template prior.

    python benchmarks/merge_variants.py [--model PT] [--pandaset DIR] [--raw] [--variants SPEC ...]

The completions are the network's points evenly spaced (`spacing.even_spacing`), as the pipeline merges them;
`--raw` merges the network's points as they come (how the merge's table in docs/MODEL.md was made).

A SPEC is `pool:VOXEL:NETWORK_WEIGHT:MIRROR_WEIGHT` (one measured point per VOXEL voxel, 0: all of them; the
weights of the weighted FPS, `kernels.fps_pruned`), `fed` (the 512 points fed to the network, unweighted: the
merge before model v3) or `sor:K:Z` (the shipped merge after dropping the completion's points whose mean distance
to their K nearest is above the mean + Z standard deviations); the variants pool the points above the ground cut only.
The shipped merge is `merge.merge_with_pool` with the points the crop kept aside pooled too (the ground band in the
box's footprint and, since the pool margin, the surround within `preprocess.POOL_MARGIN`), as the pipeline does
(printed as "shipped"); the mirror + template prior gets those points as well."""
from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from gd_completion.evaluation import pandaset_eval as pe
from gd_completion.evaluation.baselines import _resampled, network_forward
from gd_completion.evaluation.nearest import nearest_sq
from gd_completion.evaluation.priors import prior_outputs
from gd_completion.kernels import fps_pruned
from gd_completion.merge import POOL_VOXEL, merge_measured, merge_with_pool, mirrored
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.preprocess import with_aside
from gd_completion.sampling import voxel_first_indices
from gd_completion.spacing import even_spacing

# (completion, partial, rows fed to the network, box size, points kept aside) -> output points
Merge = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def weighted(voxel: float, network: float, mirror: float) -> Merge:
    """The merge's weighted FPS (`merge.merge_measured` with these weights) of a pool of the points above the ground
    cut (one per `voxel` voxel; 0: all of them)."""
    def merge(completion: np.ndarray, partial: np.ndarray, fed: np.ndarray, size: np.ndarray,
              band: np.ndarray) -> np.ndarray:
        pool = partial[voxel_first_indices(partial, voxel)] if voxel else partial
        return merge_measured(completion, pool, len(completion), network_weight=network, mirror_weight=mirror).points
    return merge


def outliers_dropped(k: int, z: float) -> Merge:
    """The shipped merge after dropping the completion's isolated points: mean distance to their k nearest
    completion points above the cloud's mean + z standard deviations."""
    def merge(completion: np.ndarray, partial: np.ndarray, fed: np.ndarray, size: np.ndarray,
              band: np.ndarray) -> np.ndarray:
        spread = cKDTree(completion).query(completion, k + 1)[0][:, 1:].mean(1)
        keep = spread <= spread.mean() + z * spread.std()
        pool = partial[voxel_first_indices(partial, POOL_VOXEL)]
        if 2 * len(pool) + keep.sum() < len(completion):
            keep[:] = True
        return merge_measured(completion[keep], pool, len(completion)).points
    return merge


def fed_only(completion: np.ndarray, partial: np.ndarray, fed: np.ndarray, size: np.ndarray,
             band: np.ndarray) -> np.ndarray:
    pool = partial[fed[:min(len(partial), len(fed))]]
    union = np.ascontiguousarray(np.concatenate([pool, mirrored(pool), completion]), np.float32)
    return union[fps_pruned(union, len(completion))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--pandaset", default="../shared/data/pandaset-002")
    parser.add_argument("--raw", action="store_true",
                        help="merge the network's raw points (as before even spacing; the MODEL.md merge table)")
    parser.add_argument("--variants", nargs="*", default=["fed", "pool:0.02:1:1", "pool:0:0.5:1", "pool:0:0.1:1",
                                                          "pool:0.01:0.25:0.5", "pool:0.01:0.3:0.6"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_model(args.model)
    observations = pe.reduced_observations(args.pandaset)
    batch, rows = _resampled([o[0] for o in observations], model.config.num_input)
    _, completions, graph = network_forward(model, batch, np.array([o[1] for o in observations]))
    if not args.raw:   # as the pipeline: the network's points evenly spaced before any merge
        completions = even_spacing(completions, graph=graph)
    merges: dict[str, Merge] = {
        "network alone": lambda c, p, r, s, b: c,
        "mirror + template": lambda c, p, r, s, b: prior_outputs(with_aside(p, b), s, len(c))["mirror_template"],
        "shipped": lambda c, p, r, s, b: merge_with_pool(c, p, aside=b, size=s).points}
    for spec in args.variants:
        kind, *values = spec.split(":")
        merges[spec] = fed_only if kind == "fed" else outliers_dropped(int(values[0]), float(values[1])) \
            if kind == "sor" else weighted(*(float(v) for v in values))
    bins = [name for name, *_ in pe.SIZE_BINS]
    print(f"{len(observations)} observations; coverage x1e3 all / {' / '.join(bins)} | fidelity x1e3 the same | "
          "ms per vehicle")
    for name, merge in merges.items():
        coverage, fidelity, where = [], [], []
        spent = 0.0
        for (partial, size, reference, band), completion, fed in zip(observations, completions, rows):
            start = time.perf_counter()
            out = merge(completion, partial, fed, size, band)
            spent += time.perf_counter() - start
            coverage.append(nearest_sq(reference, out).mean() * 1e3)
            fidelity.append(nearest_sq(partial, out).mean() * 1e3)
            where.append(pe.size_bin(len(partial)))
        cov, fid, at = np.array(coverage), np.array(fidelity), np.array(where)
        print(f"{name:20s} {cov.mean():.3f} " + " ".join(f"{cov[at == b].mean():.3f}" for b in bins)
              + f" | {fid.mean():.3f} " + " ".join(f"{fid[at == b].mean():.3f}" for b in bins)
              + f" | {1e3 * spent / len(observations):.2f}")


if __name__ == "__main__":
    main()
