"""Evaluation report: markdown tables (stdout and report.md) and PNG renders of completed vehicles."""
from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gd_completion.atomic import atomic_path
from gd_completion.render import render_vehicles

from .baselines import BASELINE_NAMES, BASELINE_TITLES
from .fusion_eval import RATIO_FRAMES, FusionResult
from .mesh_distance import FAR_FROM_SURFACE, NEAR_SURFACE
from .metrics import OBSERVED_RADIUS
from .observed import OBSERVED_DEFINITION, TAU
from .pandaset_eval import BAND_SIDE_ZONE, SENSOR_NAMES, SIZE_BINS, PandaSetItem, PandaSetResult
from .synthetic import AblationRow, SyntheticResult


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A pipe table; floats with 3 decimals (NaN as '-')."""
    def cell(v: object) -> str:
        if isinstance(v, float):
            return "-" if math.isnan(v) else f"{v:.3f}"
        return str(v)

    text = [[cell(v) for v in row] for row in rows]
    widths = [max([len(h)] + [len(r[i]) for r in text]) for i, h in enumerate(headers)]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(headers), sep] + [line(r) for r in text])


def synthetic_section(result: SyntheticResult, title: str = "Synthetic held-out set") -> str:
    """Table of CD x1e4, CD(D,G), CD(G,D), F-score@1%, Fidelity x1e3 and the shares on / far from the true mesh
    per method on a held-out synthetic set."""
    nan = float("nan")
    rows = [[BASELINE_TITLES[n], result.metrics[n]["cd"], result.metrics[n]["cd_dg"], result.metrics[n]["cd_gd"],
             result.metrics[n]["f_score"], result.metrics[n]["fidelity"], result.metrics[n].get("on_surface", nan),
             result.metrics[n].get("far", nan)] for n in BASELINE_NAMES]
    measured = any(not math.isnan(result.metrics[n].get("on_surface", nan)) for n in BASELINE_NAMES)
    sizes = ", ".join(f"{BASELINE_TITLES[n]} {result.points[n]}" for n in BASELINE_NAMES if n in result.points)
    return (f"## {title}\n\n{result.n_samples} pairs from {result.source}, ground truth of "
            f"{result.n_gt} points; normalised frame (vehicle length = 1). Output points: {sizes}.\n\n"
            + markdown_table(["method", "CD x1e4", "CD(D,G) x1e4", "CD(G,D) x1e4", "F-score@1%", "Fidelity x1e3",
                              "on surface", "far"], rows)
            + "\n\nCD(D,G): output -> ground truth (fidelity-like); CD(G,D): ground truth -> output (completeness); "
            "F-score@1%: harmonic mean of the fractions of output and ground-truth points within 0.01 (1 % of "
            "the vehicle length) of the other cloud."
            + f"\n\non surface: share of output points within {NEAR_SURFACE} ({100 * NEAR_SURFACE:.0f} % of the "
            "length) of the true mesh surface (exact point-to-triangle distance); far: beyond "
            f"{FAR_FROM_SURFACE}; the raw input's are those of its points."
            + ("" if measured else " Not measured here ('-'): the pairs come without their meshes (a prebuilt set "
               "read from a file).")
            + floor_text(result) + "\n\n" + region_section(result, title))


def floor_text(result: SyntheticResult) -> str:
    """The metric floor (a second uniform sample of the true surface) and each network's CD above it."""
    if not result.floor:
        return ""
    floor = result.floor["cd"]
    gen, ggd = result.metrics["generation"]["cd"], result.metrics["ggd_raw"]["cd"]   # the paper's claim: raw P_o
    return (f"\n\nMetric floor: a second uniform {result.n_gt}-point sample of the true surface scores CD {floor:.3f} "
            f"(CD(D,G) {result.floor['cd_dg']:.3f}, CD(G,D) {result.floor['cd_gd']:.3f}, F-score@1% "
            f"{result.floor.get('f_score', float('nan')):.3f}) against the ground truth{_mesh_floor(result.floor)}: "
            f"that is what a perfect completion scores at this sampling density. Above the floor, generation only "
            f"{gen - floor:.3f} and GGD-Net (raw P_o) {ggd - floor:.3f}: the deformation removes "
            f"{100 * (1 - (ggd - floor) / (gen - floor)) if gen > floor else float('nan'):.0f} % of the generation "
            f"branch's excess error (CD itself: {100 * (1 - ggd / gen):.1f} % lower).")


