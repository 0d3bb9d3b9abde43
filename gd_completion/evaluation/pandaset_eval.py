"""Real-data evaluation on PandaSet: single-frame completions of parked vehicles vs their multi-frame aggregate."""
from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion.datasets.pandaset import PandaSetSequence, world_box_to_sensor
from gd_completion.errors import DataFormatError
from gd_completion.geometry import Box3D, box_problem, finite_mask
from gd_completion.model.network import GGDNet
from gd_completion.preprocess import Preprocessing, crop_vehicles

from .baselines import BASELINE_NAMES, mirror_symmetry, network_outputs
from .metrics import COVERAGE_SCALE, FIDELITY_SCALE, coverage_error, fidelity

# PandaSet classes that count as vehicles (data README); "Other Vehicle - ..." classes are included too.
VEHICLE_CLASSES: tuple[str, ...] = ("Car", "Pickup Truck", "Medium-sized Truck", "Semi-truck", "Bus")
OTHER_VEHICLE_PREFIX = "Other Vehicle - "
PANDAR64 = 0
MIN_INPUT_POINTS = 50
# Input-size bins (points in the box, half-open [lo, hi)).
SIZE_BINS: tuple[tuple[str, int, float], ...] = (("50-200", 50, 200), ("200-1000", 200, 1000),
                                                  (">1000", 1000, math.inf))
REFERENCE_POINTS = 4096
REFERENCE_VOXEL = 0.01  # normalised units (vehicle length = 1): about 4-5 cm on a car


def is_vehicle_class(label: str) -> bool:
    """True for the PandaSet classes evaluated as vehicles."""
    return label in VEHICLE_CLASSES or label.startswith(OTHER_VEHICLE_PREFIX)


def size_bin(n_points: int) -> str:
    """Name of the input-size bin of a vehicle with `n_points` input points ('' below the first bin)."""
    for name, lo, hi in SIZE_BINS:
        if lo <= n_points < hi:
            return name
    return ""


@dataclass
class VehicleTrack:
    """One stationary vehicle over the drive: its in-box points per frame, in the normalised box frame."""

    uuid: str
    instance_id: int
    label: str
    frames: list[int] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)  # normalised (M, 3) per frame
    boxes: list[Box3D] = field(default_factory=list)  # world-frame box per frame

    def aggregate(self) -> np.ndarray:
        """All frames' points in the box frame (normalised), (sum M, 3) float32."""
        if not self.points:
            return np.zeros((0, 3), np.float32)
        return np.concatenate(self.points).astype(np.float32, copy=False)

    def input_frames(self, min_points: int = MIN_INPUT_POINTS, max_frames: int | None = None) -> list[int]:
        """Positions (into `frames`) with >= `min_points` points; at most `max_frames`, evenly spaced."""
        ok = [k for k, p in enumerate(self.points) if len(p) >= min_points]
        if max_frames is not None and len(ok) > max_frames:
            picks = np.unique(np.round(np.linspace(0, len(ok) - 1, max(1, max_frames))).astype(int))
            ok = [ok[i] for i in picks]
        return ok


def stationary_vehicles(sequence: PandaSetSequence, sensor: int = PANDAR64) -> dict[str, str]:
    """uuid -> PandaSet class of every track marked stationary with a vehicle class (sensor `sensor` or -1)."""
    found: dict[str, str] = {}
    indices = sequence.cuboid_indices()
    if not indices:
        raise DataFormatError(f"{sequence.cuboid_dir}: no cuboid files NN{sequence.cuboid_suffix}")
    for index in indices:
        for record in sequence.cuboids(index):
            label = str(record.get("label", ""))
            if (record.get("stationary") is True and is_vehicle_class(label)
                    and int(record.get("cuboids.sensor_id", -1)) in (-1, sensor)):
                found.setdefault(str(record.get("uuid")), label)
    return found


