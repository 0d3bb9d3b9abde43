"""Track fusion on PandaSet: fused-partial completion vs single frames (coverage) and frame-to-frame consistency."""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from gd_completion.datasets.pandaset import PandaSetSequence, world_box_to_sensor
from gd_completion.geometry import box_problem, finite_mask
from gd_completion.model.network import GGDNet
from gd_completion.preprocess import POOL_MARGIN, CroppedVehicle, Preprocessing, crop_vehicles
from gd_completion.spacing import SHIPPED_SPACING, SpacingSettings

from .baselines import published_outputs
from .metrics import CD_SCALE, COVERAGE_SCALE, chamfer, coverage_error
from .pandaset_eval import (
    MIN_INPUT_POINTS,
    PANDAR64,
    REFERENCE_POINTS,
    input_preprocessing,
    is_vehicle_class,
    multi_frame_reference,
    stationary_vehicles,
    wider_margin,
)
from .priors import PRIOR_POINTS, mirror_template

# Fused frames after which coverage is reported; "all" (0 here) = every fused frame up to the cap.
FUSED_FRAMES: tuple[int, ...] = (1, 2, 5, 10, 20, 40, 0)
RATIO_FRAMES = 5  # the target: coverage (fused completion) / (single-frame completion) <= 0.60 at k = 5


class Fusion(Protocol):
    """What the evaluation needs of `gd_completion.fusion.TrackFusion`."""

    def update(self, stamp_ns: int, vehicles: Sequence[CroppedVehicle]) -> list[CroppedVehicle]: ...


@dataclass
class FusedTrack:
    """One vehicle through the drive (Pandar64, causal order): per frame it is seen in, the frame's own
    normalised points (as cropped for the network, and as the contract crops them for the reference) and (within
    the frame cap) the fused partial TrackFusion returned."""

    uuid: str
    instance_id: int
    label: str
    stationary: bool
    frames: list[int] = field(default_factory=list)
    single: list[np.ndarray] = field(default_factory=list)  # normalised (M, 3), every frame
    fused: list[np.ndarray] = field(default_factory=list)   # normalised fused partial, first `max_frames` frames
    sizes: list[tuple[float, ...]] = field(default_factory=list)  # box (length, width, height) per frame
    asides: list[np.ndarray] = field(default_factory=list)  # the frame's points kept aside (`CroppedVehicle.aside`)
    fused_asides: list[np.ndarray] = field(default_factory=list)   # the same as the fusion hands them out, per `fused`
    # per frame, as `single`, the contract's crop (normalised): `single`'s arrays unless the inputs were cropped wider
    references: list[np.ndarray] = field(default_factory=list)

    def aggregate(self) -> np.ndarray:
        """All frames' points in the box frame (normalised), as the contract crops them: the multi-frame
        reference."""
        return np.concatenate(self.references).astype(np.float32, copy=False) if self.references else \
            np.zeros((0, 3), np.float32)

    def usable(self, position: int, min_points: int = MIN_INPUT_POINTS) -> bool:
        """True when the vehicle has >= `min_points` points in the frame at `position` itself (counted in the
        contract's crop, so every input margin scores the same vehicle-frames)."""
        return len(self.references[position]) >= min_points



def _ratio(numerator: float, denominator: float) -> float:
    return numerator / denominator if denominator > 0 else float("nan")