def _mesh_floor(floor: dict[str, float]) -> str:
    """The perfect sample's shares on / far from the true mesh ('' when not measured)."""
    on, far = floor.get("on_surface", math.nan), floor.get("far", math.nan)
    if math.isnan(on):
        return ""
    return (f", and on the true mesh: on surface {on:.3f} (1 by construction: its points are drawn on the mesh), "
            f"far {far:.3f}")


def region_section(result: SyntheticResult, title: str = "") -> str:
    """CD(G,D) x1e4 split into ground truth near the input (observed) and far from it (unobserved)."""
    rows = [[BASELINE_TITLES[n], result.metrics[n]["cd_gd_observed"], result.metrics[n]["cd_gd_unobserved"]]
            for n in BASELINE_NAMES]
    where = f" ({title})" if title else ""
    return (f"### Completeness by region{where}\n\nCD(G,D) x1e4 of the ground-truth points within "
            f"{OBSERVED_RADIUS} of an "
            f"input point (observed, {100 * result.observed_fraction:.0f} % of them) and of the others "
            "(unobserved).\n\n"
            + markdown_table(["method", "observed x1e4", "unobserved x1e4"], rows))


def ablation_section(rows: Sequence[AblationRow], n_samples: int) -> str:
    """Control-point ablation table (one row per checkpoint)."""
    table = markdown_table(["N_c", "CD(D,G) x1e4", "CD(G,D) x1e4", "CD x1e4", "generation only CD x1e4", "checkpoint"],
                           [[r.num_control, r.cd_dg, r.cd_gd, r.cd, r.cd_generation, Path(r.checkpoint).name]
                            for r in rows])
    return f"## Control-point ablation (synthetic, {n_samples} pairs, GGD-Net completion)\n\n{table}"


def _groups(items: list[PandaSetItem]) -> dict[str, list[PandaSetItem]]:
    return {"all": items, **{b: [i for i in items if i.size_bin == b] for b, *_ in SIZE_BINS}}


def _points_cell(items: list[PandaSetItem], name: str) -> str:
    counts = [i.output_points[name] for i in items if name in i.output_points]
    if not counts:
        return "-"
    if min(counts) == max(counts):
        return str(counts[0])
    return f"own: mean {np.mean(counts):.0f} ({min(counts)}-{max(counts)})"


def _metric_table(items: list[PandaSetItem], attr: str, scale: float = 1.0, points: bool = False) -> str:
    groups = _groups(items)
    headers = ["method"] + (["output points"] if points else []) + [f"{g} (n={len(v)})" for g, v in groups.items()]
    rows = [[BASELINE_TITLES[n]] + ([_points_cell(items, n)] if points else [])
            + [_nanmean([getattr(i, attr).get(n, math.nan) * scale for i in v]) for v in groups.values()]
            for n in BASELINE_NAMES]
    return markdown_table(headers, rows)


def _prior_ratios(items: list[PandaSetItem], attr: str) -> str:
    """The published completion's and the network's (evenly spaced) mean over mirror + template's, overall and per
    input-size bucket, from the unrounded means (the targets' ratios)."""
    groups = _groups(items)

    def ratios(name: str) -> str:
        means = [(_nanmean([getattr(i, attr).get(name, math.nan) for i in v]),
                  _nanmean([getattr(i, attr).get("mirror_template", math.nan) for i in v])) for v in groups.values()]
        return " / ".join(f"{a / b:.3f}" if b > 0 else "-" for a, b in means)
    return (f"Over mirror + template, from the unrounded means ({' / '.join(groups)}): published "
            f"{ratios('ggd_merge')}; network alone (evenly spaced) {ratios('ggd')}.")


