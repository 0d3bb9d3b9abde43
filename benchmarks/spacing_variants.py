"""Even-spacing variants (`spacing.even_spacing`) measured on both evaluation sets in one run, each followed by the
shipped merge (`merge.merge_with_pool`, the points kept aside pooled on PandaSet: ground band, surround):

- PandaSet-002's reduced protocol (at most 8 observations per vehicle, both sensors, exact boxes; as
  `benchmarks/merge_variants.py`): coverage error x1e3 of the network's points (spaced, before the merge) and of
  the published output, overall and per input-size bucket, and the published output's fidelity x1e3;
- the held-out meshes (`evaluation.synthetic.load_heldout_meshes`, as `gd-completion evaluate`): the published
  output's CD, CD(D,G) x1e4, F-score@1 % and share of points within 2 % of the length of the true mesh surface;
- with --consistency, track fusion's frame-to-frame consistency on PandaSet-002 (`evaluation.fusion_eval`, as
  `gd-completion evaluate`: Chamfer x1e4 between consecutive published completions, single-frame and fused, and
  their ratio, parked and moving vehicles; about 100 s per variant; `exact:` variants are not supported there).

    python benchmarks/spacing_variants.py [--model PT] [--pandaset DIR] [--meshes DIR] [--heldout N]
                                          [--variants SPEC ...] [--merge-weights NETWORK:MIRROR ...] [--consistency]

A SPEC is `ITERATIONS:STEP:FLATTEN[:NEIGHBOURS]` (`spacing.SpacingSettings`, 8 neighbours unless given), `none` (the
raw P_o) or
`exact:ITERATIONS:STEP:FLATTEN` (the planes' 16 nearest searched among all points instead of the network's graph
and two hops). The shipped settings are `5:0.3:0.3`. `--merge-weights` merges each variant with these weights of the
network's and the mirror's points (`merge.merge_with_pool`; default the shipped `0.25:0.5`), one row each. Also
printed: the mirror + template prior, given the band."""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from gd_completion.evaluation import pandaset_eval as pe
from gd_completion.evaluation.baselines import network_forward
from gd_completion.evaluation.fusion_eval import evaluate_fusion
from gd_completion.evaluation.mesh_distance import distances_to_meshes, surface_shares
from gd_completion.evaluation.nearest import nearest_sq
from gd_completion.evaluation.priors import prior_outputs
from gd_completion.evaluation.synthetic import _chamfer_row, load_heldout_meshes
from gd_completion.merge import MIRROR_WEIGHT, NETWORK_WEIGHT, check_weights, merge_with_pool
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.network import GGDNet
from gd_completion.preprocess import with_aside
from gd_completion.spacing import SpacingSettings, even_spacing


def settings_of(spec: str) -> SpacingSettings | None:
    """The `SpacingSettings` of a SPEC (None for `none`)."""
    if spec == "none":
        return None
    iterations, step, flatten, *neighbours = spec.removeprefix("exact:").split(":")
    return SpacingSettings(iterations=int(iterations), step=float(step), flatten=float(flatten),
                           neighbours=int(neighbours[0]) if neighbours else SpacingSettings.neighbours)


def spaced(spec: str, raw: np.ndarray, graph: np.ndarray) -> tuple[np.ndarray, float]:
    """The variant's points (B, N_o, 3) and its ms per vehicle."""
    start = time.perf_counter()
    settings = settings_of(spec)
    if settings is None:
        out = raw.copy()
    else:
        out = even_spacing(raw, settings, graph=None if spec.startswith("exact:") else graph)
    return out, 1e3 * (time.perf_counter() - start) / max(len(raw), 1)


def print_consistency(model: GGDNet, root: str, variants: list[str]) -> None:
    """Track fusion's consistency (`fusion_eval.evaluate_fusion`) per variant."""
    print("track fusion consistency, Chamfer x1e4 between consecutive published completions: single-frame / fused / "
          "fused over single, parked | moving")
    for spec in variants:
        if spec.startswith("exact:"):
            continue
        result = evaluate_fusion(model, root, spacing=settings_of(spec))
        rows = " | ".join(f"{row.single:.3f} / {row.fused:.3f} / {row.ratio:.3f}" for row in result.consistency)
        print(f"{spec:18s} {rows}", flush=True)


