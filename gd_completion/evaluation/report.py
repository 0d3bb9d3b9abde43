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
from .metrics import OBSERVED_RADIUS
from .pandaset_eval import SIZE_BINS, PandaSetResult
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


def synthetic_section(result: SyntheticResult) -> str:
    """Table of CD x1e4, CD(D,G), CD(G,D), F-score@1% and Fidelity x1e3 per baseline on the held-out synthetic set."""
    rows = [[BASELINE_TITLES[n], result.metrics[n]["cd"], result.metrics[n]["cd_dg"], result.metrics[n]["cd_gd"],
             result.metrics[n]["f_score"], result.metrics[n]["fidelity"]] for n in BASELINE_NAMES]
    sizes = ", ".join(f"{BASELINE_TITLES[n]} {result.points[n]}" for n in BASELINE_NAMES if n in result.points)
    return (f"## Synthetic held-out set\n\n{result.n_samples} pairs from {result.source}, ground truth of "
            f"{result.n_gt} points; normalised frame (vehicle length = 1). Output points: {sizes}.\n\n"
            + markdown_table(["method", "CD x1e4", "CD(D,G) x1e4", "CD(G,D) x1e4", "F-score@1%", "Fidelity x1e3"],
                             rows)
            + "\n\nCD(D,G): output -> ground truth (fidelity-like); CD(G,D): ground truth -> output (completeness); "
            "F-score@1%: harmonic mean of the fractions of output and ground-truth points within 0.01 (1 % of "
            "the vehicle length) of the other cloud."
            + floor_text(result) + "\n\n" + region_section(result))


def floor_text(result: SyntheticResult) -> str:
    """The metric floor (a second uniform sample of the true surface) and each network's CD above it."""
    if not result.floor:
        return ""
    floor = result.floor["cd"]
    gen, ggd = result.metrics["generation"]["cd"], result.metrics["ggd"]["cd"]
    return (f"\n\nMetric floor: a second uniform {result.n_gt}-point sample of the true surface scores CD {floor:.3f} "
            f"(CD(D,G) {result.floor['cd_dg']:.3f}, CD(G,D) {result.floor['cd_gd']:.3f}, F-score@1% "
            f"{result.floor.get('f_score', float('nan')):.3f}) against the ground truth: "
            f"that is what a perfect completion scores at this sampling density. Above the floor, generation only "
            f"{gen - floor:.3f} and GGD-Net {ggd - floor:.3f}: the deformation removes "
            f"{100 * (1 - (ggd - floor) / (gen - floor)) if gen > floor else float('nan'):.0f} % of the generation "
            f"branch's excess error (CD itself: {100 * (1 - ggd / gen):.1f} % lower).")


def region_section(result: SyntheticResult) -> str:
    """CD(G,D) x1e4 split into ground truth near the input (observed) and far from it (unobserved)."""
    rows = [[BASELINE_TITLES[n], result.metrics[n]["cd_gd_observed"], result.metrics[n]["cd_gd_unobserved"]]
            for n in BASELINE_NAMES]
    return (f"### Completeness by region\n\nCD(G,D) x1e4 of the ground-truth points within {OBSERVED_RADIUS} of an "
            f"input point (observed, {100 * result.observed_fraction:.0f} % of them) and of the others "
            "(unobserved).\n\n"
            + markdown_table(["method", "observed x1e4", "unobserved x1e4"], rows))