def _band_zone_table(items: list[PandaSetItem]) -> str:
    """The band's coverage near the sides (tyres, wheel arches) and under the body, every observation."""
    share = _nanmean([i.band_side_share for i in items])
    table = markdown_table(
        ["method", f"within {BAND_SIDE_ZONE} m of a side", "under the body"],
        [[BASELINE_TITLES[n], _nanmean([i.band_sides.get(n, math.nan) for i in items]),
          _nanmean([i.band_under.get(n, math.nan) for i in items])] for n in BASELINE_NAMES])
    share_text = "-" if math.isnan(share) else f"{100 * share:.0f}"
    return (f"The band by where it lies (coverage error x1e3, all observations): its points within {BAND_SIDE_ZONE} m "
            f"of the box's left or right side (the tyres, wheel arches and sills; {share_text} % of the band's "
            "points on average) and the others, under the body and the overhangs (the road seen beneath the "
            "vehicle, which the network does not generate: only the frame's measured band points are published, "
            "and any low chassis part).\n\n" + table)


PLACEMENT_FLOOR_TITLE = "(oracle) the vehicle's own aggregate, placed by the box"
PLACEMENT_FLOOR_NOTE = (
    "The oracle row is not a method: a perfect completion (as many random points of the vehicle's own "
    "multi-frame aggregate as the model outputs) placed by the box it is given, as every method's output is. "
    "With the exact box it shows the metric's floor; with the noisy box, what a method loses that gets the shape "
    "right but trusts the box's placement. A method below that row locates the vehicle from its points better "
    "than the box does.")


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")