def merge_weights(text: str) -> tuple[float, float]:
    """An argparse type: NETWORK:MIRROR weights of the merge (`merge.check_weights`)."""
    try:
        network, mirror = (float(w) for w in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: NETWORK:MIRROR, two numbers") from None
    try:
        check_weights(network, mirror)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{text!r}: {error}") from None
    return network, mirror


def by_bucket(values: list[float], where: np.ndarray, bins: list[str]) -> str:
    v = np.array(values)
    return f"{v.mean():.3f} " + " ".join(f"{v[where == b].mean():.3f}" for b in bins)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--pandaset", default="../shared/data/pandaset-002")
    parser.add_argument("--meshes", default="../shared/data/vehicle-meshes")
    parser.add_argument("--heldout", type=int, default=128, help="held-out mesh pairs (as the evaluation)")
    parser.add_argument("--variants", nargs="*", default=["none", "5:0.3:0", "0:0.3:0.3", "5:0.3:0.3", "8:0.3:0.3",
                                                          "5:0.3:0.45", "exact:5:0.3:0.3"])
    parser.add_argument("--merge-weights", nargs="+", type=merge_weights, default=[(NETWORK_WEIGHT, MIRROR_WEIGHT)],
                        help="NETWORK:MIRROR weights of the merge, one row per pair and variant")
    parser.add_argument("--consistency", action="store_true", help="also track fusion's consistency per variant")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_model(args.model)
    observations = pe.reduced_observations(args.pandaset)
    _, raw, graph = network_forward(model, [o[0] for o in observations], np.array([o[1] for o in observations]))
    bins = [name for name, *_ in pe.SIZE_BINS]
    where = np.array([pe.size_bin(len(o[0])) for o in observations])
    heldout = load_heldout_meshes(args.heldout, args.meshes)
    _, h_raw, h_graph = network_forward(model, list(heldout.partial), heldout.sizes)
    print(f"PandaSet: {len(observations)} observations; coverage x1e3 all / {' / '.join(bins)} of the network's "
          "points, then of the published output | its fidelity x1e3 | ms per vehicle || held-out meshes "
          f"({len(heldout.partial)} pairs), published: CD, CD(D,G) x1e4, F-score@1 %, on the surface")
    prior = [prior_outputs(with_aside(p, b), s, raw.shape[1])["mirror_template"] for p, s, _, b in observations]
    prior_coverage = [nearest_sq(o[2], q).mean() * 1e3 for o, q in zip(observations, prior)]
    print(f"{'mirror + template':22s} {by_bucket(prior_coverage, where, bins)}")
    weights: list[tuple[float, float]] = args.merge_weights
    for spec in args.variants:
        points, ms = spaced(spec, raw, graph)
        network = [nearest_sq(o[2], c).mean() * 1e3 for o, c in zip(observations, points)]
        h_points = spaced(spec, h_raw, h_graph)[0]
        for network_weight, mirror_weight in weights:
            merged = [merge_with_pool(c, p, aside=b, network_weight=network_weight, mirror_weight=mirror_weight,
                                      size=s).points for c, (p, s, _, b) in zip(points, observations)]
            published = [nearest_sq(o[2], m).mean() * 1e3 for o, m in zip(observations, merged)]
            fidelity = [nearest_sq(o[0], m).mean() * 1e3 for o, m in zip(observations, merged)]
            h_sizes = heldout.sizes if heldout.sizes is not None else [None] * len(h_points)
            h_out = np.stack([merge_with_pool(c, p, network_weight=network_weight, mirror_weight=mirror_weight,
                                              size=s).points for c, p, s in zip(h_points, heldout.partial, h_sizes)])
            row = _chamfer_row(h_out, heldout.complete)[0]
            (distance,) = distances_to_meshes([h_out], [v for v, _ in heldout.meshes], [f for _, f in heldout.meshes])
            label = spec if len(weights) == 1 else f"{spec} @{network_weight:g}:{mirror_weight:g}"
            print(f"{label:22s} {by_bucket(network, where, bins)} | {by_bucket(published, where, bins)} | "
                  f"{by_bucket(fidelity, where, bins)} | {ms:.2f} || {row['cd']:.2f} {row['cd_dg']:.2f} "
                  f"{row['f_score']:.3f} {surface_shares(distance)[0]:.3f}", flush=True)
    if args.consistency:
        print_consistency(model, args.pandaset, args.variants)


if __name__ == "__main__":
    main()