def collect_tracks(sequence: PandaSetSequence, vehicles: dict[str, str], prep: Preprocessing, *,
                   frames: Sequence[int] | None = None, sensor: int = PANDAR64) -> dict[str, VehicleTrack]:
    """In-box points of `vehicles` (uuid -> class) in every frame, through the preprocessing contract (`prep`).

    Points and cuboids are both in the world frame, so each frame's world box takes its points into the
    box frame; the uuid links frames. Frames without a lidar file are skipped.
    """
    tracks = {uuid: VehicleTrack(uuid, sequence.track_ids.get(uuid, 0), label) for uuid, label in vehicles.items()}
    by_id = {t.instance_id: t for t in tracks.values()}
    eye, zero = np.eye(3), np.zeros(3)
    for index in (sequence.frame_indices() if frames is None else frames):
        boxes = [world_box_to_sensor(r, eye, zero, sequence.track_ids.get(str(r.get("uuid")), 0))
                 for r in sequence.cuboids(index)
                 if str(r.get("uuid")) in tracks and int(r.get("cuboids.sensor_id", -1)) in (-1, sensor)]
        boxes = [b for b in boxes if box_problem(b) is None]
        if not boxes:
            continue
        arrays = sequence.load_lidar(index)
        points = arrays["xyz"][arrays["sensor"] == sensor]
        points = points[finite_mask(points)]
        for vehicle in crop_vehicles(points, boxes, prep)[0]:
            track = by_id[vehicle.box.instance_id]
            track.frames.append(int(index))
            track.points.append(vehicle.normalized)
            track.boxes.append(vehicle.box)
    return tracks


def multi_frame_reference(track: VehicleTrack | Any, n: int = REFERENCE_POINTS) -> np.ndarray | None:
    """The track's multi-frame aggregate (`aggregate()` of a track with `frames` and `instance_id`) sampled to
    `n` near-uniform points (seeded by the track), or None for a vehicle seen in a single frame."""
    if len(track.frames) < 2:
        return None
    return reference_sample(track.aggregate(), n, seed=track.instance_id)


def reference_sample(points: np.ndarray, n: int = REFERENCE_POINTS, voxel: float = REFERENCE_VOXEL,
                     seed: int = 0) -> np.ndarray:
    """`n` points of an aggregate with near-uniform surface density: one random point per occupied voxel,
    then a random subset (or, with fewer voxels, every voxel point plus random others)."""
    points = np.asarray(points, dtype=np.float32)
    if len(points) == 0:
        raise ValueError("reference_sample: empty aggregate")
    rng = np.random.default_rng(seed)
    shuffled = points[rng.permutation(len(points))]
    cells = np.floor(shuffled / voxel).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    if len(first) >= n:
        return shuffled[rng.choice(first, n, replace=False)]
    rest = np.setdiff1d(np.arange(len(points)), first)
    extra = rng.choice(rest, n - len(first), replace=len(rest) < n - len(first)) if len(rest) else \
        rng.choice(first, n - len(first), replace=True)
    return shuffled[np.concatenate([first, extra])]


@dataclass
class PandaSetItem:
    """One (vehicle, frame) evaluation: input size and, per baseline, coverage error and fidelity (scaled)."""

    uuid: str
    label: str
    frame: int
    n_points: int
    size_bin: str
    coverage: dict[str, float]
    fidelity: dict[str, float]


@dataclass
class PandaSetResult:
    """Items of the PandaSet evaluation, render examples and bookkeeping."""

    items: list[PandaSetItem]
    n_vehicles: int
    n_candidates: int
    max_frames_per_vehicle: int | None
    seconds: dict[str, float]
    examples: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]
    notes: list[str] = field(default_factory=list)