@dataclass
class CoverageRow:
    """Coverage error x1e3 after `k` fused frames (k = 0: all fused frames up to the cap), means over vehicles."""

    k: int
    n_vehicles: int
    raw_fused: float
    fused_completion: float
    n_single: int                  # vehicles with >= MIN_INPUT_POINTS in that frame itself
    fused_completion_single: float  # fused completion over those same vehicles
    single_completion: float
    single_with_fused: float = float("nan")   # the single-frame completion with every raw fused point added
    library_oracle: float = float("nan")      # `library_oracle` over the same vehicles (k = RATIO_FRAMES only)
    prior_fused: float = float("nan")         # the box-only prior mirror + template on the fused partial and
    prior_single: float = float("nan")        # on the k-th frame alone, both over the vehicles of (c)

    @property
    def ratio(self) -> float:
        """Fused completion / single-frame completion on the same vehicle-frames."""
        return _ratio(self.fused_completion_single, self.single_completion)

    @property
    def measured_bound(self) -> float:
        """(single-frame completion + every raw fused point) / single-frame completion: how far the fused
        measurements themselves, added in full to the single-frame completion, lower its error."""
        return _ratio(self.single_with_fused, self.single_completion)

    @property
    def prior_ratio(self) -> float:
        """Mirror + template on the fused partial / on the k-th frame alone: what fusion gives the box-only prior."""
        return _ratio(self.prior_fused, self.prior_single)

    @property
    def library_ratio(self) -> float:
        """(e) `library_oracle` / single-frame completion: what the best of the other vehicles' aggregates, picked
        knowing the reference, gives beside the fused measurements (an oracle of one recipe, not a bound)."""
        return _ratio(self.library_oracle, self.single_completion)


@dataclass
class ConsistencyRow:
    """Mean Chamfer x1e4 between completions of one vehicle in consecutive frames."""

    group: str  # "stationary" or "moving"
    n_vehicles: int
    n_pairs: int
    single: float    # published completions (after the measured merge)
    fused: float
    single_network: float = float("nan")   # the network's own outputs, without the merge
    fused_network: float = float("nan")
    ratio: float = field(init=False)   # fused / single-frame (smaller is more consistent)
    ratio_network: float = field(init=False)

    def __post_init__(self) -> None:
        self.ratio = _ratio(self.fused, self.single)
        self.ratio_network = _ratio(self.fused_network, self.single_network)


@dataclass
class FusionResult:
    """Both parts of the fusion evaluation and their caps."""

    coverage: list[CoverageRow]
    consistency: list[ConsistencyRow]
    max_frames: int | None   # None: every frame of each vehicle
    consistency_frames: int
    max_vehicles: int | None
    n_stationary: int
    n_moving: int
    seconds: dict[str, float]
    notes: list[str] = field(default_factory=list)

    def coverage_ratio(self, k: int = RATIO_FRAMES) -> float:
        """(a)/(c) at `k` fused frames (NaN when the row is missing)."""
        return self._row_value(k, "ratio")

    def measured_bound(self, k: int = RATIO_FRAMES) -> float:
        """(d)/(c) at `k` fused frames (`CoverageRow.measured_bound`; NaN when the row is missing)."""
        return self._row_value(k, "measured_bound")

    def library_ratio(self, k: int = RATIO_FRAMES) -> float:
        """(e)/(c) at `k` fused frames (`CoverageRow.library_ratio`; NaN when the row is missing or not computed)."""
        return self._row_value(k, "library_ratio")

    def _row_value(self, k: int, name: str) -> float:
        row = next((r for r in self.coverage if r.k == k), None)
        return float("nan") if row is None else float(getattr(row, name))


def consistency(completions: Sequence[np.ndarray], frames: Sequence[int]) -> list[float]:
    """Chamfer (unscaled) between completions of consecutive frames (frame numbers differing by one)."""
    pairs = [(i, i + 1) for i in range(len(frames) - 1) if frames[i + 1] == frames[i] + 1]
    if not pairs:
        return []
    a = np.stack([completions[i] for i, _ in pairs])
    b = np.stack([completions[j] for _, j in pairs])
    return [float(v) for v in chamfer(a, b)]