def ablation_section(rows: Sequence[AblationRow], n_samples: int) -> str:
    """Control-point ablation table (one row per checkpoint)."""
    table = markdown_table(["N_c", "CD(D,G) x1e4", "CD(G,D) x1e4", "CD x1e4", "generation only CD x1e4", "checkpoint"],
                           [[r.num_control, r.cd_dg, r.cd_gd, r.cd, r.cd_generation, Path(r.checkpoint).name]
                            for r in rows])
    return f"## Control-point ablation (synthetic, {n_samples} pairs, GGD-Net completion)\n\n{table}"


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def pandaset_section(result: PandaSetResult, num_control: int | None = None, num_input: int | None = None) -> str:
    """Coverage error and Fidelity (x1e3) per baseline, overall and by input size."""
    bins = [name for name, *_ in SIZE_BINS]
    groups = {"all": result.items, **{b: [i for i in result.items if i.size_bin == b] for b in bins}}
    headers = ["method"] + [f"{g} (n={len(items)})" for g, items in groups.items()]
    parts = [f"## PandaSet 002: single frame vs multi-frame aggregate\n\n"
             f"{len(result.items)} vehicle-frames of {result.n_vehicles} stationary vehicles "
             f"({result.n_candidates} stationary vehicle tracks in the sequence; Pandar64 points, >= 50 points "
             f"in the box, at most {result.max_frames_per_vehicle or 'all'} frames per vehicle). Reference: the "
             f"vehicle's points over all frames in its box frame, 4096 voxel-uniform samples. Normalised frame."]
    for title, attr in (("Coverage error x1e3 (reference -> output)", "coverage"),
                        ("Fidelity x1e3 (input -> output)", "fidelity")):
        rows = [[BASELINE_TITLES[n]] + [_mean([getattr(i, attr)[n] for i in items]) for items in groups.values()]
                for n in BASELINE_NAMES]
        parts.append(f"### {title}\n\n" + markdown_table(headers, rows))
    classes = Counter(i.label for i in result.items)
    parts.append("Vehicle-frames per class: " + ", ".join(f"{k} {v}" for k, v in classes.most_common()) + ".")
    if num_control and num_input:
        parts.append(f"The networks see each input resampled to {num_input} points (FPS down, cyclic repetition up) "
                     f"and copy {num_control} FPS control points from it, so inputs of at most {num_control} points "
                     f"are fully kept (fidelity 0) by both network methods.")
    parts += [f"Note: {note}" for note in result.notes]
    return "\n\n".join(parts)


def fusion_section(result: FusionResult) -> str:
    """Coverage error x1e3 after k fused frames and frame-to-frame consistency (Chamfer x1e4), with the targets."""
    caps = (f"the first {result.max_frames} frames of each vehicle fused"
            + (f", the first {result.max_vehicles} stationary and {result.max_vehicles} moving vehicles"
               if result.max_vehicles is not None else "")
            + f" ({result.n_stationary} stationary, {result.n_moving} moving vehicles with >= 50 points in a frame)")
    parts = [f"## PandaSet 002: track fusion\n\nTrackFusion fed every frame in time order (Pandar64 points; {caps}). "
             "Normalised frame of the current box."]
    rows = [[str(r.k) if r.k else f"all (<= {result.max_frames})", r.n_vehicles, r.raw_fused, r.fused_completion,
             r.n_single, r.fused_completion_single, r.single_completion, r.ratio] for r in result.coverage]
    ratio = result.coverage_ratio(RATIO_FRAMES)
    parts.append("### Coverage error x1e3 after k fused frames (stationary vehicles)\n\n"
                 "Reference: the vehicle's points over all frames of the sequence in its box frame, 4096 voxel-uniform "
                 "samples. (a) GGD-Net on the fused partial, (b) the raw fused points, (c) GGD-Net on the k-th frame "
                 "alone, only where that frame itself has >= 50 points in the box ((a) is repeated over those same "
                 "vehicles for the ratio). The reference contains the fused frames, so (b) falls towards 0 as the "
                 "fused frames approach all the vehicle's frames.\n\n"
                 + markdown_table(["k", "vehicles", "(b) raw fused", "(a) fused completion", "vehicles >= 50 pts",
                                   "(a) same vehicles", "(c) single-frame completion", "(a)/(c)"], rows)
                 + f"\n\nTarget (a)/(c) <= 0.60 at k = {RATIO_FRAMES}: {ratio:.3f}, "
                 + ("met." if ratio <= 0.60 else "not met."))
    rows = [[r.group, r.n_vehicles, r.n_pairs, r.single, r.fused, r.ratio] for r in result.consistency]
    verdict = ", ".join(f"{r.group} {r.ratio:.3f} ({'met' if r.ratio <= 0.5 else 'not met'})"
                        for r in result.consistency)
    parts.append(f"### Temporal consistency (Chamfer x1e4 between consecutive completions)\n\n"
                 f"PCN's KITTI consistency: mean Chamfer between GGD-Net completions of the same vehicle in "
                 f"consecutive frames, over the first {result.consistency_frames} frames of each vehicle, pairs of "
                 "frames that both have >= 50 points in the box; moving vehicles: tracks not marked stationary, "
                 "box per frame from the cuboids.\n\n"
                 + markdown_table(["vehicles", "with >= 1 pair", "pairs", "single frame x1e4", "fused x1e4",
                                   "fused / single"], rows)
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
