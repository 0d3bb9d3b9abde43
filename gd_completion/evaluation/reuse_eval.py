"""Completion reuse on PandaSet: the published clouds of the whole sequence with reuse against every frame
completed afresh (coverage of stationary vehicles, frame-to-frame consistency), with the cuboid ids and with
the built-in association instead of them."""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.evaluation.association_eval import AssociationResult, association_agreement
from gd_completion.evaluation.fusion_eval import FusedTrack, fuse_drive
from gd_completion.evaluation.metrics import CD_SCALE, COVERAGE_SCALE
from gd_completion.evaluation.nearest import nearest_sq
from gd_completion.evaluation.pandaset_eval import (
    MIN_INPUT_POINTS,
    REFERENCE_POINTS,
    multi_frame_reference,
    wider_margin,
)
from gd_completion.evaluation.priors import mirror_template
from gd_completion.geometry import normalize
from gd_completion.preprocess import Preprocessing

# (name, track_ids, reuse on): the runs compared; "fresh" completes every vehicle in every frame
RUNS: tuple[tuple[str, str, bool], ...] = (("fresh", "message", False), ("reuse, cuboid ids", "message", True),
                                           ("reuse, association", "associate", True))


@dataclass
class ReuseRun:
    """One pass over the sequence: per (instance id, frame) the published points (normalised by the box)."""

    name: str
    outputs: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    runs: int = 0
    reused: int = 0
    seconds: float = 0.0


@dataclass(frozen=True)
class ReuseRow:
    """Coverage (stationary vehicles, x1e3) and consistency (Chamfer x1e4 between consecutive frames' published
    points, stationary and moving) of one run."""

    name: str
    runs: int
    reused: int
    seconds: float
    coverage: float
    consistency_stationary: float
    consistency_moving: float


@dataclass
class ReuseResult:
    rows: list[ReuseRow]
    vehicle_frames: int
    coverage_items: int
    association: AssociationResult
    seconds: dict[str, float]
    input_margin: float | None = None   # the completers' crop margin when wider than the contract's


def play_sequence(root: str | Path, completer: Any, sensor: int = 0, frames: int | None = None) -> ReuseRun:
    """Feed every frame (sensor frame, time order, stamped) to `completer.complete_frame`; keep each vehicle's
    published points (measured and completion, as the node publishes them) normalised by its box; the first
    `frames` frames only when given."""
    sequence = PandaSetSequence(root)
    run = ReuseRun("")
    start = time.perf_counter()
    for index in sequence.frame_indices()[:frames]:
        frame = sequence.frame(index, (sensor,))[0]
        result = completer.complete_frame(frame.xyz, frame.boxes, stamp_ns=sequence.stamp_ns(index))
        run.runs += result.stats.completions_run
        run.reused += result.stats.completions_reused
        boxes = {b.instance_id: b for b in frame.boxes}
        for key in np.unique(result.instance_id):
            rows = result.instance_id == key
            run.outputs[(int(key), int(index))] = normalize(result.points[rows], boxes[int(key)]).astype(np.float32)
    run.seconds = time.perf_counter() - start
    return run


def evaluate_reuse(root: str | Path, completer_factory: Callable[[str, bool], Any], *,
                   preprocessing: Preprocessing | None = None, reference_points: int = REFERENCE_POINTS,
                   frames: int | None = None, input_margin: float | None = None) -> ReuseResult:
    """The runs of `RUNS` (`completer_factory(track_ids, reuse)` gives a fresh completer for each), scored on the
    vehicles every run published in a frame (the same vehicle-frames for every row); the first `frames` frames of
    the sequence only when given (references from those frames too). `input_margin`: the crop margin the
    completers use when wider than the contract's (the prior's inputs then use it too; the references and the
    vehicle-frames scored keep the contract's crop). The completers keep their own points aside
    (`VehicleCompleter.pool_margin`)."""
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    indices = PandaSetSequence(root).frame_indices()[:frames]
    drive = fuse_drive(root, preprocessing=preprocessing, frames=indices, input_margin=input_margin)
    tracks = drive.tracks
    references = {i: multi_frame_reference(t, reference_points) for i, t in tracks.items() if t.stationary}
    seconds["references"] = time.perf_counter() - t0
    runs = []
    for name, track_ids, reuse in RUNS:
        run = play_sequence(root, completer_factory(track_ids, reuse), frames=frames)
        run.name = name
        runs.append(run)
        seconds[name] = run.seconds
    t1 = time.perf_counter()
    common = set.intersection(*(set(r.outputs) for r in runs))
    common = {k for k in common if k[0] in tracks}
    usable = {(i, f) for i, f in common
              if f in tracks[i].frames and tracks[i].usable(tracks[i].frames.index(f), MIN_INPUT_POINTS)}
    covered = sorted(k for k in usable if references.get(k[0]) is not None)
    runs.append(prior_run(tracks, usable))
    rows = []
    for run in runs:
        cover = [_mean_nearest_sq(reference, run.outputs[(i, f)]) for i, f in covered
                 if (reference := references[i]) is not None]
        steady: dict[bool, list[float]] = {True: [], False: []}
        for i, f in sorted(usable):
            if (i, f + 1) in usable:
                a, b = run.outputs[(i, f)], run.outputs[(i, f + 1)]
                steady[tracks[i].stationary].append(_mean_nearest_sq(a, b) + _mean_nearest_sq(b, a))
        rows.append(ReuseRow(run.name, run.runs, run.reused, run.seconds, _mean(cover) * COVERAGE_SCALE,
                             _mean(steady[True]) * CD_SCALE, _mean(steady[False]) * CD_SCALE))
    seconds["metrics"] = time.perf_counter() - t1
    return ReuseResult(rows, len(usable), len(covered), association_agreement(root), seconds,
                       wider_margin(preprocessing or Preprocessing(), input_margin))