def library_oracle(reference: np.ndarray, measured: np.ndarray, size: np.ndarray,
                   library: Sequence[tuple[np.ndarray, np.ndarray]], n: int = PRIOR_POINTS) -> float:
    """Coverage error (unscaled) of the best of the outputs "`measured` (normalised), its mirror image and one
    library shape, thinned to `n` points by farthest point sampling", chosen knowing `reference`: an oracle, not
    a method. Each library entry is a vehicle's points (normalised by its own box) and its box size, stretched
    per axis to `size`; NaN for an empty library."""
    measured = np.asarray(measured, np.float32).reshape(-1, 3)
    errors = [float(coverage_error(reference, mirror_template(measured, size, n, stretched(shape, shape_size, size))))
              for shape, shape_size in library]
    return min(errors, default=float("nan"))


def stretched(shape: np.ndarray, shape_size: Sequence[float] | np.ndarray, size: Sequence[float] | np.ndarray
              ) -> np.ndarray:
    """(M, 3) float32: a vehicle's points, normalised by its own box of `shape_size`, stretched per axis to the
    normalised frame of a box of `size` (both (length, width, height))."""
    target, source = np.asarray(size, np.float64), np.asarray(shape_size, np.float64)
    return np.asarray(shape, np.float32) * ((target / target[0]) / (source / source[0])).astype(np.float32)