def pandaset_section(result: PandaSetResult, num_control: int | None = None, num_input: int | None = None) -> str:
    """Coverage (random and voxel-uniform reference), fidelity, the two-sided metric, per sensor and under box
    noise: every method, overall and by input size."""
    items = result.items
    sensors = " and ".join(SENSOR_NAMES.get(s, str(s)) for s in result.sensors)
    cap = result.max_frames_per_vehicle
    limit = f"at most {cap} per vehicle" if cap else "every observation"
    per_sensor = Counter(SENSOR_NAMES.get(i.sensor, str(i.sensor)) for i in items)
    parts = [f"## PandaSet 002: single frame vs multi-frame aggregate\n\n"
             f"{len(items)} observations (frame, sensor) of {result.n_vehicles} stationary vehicles "
             f"({result.n_candidates} stationary vehicle tracks in the sequence; {sensors} points, "
             + ", ".join(f"{k} {v}" for k, v in per_sensor.most_common())
             + f"; >= 50 points in the box after the crop and ground cut; "
             f"{limit}; exact boxes). Reference: the vehicle's points over all frames and sensors in its box frame. "
             f"Normalised frame (vehicle length = 1). Every method without an input count of its own outputs "
             f"2,048 points (the model's N_o); raw input and mirror keep their own counts."
             + (f" Inputs (exact and noisy boxes) cropped with a margin of {result.input_margin:g} m, wider than the "
                "model's contract; the references, the fidelity's in-box points and the size buckets (counted in "
                "the contract's crop) keep the contract's."
                if result.input_margin is not None else "")
             + (f" The measured points above the ground within {result.pool_margin:g} m of the box (the node's "
                "pool_margin) but outside the crop are kept aside like the ground band's: pooled by the measured "
                "merge and given to the raw input and the priors, not fed to the network."
                if result.pool_margin is not None else "")]
    parts.append(f"### Coverage error x1e3 (reference -> output), random reference ({result.random_points:,} points)"
                 "\n\n" + _metric_table(items, "coverage", points=True) + "\n\n" + _prior_ratios(items, "coverage"))
    parts.append(f"### Coverage error x1e3, voxel-uniform reference ({result.voxel_points} points, one per "
                 f"0.01 voxel first)\n\n" + _metric_table(items, "coverage_voxel"))
    parts.append("### Fidelity x1e3 (all in-box points above the ground cut of the frame -> output)\n\n"
                 + _metric_table(items, "fidelity"))
    parts.append("### Ground band kept: coverage error x1e3, exact box, every in-box point in the reference\n\n"
                 "The same observations and outputs; the reference is a random sample "
                 f"({result.random_points:,} points) of every point inside the exact box (no crop margin, so not "
                 "the road beside the vehicle) of every frame and sensor, the lowest 0.1 m of the box (tyres, wheel "
                 "arches and the road under them, which the crop's ground cut drops from the network's inputs) "
                 "included. The band's points inside the box's footprint are pooled by "
                 "the measured merge, and are part of the raw input and of the priors' inputs too.\n\n"
                 + _metric_table(items, "coverage_band") + "\n\n" + _prior_ratios(items, "coverage_band")
                 + "\n\nThat reference's ground-band points alone (coverage error x1e3 of the band; observations "
                 "whose reference has band points):\n\n" + _metric_table(items, "band_coverage")
                 + "\n\n" + _band_zone_table(items))
    parts.append("### Ground band kept: fidelity x1e3 (every point of the frame inside the exact box, band included -> "
                 "output)\n\n"
                 + _metric_table(items, "fidelity_band"))
    groups = _groups(items)
    rows = [[BASELINE_TITLES[n], _nanmean([i.precision[n] for i in items]), _nanmean([i.judged[n] for i in items]),
             _nanmean([i.recall[n] for i in items])] + [_nanmean([i.f_score[n] for i in v]) for v in groups.values()]
            + [f"{100 * _nanmean([i.outside_crop[n] for i in items]):.2f} %"] for n in BASELINE_NAMES]
    parts.append(f"### Two-sided: precision and F-score at tau = {TAU} (2 % of the length), random reference\n\n"
                 "Precision: share of the output points within tau of the reference, counted only where the "
                 "reference observed that part of the vehicle (judged points). Judged: share of the output judged. "
                 "Recall: share of the reference within tau of the output. F-score = 2PR / (P + R), mean over "
                 "observations. Beside the crop: share of the output points outside the exact box grown by the "
                 "contract's crop margin (published beside the vehicle: measured points of the pool margin and their "
                 "mirror image, network points past the box).\n\n"
                 + markdown_table(["method", "precision", "judged", "recall"]
                                  + [f"F-score {g} (n={len(v)})" for g, v in groups.items()] + ["beside the crop"],
                                  rows)
                 + "\n\n" + OBSERVED_DEFINITION)
    rows = [[BASELINE_TITLES[n]] + [_nanmean([i.coverage[n] for i in items if i.sensor == s]) for s in result.sensors]
            for n in BASELINE_NAMES]
    parts.append("### Coverage error x1e3 by sensor (random reference)\n\n"
                 + markdown_table(["method"] + [f"{SENSOR_NAMES.get(s, s)} (n={sum(i.sensor == s for i in items)})"
                                                for s in result.sensors], rows))
    if result.noise is not None:
        noisy = [i for i in items if i.noisy_coverage]
        rows = []
        for n in BASELINE_NAMES:
            clean = _nanmean([i.coverage[n] for i in noisy])
            shaken = _nanmean([i.noisy_coverage[n] for i in noisy])
            rows.append([BASELINE_TITLES[n], clean, shaken, f"{100 * (shaken / clean - 1):+.1f} %"]
                        + [_nanmean([i.noisy_coverage[n] for i in noisy if i.size_bin == b]) for b, *_ in SIZE_BINS])
        floors = [i for i in noisy if i.placement_floor is not None]
        if floors:
            pairs = [i.placement_floor for i in floors if i.placement_floor is not None]
            clean, shaken = (_nanmean([p[j] for p in pairs]) for j in (0, 1))
            rows.append([PLACEMENT_FLOOR_TITLE, clean, shaken, "n/a (a floor)"]
                        + [_nanmean([i.placement_floor[1] for i in floors if i.size_bin == b and i.placement_floor])
                           for b, *_ in SIZE_BINS])
        parts.append(f"### Box noise: coverage error x1e3 (random reference) with detector-like box errors\n\n"
                     f"{len(noisy)} observations. Each box perturbed ({result.noise.describe()}, drawn per (track, "
                     "frame, sensor)); the points are cropped, ground-cut and normalised with the noisy box, every "
                     "method completes (box priors from the noisy box, networks given its size), the output is "
                     "denormalised with the noisy box and renormalised with the true box, and scored against the "
                     "clean reference.\n\n"
                     + markdown_table(["method", "clean", "noisy", "degradation"]
                                      + [f"noisy {b}" for b, *_ in SIZE_BINS], rows)
                     + ("\n\n" + PLACEMENT_FLOOR_NOTE if floors else ""))
    classes = Counter(i.label for i in items)
    parts.append("Observations per class: " + ", ".join(f"{k} {v}" for k, v in classes.most_common()) + ".")
    if num_control and num_input:
        parts.append(f"The networks see each input resampled to {num_input} points (FPS down, cyclic repetition up) "
                     f"and copy {num_control} FPS control points from it, so inputs of at most {num_control} points "
                     f"are fully kept (fidelity 0) by both network methods.")
    parts += [f"Note: {note}" for note in result.notes]
    return "\n\n".join(parts)