def prior_run(tracks: dict[int, FusedTrack], keys: set[tuple[int, int]]) -> ReuseRun:
    """The no-learning baseline published as the node publishes a completion: each vehicle-frame's measured points
    beside "mirror + template" (`priors.mirror_template`, 2,048 points) of them, for the (instance id, frame) `keys`."""
    run = ReuseRun("mirror + template (no network)")
    start = time.perf_counter()
    for i, f in sorted(keys):
        track = tracks[i]
        position = track.frames.index(f)
        partial = np.asarray(track.single[position], np.float32)
        run.outputs[(i, f)] = np.concatenate([partial, mirror_template(partial, np.asarray(track.sizes[position]))])
    run.seconds = time.perf_counter() - start
    return run


def _mean_nearest_sq(source: np.ndarray, target: np.ndarray) -> float:
    """Mean squared distance from each `source` point to its nearest `target` point (`evaluation.nearest`):
    `metrics.coverage_error` (reference -> output) and one direction of `metrics.chamfer`, for clouds of any size."""
    return float(np.mean(nearest_sq(source, target)))


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def reuse_section(result: ReuseResult) -> str:
    """Markdown section of the report."""
    from gd_completion.evaluation.report import markdown_table

    fresh = result.rows[0]
    table = markdown_table(
        ["run", "network runs", "reused", "seconds", "coverage x1e3 (stationary)", "vs fresh",
         "consistency stationary", "vs fresh", "consistency moving", "vs fresh"],
        [[r.name, r.runs, r.reused, f"{r.seconds:.1f}", f"{r.coverage:.3f}", f"{r.coverage / fresh.coverage:.3f}",
          f"{r.consistency_stationary:.3f}", f"{r.consistency_stationary / fresh.consistency_stationary:.3f}",
          f"{r.consistency_moving:.3f}", f"{r.consistency_moving / fresh.consistency_moving:.3f}"]
         for r in result.rows])
    a = result.association
    return (
        "## PandaSet 002: completion reuse\n\n"
        "The whole sequence (Pandar64, sensor frame, time order) through `VehicleCompleter.complete_frame` as the node "
        "runs it (measured points published, measured merge, no track fusion): every vehicle completed in every frame "
        "(fresh) against reuse (`gd_completion.reuse`, default settings, no frame budget) keyed by the cuboid ids and "
        "by the built-in association with the ids hidden. Scored on the published points of each vehicle (its measured "
        f"points and its completion, normalised by its box) over the {result.vehicle_frames} vehicle-frames every run "
        f"published with >= {MIN_INPUT_POINTS} input points, beside the no-learning baseline published the same way "
        "(measured points and mirror + template of them, 2,048 points): coverage error against the multi-frame "
        f"reference ({result.coverage_items} stationary vehicle-frames), consistency = Chamfer x1e4 between a "
        "vehicle's published points in consecutive frames (lower is better for both)."
        + (f" Inputs cropped with a margin of {result.input_margin:g} m (the completers' crop_margin, and the "
           "baseline's); the references and the vehicle-frames scored keep the model's contract."
           if result.input_margin is not None else "") + "\n\n" + table + "\n\n"
        f"Association with the cuboid ids hidden ({a.frames} frames, {a.boxes} car/van/truck boxes, the annotated "
        f"boxes, without detector noise): {a.kept_links} of {a.true_links} true frame-to-frame links kept "
        f"({100 * a.kept:.1f} %), {a.wrong_links} of {a.links} links joining two different vehicles "
        f"({100 * a.wrong:.1f} %), {100 * a.purity:.1f} % of the boxes carry their vehicle's most frequent id.")