def evaluate_pandaset(model: GGDNet, root: str | Path, *, max_frames_per_vehicle: int | None = 10,
                      max_vehicles: int | None = None, reference_points: int = REFERENCE_POINTS,
                      max_batch: int = 32, n_examples: int = 4, frames: Sequence[int] | None = None,
                      preprocessing: Preprocessing | None = None) -> PandaSetResult:
    """Complete single frames of every stationary PandaSet vehicle and compare with its multi-frame aggregate.

    `preprocessing`: the model's contract (its checkpoint's; default the contract's defaults); every frame
    with at least one point is collected (the aggregate), inputs need MIN_INPUT_POINTS.

    Inputs with >= 50 Pandar64 points in the box; at most `max_frames_per_vehicle` frames per vehicle
    (evenly spaced); vehicles whose aggregate comes from a single frame are left out (no multi-frame reference).
    """
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    sequence = PandaSetSequence(root)
    vehicles = stationary_vehicles(sequence)
    n_candidates = len(vehicles)
    if max_vehicles is not None:
        vehicles = dict(list(vehicles.items())[:max_vehicles])
    prep = replace(preprocessing or Preprocessing(), min_points=1)
    tracks = collect_tracks(sequence, vehicles, prep, frames=frames)
    seconds["load+crop"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    notes: list[str] = []
    partials: list[np.ndarray] = []
    refs: list[np.ndarray] = []
    meta: list[tuple[VehicleTrack, int]] = []
    used = 0
    single_frame = 0
    for track in tracks.values():
        picks = track.input_frames(MIN_INPUT_POINTS, max_frames_per_vehicle)
        if not picks:
            continue
        reference = multi_frame_reference(track, reference_points)
        if reference is None:
            single_frame += 1
            continue
        used += 1
        for k in picks:
            partials.append(track.points[k])
            refs.append(reference)
            meta.append((track, k))
    if single_frame:
        notes.append(f"{single_frame} vehicles seen in a single frame only were left out (no multi-frame reference)")
    generated, completion = network_outputs(model, partials, max_batch=max_batch)
    seconds["network"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    items: list[PandaSetItem] = []
    reference_batch = np.stack(refs) if refs else np.zeros((0, reference_points, 3), np.float32)
    net_cov = {"generation": coverage_error(reference_batch, generated).numpy() * COVERAGE_SCALE,
               "ggd": coverage_error(reference_batch, completion).numpy() * COVERAGE_SCALE}
    for i, ((track, k), partial, reference) in enumerate(zip(meta, partials, refs)):
        outputs = {"input": partial, "mirror": mirror_symmetry(partial)}
        cov = {name: float(coverage_error(reference, out)) * COVERAGE_SCALE for name, out in outputs.items()}
        fid = {name: float(fidelity(partial, out)) * FIDELITY_SCALE for name, out in outputs.items()}
        for name, out in (("generation", generated[i]), ("ggd", completion[i])):
            cov[name] = float(net_cov[name][i])
            fid[name] = float(fidelity(partial, out)) * FIDELITY_SCALE
        items.append(PandaSetItem(track.uuid, track.label, track.frames[k], len(partial), size_bin(len(partial)),
                                  {n: cov[n] for n in BASELINE_NAMES}, {n: fid[n] for n in BASELINE_NAMES}))
    seconds["metrics"] = time.perf_counter() - t2
    examples = _examples(items, meta, partials, completion, refs, n_examples)
    return PandaSetResult(items, used, n_candidates, max_frames_per_vehicle, seconds, examples, notes)


def _examples(items: list[PandaSetItem], meta: list[tuple[VehicleTrack, int]], partials: list[np.ndarray],
              completion: np.ndarray, refs: list[np.ndarray], n: int
              ) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Up to `n` render items (title, input, GGD-Net completion, reference): each size bin in turn, one
    frame per vehicle, the vehicles with the largest aggregates first."""
    order = sorted(range(len(items)), key=lambda i: -sum(len(p) for p in meta[i][0].points))
    chosen: list[int] = []
    seen: set[str] = set()
    for _ in range(n):
        for name, *_ in SIZE_BINS:
            if len(chosen) >= n:
                break
            for i in order:
                if items[i].size_bin == name and items[i].uuid not in seen:
                    chosen.append(i)
                    seen.add(items[i].uuid)
                    break
    return [(f"{items[i].label} {items[i].uuid[:8]} f{items[i].frame:02d}", partials[i], completion[i], refs[i])
            for i in chosen]