def fusion_section(result: FusionResult) -> str:
    """Coverage error x1e3 after k fused frames and frame-to-frame consistency (Chamfer x1e4), with the targets."""
    fused = ("every frame of each vehicle fused" if result.max_frames is None
             else f"the first {result.max_frames} frames of each vehicle fused")
    caps = (fused
            + (f", the first {result.max_vehicles} stationary and {result.max_vehicles} moving vehicles"
               if result.max_vehicles is not None else "")
            + f" ({result.n_stationary} stationary, {result.n_moving} moving vehicles with >= 50 points in a frame)")
    parts = [f"## PandaSet 002: track fusion\n\nTrackFusion fed every frame in time order (Pandar64 points; {caps}). "
             "Normalised frame of the current box."]
    every = "all" if result.max_frames is None else f"all (<= {result.max_frames})"
    rows = [[str(r.k) if r.k else every, r.n_vehicles, r.raw_fused, r.fused_completion, r.n_single,
             r.fused_completion_single, r.single_completion, r.ratio, r.single_with_fused, r.measured_bound,
             r.library_oracle, r.library_ratio] for r in result.coverage]
    ratio = result.coverage_ratio(RATIO_FRAMES)
    parts.append("### Coverage error x1e3 after k fused frames (stationary vehicles)\n\n"
                 "Reference: the vehicle's points over all frames of the sequence in its box frame, 4096 voxel-uniform "
                 "samples. Completions as published (GGD-Net, then the measured merge with one of the measured points "
                 "per 1 % voxel: a single frame's or a fused partial's). "
                 "(a) GGD-Net on the fused partial, (b) the raw fused points, (c) GGD-Net on the k-th frame "
                 "alone, only where that frame itself has >= 50 points in the box ((a) is repeated over those same "
                 "vehicles for the ratio). The reference contains the fused frames, so (b) falls towards 0 as the "
                 "fused frames approach all the vehicle's frames. (d): (c) with every raw fused point added (more "
                 "points than the 2,048 published): what the fused measurements themselves can add to the single-"
                 "frame completion; (d)/(c) above a target means the fused frames saw too little that the k-th frame "
                 "had not, and only a better guess of the unseen parts could reach it. (e), at k = "
                 f"{RATIO_FRAMES} only: an oracle of that better guess, not a method: the raw fused points, their "
                 "mirror image and one real vehicle's points (another stationary vehicle's reference, stretched to "
                 "this box), thinned to 2,048 points by farthest point sampling, the vehicle picked from all the "
                 "others knowing this vehicle's reference (the best of one recipe, not a bound).\n\n"
                 + markdown_table(["k", "vehicles", "(b) raw fused", "(a) fused completion", "vehicles >= 50 pts",
                                   "(a) same vehicles", "(c) single-frame completion", "(a)/(c)",
                                   "(d) (c) + raw fused", "(d)/(c)", "(e) library oracle", "(e)/(c)"], rows)
                 + f"\n\nTarget (a)/(c) <= 0.60 at k = {RATIO_FRAMES}: {ratio:.3f}, "
                 + ("met." if ratio <= 0.60 else "not met.")
                 + f" The fused measurements alone, added in full, give (d)/(c) = {result.measured_bound():.3f} there;"
                 f" with the best-matching other vehicle's points, (e)/(c) = {result.library_ratio():.3f}.")
    rows = [[str(r.k) if r.k else every, r.n_single, r.fused_completion_single, r.single_completion, r.ratio,
             r.prior_fused, r.prior_single, r.prior_ratio] for r in result.coverage]
    parts.append("### Beside the box-only prior\n\n"
                 "The same vehicles and frames as (a)/(c): the no-learning prior mirror + template (the input, its "
                 "mirror image and the sedan template fitted to the box, thinned to 2,048 points) on the fused partial "
                 "and on the k-th frame alone. A gain of fusion that the prior shares is the fused points', not the "
                 "network's.\n\n"
                 + markdown_table(["k", "vehicles >= 50 pts", "(a) fused completion", "(c) single-frame completion",
                                   "(a)/(c)", "prior on the fused partial", "prior on the k-th frame",
                                   "prior fused / single"], rows))
    rows = [[r.group, r.n_vehicles, r.n_pairs, r.single, r.fused, r.ratio, r.single_network, r.fused_network,
             r.ratio_network] for r in result.consistency]
    verdict = ", ".join(f"{r.group} {r.ratio:.3f} ({'met' if r.ratio <= 0.5 else 'not met'}; without the merge "
                        f"{r.ratio_network:.3f})" for r in result.consistency)
    parts.append(f"### Temporal consistency (Chamfer x1e4 between consecutive completions)\n\n"
                 f"PCN's KITTI consistency: mean Chamfer between published completions of the same vehicle in "
                 f"consecutive frames, over the first {result.consistency_frames} frames of each vehicle, pairs of "
                 "frames that both have >= 50 points in the box; moving vehicles: tracks not marked stationary, "
                 "box per frame from the cuboids. The last three columns: the network's own outputs, without the "
                 "measured merge (node parameter measured_merge: false): the merge re-samples the measured points "
                 "every frame, which costs consistency.\n\n"
                 + markdown_table(["vehicles", "with >= 1 pair", "pairs", "single frame x1e4", "fused x1e4",
                                   "fused / single", "no merge: single x1e4", "no merge: fused x1e4",
                                   "no merge: fused / single"], rows)
                 + f"\n\nTarget fused / single <= 0.5 (2x more consistent): {verdict}.")
    parts += [f"Note: {note}" for note in result.notes]
    return "\n\n".join(parts)


def write_report(out_dir: str | Path, sections: Sequence[str], title: str = "GGD-Net evaluation") -> Path:
    """Write `# title` and the sections to out_dir/report.md (atomically); returns the path."""
    path = Path(out_dir) / "report.md"
    with atomic_path(path) as tmp:
        tmp.write_text(f"# {title}\n\n" + "\n\n".join(sections) + "\n")
    return path


def write_renders(out_dir: str | Path, name: str,
                  items: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]]) -> Path | None:
    """PNG of input (blue), completion (red) and reference (grey) per vehicle; None without items."""
    if not items:
        return None
    return render_vehicles(Path(out_dir) / name, list(items))