def shape_library(tracks: dict[int, FusedTrack], references: dict[int, np.ndarray | None]
                  ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Instance id -> (reference, median box size) of every track with a reference: `library_oracle`'s shapes."""
    return {i: (r, np.median(np.array(tracks[i].sizes), axis=0)) for i, r in references.items() if r is not None}


def vehicle_tracks(sequence: PandaSetSequence, sensor: int = PANDAR64) -> dict[str, tuple[str, bool]]:
    """uuid -> (class, stationary) of every vehicle track of the sequence (sensor `sensor` or -1)."""
    parked = stationary_vehicles(sequence, sensor)
    found: dict[str, tuple[str, bool]] = {}
    for index in sequence.cuboid_indices():
        for record in sequence.cuboids(index):
            label, uuid = str(record.get("label", "")), str(record.get("uuid"))
            if is_vehicle_class(label) and int(record.get("cuboids.sensor_id", -1)) in (-1, sensor):
                found.setdefault(uuid, (parked.get(uuid, label), uuid in parked))
    return found


def load_frames(sequence: PandaSetSequence, uuids: set[str], prep: Preprocessing, sensor: int = PANDAR64,
                frames: Sequence[int] | None = None, input_margin: float | None = None,
                pool_margin: float = POOL_MARGIN) -> list[tuple[int, list[CroppedVehicle], list[CroppedVehicle]]]:
    """(frame, vehicles of `uuids` cropped for the network, the same cropped by the contract `prep`) per frame in
    time order, the two lists in the same order; world-frame boxes and points. `input_margin`
    (`pandaset_eval.input_preprocessing`): the first list's crop margin, wider than the contract's (None or the
    contract's: both lists are the same); a vehicle the contract's crop does not hold is left out of both.
    `pool_margin`: the margin of the points kept aside for the merge (`preprocess.crop_vehicles`), as the pipeline's."""
    inputs = input_preprocessing(prep, input_margin)
    eye, zero = np.eye(3), np.zeros(3)
    out: list[tuple[int, list[CroppedVehicle], list[CroppedVehicle]]] = []
    for index in (sequence.frame_indices() if frames is None else frames):
        records: dict[str, dict] = {}
        for r in sequence.cuboids(index):
            uuid = str(r.get("uuid"))
            if uuid in uuids and int(r.get("cuboids.sensor_id", -1)) in (-1, sensor):
                records.setdefault(uuid, r)  # one box per track and frame
        boxes = [world_box_to_sensor(r, eye, zero, sequence.track_ids.get(u, 0)) for u, r in records.items()]
        boxes = [b for b in boxes if box_problem(b) is None]
        if not boxes:
            continue
        arrays = sequence.load_lidar(index)
        points = arrays["xyz"][arrays["sensor"] == sensor]
        points = points[finite_mask(points)]
        references = crop_vehicles(points, boxes, prep, pool_margin)[0]
        if inputs is prep:
            out.append((int(index), references, references))
            continue
        held = [v.box for v in references]   # the same boxes, so a wider crop holds each of them too
        out.append((int(index), crop_vehicles(points, held, inputs, pool_margin)[0], references))
    return out


def _positions(track: FusedTrack, max_frames: int | None, consistency_frames: int
               ) -> tuple[list[tuple[int, int]], list[int]]:
    """((k, position) of the coverage rows, consistency positions) of a track, within the caps."""
    n = len(track.frames) if max_frames is None else min(len(track.frames), max_frames)
    cover = [(k, k - 1 if k else n - 1) for k in FUSED_FRAMES if k <= n] if track.stationary else []
    steady = [p for p in range(min(n, consistency_frames)) if track.usable(p)]
    return cover, steady


@dataclass
class FusedDrive:
    """The chosen vehicles of a drive fed to a track fusion frame by frame (`fuse_drive`)."""

    tracks: dict[int, FusedTrack]   # by instance id
    dropped: int                    # vehicle-frames the fusion returned nothing for (their own frame kept)
    counters: dict[str, int]        # the fusion's counters at the end (when it has them)
    seconds: dict[str, float]


def fuse_drive(root: str | Path, *, max_frames: int | None = None, max_vehicles: int | None = None,
               preprocessing: Preprocessing | None = None, frames: Sequence[int] | None = None,
               fusion_factory: Callable[[], Fusion] | None = None, input_margin: float | None = None,
               pool_margin: float = POOL_MARGIN) -> FusedDrive:
    """Feed PandaSet's vehicles (Pandar64, time order) frame by frame to a fresh fusion, each vehicle's first
    `max_frames` frames (None: all); `max_vehicles`: the first N stationary and first N moving vehicles with
    >= MIN_INPUT_POINTS points in one frame. `fusion_factory`: default `gd_completion.fusion.TrackFusion`.
    `input_margin`: the crop margin of what the fusion is fed (the node's `crop_margin`; `load_frames`); the
    references and the points counted keep the contract's crop; `pool_margin`: as `load_frames`."""
    if fusion_factory is None:
        from gd_completion.fusion import TrackFusion
        fusion_factory = TrackFusion
    max_frames = None if max_frames is None else max(1, max_frames)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    sequence = PandaSetSequence(root)
    kinds = vehicle_tracks(sequence)
    prep = replace(preprocessing or Preprocessing(), min_points=1)
    loaded = load_frames(sequence, set(kinds), prep, frames=frames, input_margin=input_margin, pool_margin=pool_margin)
    ids = {sequence.track_ids.get(u, 0): u for u in kinds}
    tracks = {i: FusedTrack(u, i, *kinds[u]) for i, u in ids.items()}
    for index, vehicles, references in loaded:
        for vehicle, reference in zip(vehicles, references, strict=True):
            track = tracks[vehicle.box.instance_id]
            track.frames.append(index)
            track.single.append(vehicle.normalized)
            track.references.append(reference.normalized)
            track.sizes.append(vehicle.box.size)
            track.asides.append(vehicle.aside)
    seen = [t for t in tracks.values() if any(t.usable(p) for p in range(len(t.frames)))]
    chosen = {t.instance_id: t for group in (True, False)
              for t in [t for t in seen if t.stationary == group][:max_vehicles]}
    seconds["load+crop"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    fusion = fusion_factory()
    dropped = 0
    for index, vehicles, _ in loaded:
        fed = [v for v in vehicles if v.box.instance_id in chosen
               and (max_frames is None or len(chosen[v.box.instance_id].fused) < max_frames)]
        if not fed:
            continue
        returned = {v.box.instance_id: v for v in fusion.update(sequence.stamp_ns(index), fed)}
        for vehicle in fed:  # a vehicle the fusion did not return keeps its own frame (counted in the notes)
            out = returned.get(vehicle.box.instance_id)
            dropped += out is None
            chosen[vehicle.box.instance_id].fused.append(np.asarray((out or vehicle).normalized, np.float32))
            chosen[vehicle.box.instance_id].fused_asides.append((out or vehicle).aside)
    seconds["fusion"] = time.perf_counter() - t1
    return FusedDrive(chosen, dropped, dict(getattr(fusion, "counters", {})), seconds)


def evaluate_fusion(model: GGDNet, root: str | Path, *, max_frames: int | None = None, consistency_frames: int = 10,
                    max_vehicles: int | None = None, reference_points: int = REFERENCE_POINTS, max_batch: int = 32,
                    preprocessing: Preprocessing | None = None, frames: Sequence[int] | None = None,
                    fusion_factory: Callable[[], Fusion] | None = None,
                    spacing: SpacingSettings | None = SHIPPED_SPACING, input_margin: float | None = None,
                    pool_margin: float = POOL_MARGIN) -> FusionResult:
    """Feed PandaSet's vehicles frame by frame to TrackFusion and complete the fused partials.

    Coverage (stationary vehicles seen in >= 2 frames, reference = all frames' points): the raw fused points,
    their completion and the single-frame completion after k of the vehicle's first `max_frames` frames (None:
    all of them); at k = RATIO_FRAMES also `library_oracle` with the other stationary vehicles' references.
    Consistency (stationary and moving): Chamfer between completions in consecutive frames among the first
    `consistency_frames` frames of each vehicle, frames with >= MIN_INPUT_POINTS points only.
    `max_vehicles`, `frames`, `fusion_factory`, `input_margin`, `pool_margin`: as `fuse_drive`; `spacing`: the
    completions' even spacing (as `published_outputs`; None: off).
    """
    max_frames = None if max_frames is None else max(1, max_frames)
    drive = fuse_drive(root, max_frames=max_frames, max_vehicles=max_vehicles, preprocessing=preprocessing,
                       frames=frames, fusion_factory=fusion_factory, input_margin=input_margin,
                       pool_margin=pool_margin)
    chosen, dropped, seconds = drive.tracks, drive.dropped, dict(drive.seconds)

    t2 = time.perf_counter()
    plans = {i: _positions(t, max_frames, consistency_frames) for i, t in chosen.items()}
    fused_keys = sorted({(i, p) for i, (cover, steady) in plans.items() for p in [p for _, p in cover] + steady})
    single_keys = sorted({(i, p) for i, (cover, steady) in plans.items() for p in [p for _, p in cover] + steady
                          if chosen[i].usable(p)})
    # both clouds are normalised by the frame's own box (the fused partial by the current box): its sizes
    # (the published completion: the network's after the measured merge, as the pipeline gives it)
    fused_in = [chosen[i].fused[p] for i, p in fused_keys]
    fused = published_outputs(model, fused_in, np.array([chosen[i].sizes[p] for i, p in fused_keys]).reshape(-1, 3),
                              max_batch=max_batch, asides=[chosen[i].fused_asides[p] for i, p in fused_keys],
                              spacing=spacing)
    single_in = [chosen[i].single[p] for i, p in single_keys]
    single = published_outputs(model, single_in, np.array([chosen[i].sizes[p] for i, p in single_keys]).reshape(
        -1, 3), max_batch=max_batch, asides=[chosen[i].asides[p] for i, p in single_keys], spacing=spacing)
    fused_done, single_done = dict(zip(fused_keys, fused.published)), dict(zip(single_keys, single.published))
    fused_network, single_network = dict(zip(fused_keys, fused.completion)), dict(zip(single_keys, single.completion))
    seconds["network"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    notes = [f"TrackFusion returned no fused partial for {dropped} vehicle-frames (their own frame was used)"] \
        if dropped else []
    wider = wider_margin(preprocessing or Preprocessing(), input_margin)
    if wider is not None:
        notes.append(f"inputs (each frame's crop fed to the fusion and to the single-frame completion) cropped with "
                     f"a margin of {wider:g} m, as the node's crop_margin; references and the vehicle-frames "
                     "scored keep the model's contract")
    counters = drive.counters
    if "frames_aligned" in counters:
        aligned, refused = counters["frames_aligned"], counters["alignments_refused"]
        notes.append(f"frames aligned to their track before fusion: {aligned}, alignments refused: {refused} "
                     "(stored as their boxes place them)" if aligned + refused else
                     "no frame was aligned to its track (alignment off: frames stored as their boxes place them)")
    references = {i: multi_frame_reference(t, reference_points) for i, t in chosen.items() if plans[i][0]}
    single_only = sum(r is None for r in references.values())
    library = shape_library(chosen, references)
    per_k: dict[int, list[tuple[float, ...]]] = {k: [] for k in FUSED_FRAMES}
    for i, (cover, _) in plans.items():
        track, reference = chosen[i], references.get(i)
        if reference is None:
            continue
        for k, p in cover:
            size = np.asarray(track.sizes[p])
            raw, done = _coverage(reference, track.fused[p]), _coverage(reference, fused_done[(i, p)])
            prior_fused = _coverage(reference, mirror_template(track.fused[p], size))
            one = plus = oracle = prior_single = float("nan")
            if (i, p) in single_done:
                one = _coverage(reference, single_done[(i, p)])
                plus = _coverage(reference, np.concatenate([single_done[(i, p)], track.fused[p]]))
                prior_single = _coverage(reference, mirror_template(track.single[p], size))
                if k == RATIO_FRAMES:
                    oracle = library_oracle(reference, track.fused[p], size, [
                        entry for j, entry in library.items() if j != i]) * COVERAGE_SCALE
            per_k[k].append((raw, done, one, plus, oracle, prior_fused, prior_single))
    if single_only:
        notes.append(f"{single_only} stationary vehicles seen in a single frame only were left out of the coverage "
                     "table (no multi-frame reference)")
    coverage = []
    for k, rows in per_k.items():
        values = np.array(rows, dtype=np.float64).reshape(-1, 7)
        same = values[~np.isnan(values[:, 2])]
        coverage.append(CoverageRow(k, len(values), _mean(values[:, 0]), _mean(values[:, 1]), len(same),
                                    _mean(same[:, 1]), _mean(same[:, 2]), _mean(same[:, 3]), _mean(same[:, 4]),
                                    _mean(same[:, 5]), _mean(same[:, 6])))
    rows_c = []
    for name, group in (("stationary", True), ("moving", False)):
        single_cd: list[float] = []
        fused_cd: list[float] = []
        single_net: list[float] = []
        fused_net: list[float] = []
        vehicles = 0
        for i, (_, steady) in plans.items():
            track = chosen[i]
            if track.stationary != group:
                continue
            frames_used = [track.frames[p] for p in steady]
            pairs = consistency([single_done[(i, p)] for p in steady], frames_used)
            vehicles += bool(pairs)
            single_cd += pairs
            fused_cd += consistency([fused_done[(i, p)] for p in steady], frames_used)
            single_net += consistency([single_network[(i, p)] for p in steady], frames_used)
            fused_net += consistency([fused_network[(i, p)] for p in steady], frames_used)
        rows_c.append(ConsistencyRow(name, vehicles, len(single_cd), *(_mean(np.array(v)) * CD_SCALE for v in (
            single_cd, fused_cd, single_net, fused_net))))
    seconds["metrics"] = time.perf_counter() - t3
    n_stationary = sum(t.stationary for t in chosen.values())
    return FusionResult(coverage, rows_c, max_frames, consistency_frames, max_vehicles, n_stationary,
                        len(chosen) - n_stationary, seconds, notes)


def _coverage(reference: np.ndarray, output: np.ndarray) -> float:
    """Coverage error x1e3 (`metrics.coverage_error` times COVERAGE_SCALE)."""
    return float(coverage_error(reference, output)) * COVERAGE_SCALE


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else float("nan")
