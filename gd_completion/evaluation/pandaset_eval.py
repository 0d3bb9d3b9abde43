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
from gd_completion.geometry import Box3D, box_problem, finite_mask, normalize
from gd_completion.model.network import GGDNet
from gd_completion.preprocess import POOL_MARGIN, CroppedVehicle, Preprocessing, above_ground, crop_vehicles, with_aside

from .baselines import BASELINE_NAMES, mirror_symmetry, published_outputs
from .box_noise import BoxNoise, noisy_box, reframe
from .metrics import COVERAGE_SCALE, FIDELITY_SCALE
from .nearest import nearest_sq
from .observed import MAX_POSES, TAU, RangeImages, pose_subset, range_images, two_sided
from .priors import prior_outputs

# PandaSet classes that count as vehicles (data README); "Other Vehicle - ..." classes are included too.
VEHICLE_CLASSES: tuple[str, ...] = ("Car", "Pickup Truck", "Medium-sized Truck", "Semi-truck", "Bus")
OTHER_VEHICLE_PREFIX = "Other Vehicle - "
PANDAR64 = 0
PANDARGT = 1
SENSORS: tuple[int, ...] = (PANDAR64, PANDARGT)
SENSOR_NAMES = {PANDAR64: "Pandar64", PANDARGT: "PandarGT"}
MIN_INPUT_POINTS = 50
# Input-size bins (points in the box, half-open [lo, hi)).
SIZE_BINS: tuple[tuple[str, int, float], ...] = (("50-200", 50, 200), ("200-1000", 200, 1000),
                                                  (">1000", 1000, math.inf))
REFERENCE_POINTS = 4096           # voxel-uniform reference
RANDOM_REFERENCE_POINTS = 20_000  # random reference (the scorer)
DEFAULT_BOX_NOISE = BoxNoise()
REFERENCE_VOXEL = 0.01  # normalised units (vehicle length = 1): about 4-5 cm on a car
# The ground band's points within this many metres of a side of the box are the tyres' and wheel arches' zone; those
# farther inside lie under the body or the overhangs (the road seen beneath the vehicle, and any low chassis part).
BAND_SIDE_ZONE = 0.4


def is_vehicle_class(label: str) -> bool:
    """True for the PandaSet classes evaluated as vehicles."""
    return label in VEHICLE_CLASSES or label.startswith(OTHER_VEHICLE_PREFIX)


def size_bin(n_points: int) -> str:
    """Name of the input-size bin of a vehicle with `n_points` points in the contract's crop ('' below the first
    bin)."""
    for name, lo, hi in SIZE_BINS:
        if lo <= n_points < hi:
            return name
    return ""


@dataclass
class VehicleTrack:
    """One stationary vehicle over the drive: its in-box points per (frame, sensor) entry, in the normalised
    box frame, with the world box, the sensor position and (box-noise runs) the crop of a noisy box. `points` are
    the inputs (cropped with the input margin), `reference` the same entry through the evaluation's contract (the
    aggregate's points; the same arrays when the margins agree)."""

    uuid: str
    instance_id: int
    label: str
    frames: list[int] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)  # normalised (M, 3) per entry
    boxes: list[Box3D] = field(default_factory=list)  # world-frame box per entry
    sensors: list[int] = field(default_factory=list)  # PandaSet sensor id per entry
    origins: list[np.ndarray] = field(default_factory=list)  # world sensor position (poses.json) per entry
    noisy: list[CroppedVehicle | None] = field(default_factory=list)  # the crop of the noisy box
    asides: list[np.ndarray] = field(default_factory=list)  # normalised (K + S, 3) per entry: `CroppedVehicle.aside`
    in_box: list[np.ndarray] = field(default_factory=list)  # normalised (M', 3) per entry: every point inside
    # the exact box (no crop margin), the ground band (the lowest `ground_clearance` of the box) included
    reference: list[np.ndarray] = field(default_factory=list)  # normalised (R, 3) per entry: the contract's crop

    def aggregate(self) -> np.ndarray:
        """All entries' reference points in the box frame (normalised), (sum R, 3) float32."""
        if not self.reference:
            return np.zeros((0, 3), np.float32)
        return np.concatenate(self.reference).astype(np.float32, copy=False)

    def aggregate_in_box(self) -> np.ndarray:
        """All entries' points inside the exact box, ground band included (normalised), (sum M', 3) float32."""
        if not self.in_box:
            return np.zeros((0, 3), np.float32)
        return np.concatenate(self.in_box).astype(np.float32, copy=False)

    def input_frames(self, min_points: int = MIN_INPUT_POINTS, max_frames: int | None = None) -> list[int]:
        """Positions (into `frames`) with >= `min_points` reference points (the same observations whatever the
        input margin); at most `max_frames`, evenly spaced."""
        ok = [k for k, p in enumerate(self.reference) if len(p) >= min_points]
        if max_frames is not None and len(ok) > max_frames:
            picks = np.unique(np.round(np.linspace(0, len(ok) - 1, max(1, max_frames))).astype(int))
            ok = [ok[i] for i in picks]
        return ok

    def pose_scans(self, max_poses: int = MAX_POSES, sensor: int = PANDAR64) -> list[tuple[np.ndarray, np.ndarray]]:
        """(sensor position, points) in the normalised box frame for at most `max_poses` entries of `sensor`
        (evenly spaced over its frames; poses.json holds that lidar's pose): the scans of `observed`."""
        entries = [k for k, s in enumerate(self.sensors) if s == sensor]
        rich = [k for k in entries if len(self.reference[k]) >= MIN_INPUT_POINTS] or entries
        return [(normalize(self.origins[k][None], self.boxes[k])[0], self.reference[k])
                for k in (rich[i] for i in pose_subset(len(rich), max_poses))]


def vehicle_tracks(sequence: PandaSetSequence, sensor: int | Sequence[int] = PANDAR64, *,
                   stationary_only: bool = False) -> dict[str, str]:
    """uuid -> PandaSet class (its first record's) of every track with a vehicle class (cuboid sensor id -1 or one of
    `sensor`); with `stationary_only`, only of the tracks with a record marked stationary."""
    wanted = {-1, *((sensor,) if isinstance(sensor, int) else sensor)}
    found: dict[str, str] = {}
    indices = sequence.cuboid_indices()
    if not indices:
        raise DataFormatError(f"{sequence.cuboid_dir}: no cuboid files NN{sequence.cuboid_suffix}")
    for index in indices:
        for record in sequence.cuboids(index):
            label = str(record.get("label", ""))
            if ((record.get("stationary") is True or not stationary_only) and is_vehicle_class(label)
                    and int(record.get("cuboids.sensor_id", -1)) in wanted):
                found.setdefault(str(record.get("uuid")), label)
    return found


def stationary_vehicles(sequence: PandaSetSequence, sensor: int | Sequence[int] = PANDAR64) -> dict[str, str]:
    """uuid -> PandaSet class of every track marked stationary with a vehicle class (cuboid sensor id -1 or
    one of `sensor`)."""
    return vehicle_tracks(sequence, sensor, stationary_only=True)


def input_preprocessing(prep: Preprocessing, input_margin: float | None) -> Preprocessing:
    """The contract `prep` with the inputs' crop margin `input_margin`: `prep` itself for None or the contract's own
    margin (so `is prep` tells a wider crop). ValueError when it is narrower than the contract's (an input would then
    miss its reference's points) or out of the contract's bounds."""
    if input_margin is None or input_margin == prep.crop_margin:
        return prep
    inputs = replace(prep, crop_margin=float(input_margin))
    if not inputs.crop_margin >= prep.crop_margin:
        raise ValueError(f"input margin {input_margin}: narrower than the contract's {prep.crop_margin} m")
    return inputs


def wider_margin(prep: Preprocessing, input_margin: float | None) -> float | None:
    """`input_margin` when it widens the contract `prep`'s crop, else None (the contract's own); checked as
    `input_preprocessing` checks it. What the reports call a wider crop."""
    return None if input_preprocessing(prep, input_margin) is prep else input_margin


def collect_tracks(sequence: PandaSetSequence, vehicles: dict[str, str], prep: Preprocessing, *,
                   frames: Sequence[int] | None = None, sensors: Sequence[int] = (PANDAR64,),
                   noise: BoxNoise | None = None, noise_min_points: int = MIN_INPUT_POINTS,
                   input_margin: float | None = None, pool_margin: float = POOL_MARGIN) -> dict[str, VehicleTrack]:
    """In-box points of `vehicles` (uuid -> class) per frame and sensor, through the preprocessing contract
    (`prep`).

    Points and cuboids are both in the world frame, so each frame's world box takes its points into the
    box frame; the uuid links frames; a sensor uses the cuboids with sensor id -1 or its own. Frames without
    a lidar file are skipped. With `noise`, entries with >= `noise_min_points` points are cropped again with
    a noisy box (`box_noise.noisy_box`, key (track id, frame, sensor)); None where that crop is empty. Every
    entry also keeps all its points inside the exact box (no crop margin: the road beside the vehicle is not
    vehicle), the ground band below `prep.ground_clearance` included (`in_box`).
    `input_margin` (metres; default `prep.crop_margin`): the crop margin of the inputs, the exact and the noisy
    boxes' (`points`, `asides`, `noisy`); the references keep `prep`'s (`reference`) or the exact box (`in_box`). It
    can only widen the contract's (ValueError; `Preprocessing` bounds it above), so an entry's inputs hold its
    reference's points. `pool_margin` (metres): the inputs' points kept aside for the merge within it (`asides`,
    `noisy`; `preprocess.crop_vehicles`), as the pipeline's.
    """
    inputs = input_preprocessing(prep, input_margin)
    tracks = {uuid: VehicleTrack(uuid, sequence.track_ids.get(uuid, 0), label) for uuid, label in vehicles.items()}
    by_id = {t.instance_id: t for t in tracks.values()}
    eye, zero = np.eye(3), np.zeros(3)
    for index in (sequence.frame_indices() if frames is None else frames):
        records = [r for r in sequence.cuboids(index) if str(r.get("uuid")) in tracks]
        if not records:
            continue
        arrays = sequence.load_lidar(index)
        origin = sequence.pose(index)[1]
        for sensor in sensors:
            boxes = [world_box_to_sensor(r, eye, zero, sequence.track_ids.get(str(r.get("uuid")), 0))
                     for r in records if int(r.get("cuboids.sensor_id", -1)) in (-1, sensor)]
            boxes = [b for b in boxes if box_problem(b) is None]
            if not boxes:
                continue
            points = arrays["xyz"][arrays["sensor"] == sensor]
            points = points[finite_mask(points)]
            cropped = crop_vehicles(points, boxes, prep, pool_margin)[0]   # the surround is not in `normalized`
            given = cropped if inputs is prep else crop_vehicles(points, boxes, inputs, pool_margin)[0]
            entered = {v.box.instance_id: v for v in given}
            in_box = {v.box.instance_id: v.normalized for v in crop_vehicles(
                points, boxes, replace(prep, crop_margin=0.0, ground_clearance=0.0, min_points=1))[0]}
            noisy: dict[int, CroppedVehicle] = {}
            if noise is not None:
                shaken = [noisy_box(v.box, noise, (v.box.instance_id, index, sensor)) for v in cropped
                          if len(v.normalized) >= noise_min_points]
                noisy = {v.box.instance_id: v for v in crop_vehicles(points, shaken, inputs, pool_margin)[0]}
            for vehicle in cropped:
                track = by_id[vehicle.box.instance_id]
                entry = entered[vehicle.box.instance_id]   # the wider crop holds the reference's points
                track.frames.append(int(index))
                track.reference.append(vehicle.normalized)
                track.points.append(entry.normalized)
                track.asides.append(entry.aside)
                track.boxes.append(vehicle.box)
                track.sensors.append(int(sensor))
                track.origins.append(np.asarray(origin, np.float64))
                track.noisy.append(noisy.get(vehicle.box.instance_id))
                track.in_box.append(in_box.get(vehicle.box.instance_id, np.zeros((0, 3), np.float32)))
    return tracks


def in_ground_band(normalized: np.ndarray, box: Box3D, ground_clearance: float) -> np.ndarray:
    """Bool (M,): normalised points in the box's lowest `ground_clearance` metres (those the crop's ground cut drops:
    tyres, wheel arches, and the road)."""
    return ~above_ground(normalized, box, ground_clearance)


def near_a_side(normalized: np.ndarray, box: Box3D, zone: float = BAND_SIDE_ZONE) -> np.ndarray:
    """Bool (M,): normalised points within `zone` metres of the box's left or right side (|y| beyond half the
    width less `zone`); the strips under the front and rear overhangs are not."""
    return np.abs(normalized[:, 1]) * box.size[0] >= box.size[1] / 2 - zone


def outside_box(normalized: np.ndarray, box: Box3D, margin: float) -> np.ndarray:
    """Bool (M,): normalised points outside `box` grown by `margin` metres on every side."""
    half = (np.asarray(box.size, np.float64) / 2 + margin) / box.size[0]
    return (np.abs(normalized) > half).any(axis=1)


def placement_floor(reference: np.ndarray, perfect: np.ndarray, placed_by: Box3D, true_box: Box3D) -> float:
    """Coverage error x1e3 of a perfect completion placed by a box: `perfect` (points of the vehicle's own
    aggregate, normalised by `true_box`) taken as if it were normalised by `placed_by`, back in `true_box`'s
    frame, against `reference`. With a noisy `placed_by` this is what any method loses that gets the shape
    right but trusts the box's placement (not a method: it uses the reference)."""
    return float(nearest_sq(reference, reframe(perfect, placed_by, true_box)).mean()) * COVERAGE_SCALE


def multi_frame_reference(track: VehicleTrack | Any, n: int = REFERENCE_POINTS) -> np.ndarray | None:
    """The track's multi-frame aggregate (`aggregate()` of a track with `frames` and `instance_id`) sampled to
    `n` near-uniform points (seeded by the track), or None for a vehicle seen in a single frame."""
    if len(set(track.frames)) < 2:
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


def random_reference(points: np.ndarray, n: int = RANDOM_REFERENCE_POINTS, seed: int = 0) -> np.ndarray:
    """`n` points of an aggregate drawn at random without replacement (all of them when it has fewer)."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if len(points) == 0:
        raise ValueError("random_reference: empty aggregate")
    return points[np.sort(np.random.default_rng(seed).choice(len(points), min(n, len(points)), replace=False))]


@dataclass
class PandaSetItem:
    """One (vehicle, frame, sensor) observation: its size (points in the contract's crop) and, per method, the scaled
    metrics.

    coverage: random reference; coverage_voxel: voxel-uniform reference; coverage_band: random reference of every
    point inside the exact box, ground band included, and band_coverage its points in the band only (NaN where it
    has none), band_sides and band_under the band's points within `BAND_SIDE_ZONE` of a side and the others,
    band_side_share the share of the band's points near a side; fidelity_band: every point of the frame inside the
    exact box, band included, to the output; outside_crop: the share of the output's points outside the exact box
    grown by the contract's crop margin (published beside the vehicle); noisy_coverage: the box-noise run
    (random reference, clean box's frame; NaN when the noisy crop was empty); precision, judged, recall,
    f_score: the two-sided metric of `observed` (fractions); placement_floor: `placement_floor` of the exact and
    the noisy box (box-noise run only)."""

    uuid: str
    label: str
    frame: int
    sensor: int
    n_points: int
    size_bin: str
    coverage: dict[str, float]
    fidelity: dict[str, float]
    coverage_voxel: dict[str, float] = field(default_factory=dict)
    precision: dict[str, float] = field(default_factory=dict)
    judged: dict[str, float] = field(default_factory=dict)
    recall: dict[str, float] = field(default_factory=dict)
    f_score: dict[str, float] = field(default_factory=dict)
    noisy_coverage: dict[str, float] = field(default_factory=dict)
    coverage_band: dict[str, float] = field(default_factory=dict)   # reference with the ground band (random)
    band_coverage: dict[str, float] = field(default_factory=dict)   # that reference's ground-band points only
    fidelity_band: dict[str, float] = field(default_factory=dict)   # every in-box point of the frame -> output
    band_sides: dict[str, float] = field(default_factory=dict)   # the band's points near a side (`near_a_side`)
    band_under: dict[str, float] = field(default_factory=dict)   # the band's other points (under the body)
    band_side_share: float = math.nan   # share of the reference's band points near a side
    outside_crop: dict[str, float] = field(default_factory=dict)   # share of the output beside the contract's crop
    output_points: dict[str, int] = field(default_factory=dict)
    placement_floor: tuple[float, float] | None = None   # (exact box, noisy box): see `placement_floor`


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
    worst: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    sensors: tuple[int, ...] = SENSORS
    noise: BoxNoise | None = None
    random_points: int = RANDOM_REFERENCE_POINTS
    voxel_points: int = REFERENCE_POINTS
    input_margin: float | None = None   # the inputs' crop margin when wider than the contract's
    pool_margin: float | None = None    # the margin of the points kept aside for the merge, when wider than the inputs'


def reduced_observations(root: str | Path, max_frames_per_vehicle: int = 8, pool_margin: float = POOL_MARGIN
                         ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The reduced protocol's observations, for quick comparisons (`benchmarks/merge_variants.py`,
    `benchmarks/spacing_variants.py`): (normalised partial, box size, random multi-frame reference, the points kept
    aside for the merge: the ground band and the surround within `pool_margin`) of at most
    `max_frames_per_vehicle` frames x sensors of every stationary vehicle seen in more than one frame, exact boxes."""
    sequence = PandaSetSequence(root)
    tracks = collect_tracks(sequence, stationary_vehicles(sequence, SENSORS), replace(Preprocessing(), min_points=1),
                            sensors=SENSORS, pool_margin=pool_margin)
    observations = []
    for track in tracks.values():
        picks = track.input_frames(MIN_INPUT_POINTS, max_frames_per_vehicle)
        if picks and len(set(track.frames)) > 1:
            reference = random_reference(track.aggregate(), RANDOM_REFERENCE_POINTS, seed=track.instance_id)
            observations += [(track.points[k], np.array(track.boxes[k].size), reference, track.asides[k])
                             for k in picks]
    return observations


def evaluate_pandaset(model: GGDNet, root: str | Path, *, max_frames_per_vehicle: int | None = None,
                      max_vehicles: int | None = None, reference_points: int = REFERENCE_POINTS,
                      random_points: int = RANDOM_REFERENCE_POINTS, max_batch: int = 32, n_examples: int = 4,
                      frames: Sequence[int] | None = None, preprocessing: Preprocessing | None = None,
                      sensors: Sequence[int] = SENSORS, noise: BoxNoise | None = DEFAULT_BOX_NOISE,
                      input_margin: float | None = None, pool_margin: float = POOL_MARGIN) -> PandaSetResult:
    """Complete single observations (frame, sensor) of every stationary PandaSet vehicle and compare every
    method with the vehicle's multi-frame aggregate (all frames, all `sensors`).

    `preprocessing`: the model's contract (its checkpoint's; default the contract's defaults); every entry
    with at least one point goes into the aggregate, inputs need MIN_INPUT_POINTS points. By default every
    observation is evaluated; `max_frames_per_vehicle` keeps at most that many per vehicle (evenly spaced),
    `max_vehicles` the first N stationary vehicles. Vehicles seen in a single frame are left out (no
    multi-frame reference). `noise`: also run the evaluation with noisy boxes (None skips it). `input_margin`: the
    inputs' crop margin (metres; default the contract's), the references' stays the contract's (`collect_tracks`);
    `pool_margin`: the margin of the points kept aside for the merge (`preprocess.crop_vehicles`), as the pipeline's.
    """
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    sensors = tuple(sensors)
    sequence = PandaSetSequence(root)
    vehicles = stationary_vehicles(sequence, sensors)
    n_candidates = len(vehicles)
    if max_vehicles is not None:
        vehicles = dict(list(vehicles.items())[:max_vehicles])
    prep = replace(preprocessing or Preprocessing(), min_points=1)
    input_margin = wider_margin(prep, input_margin)
    tracks = collect_tracks(sequence, vehicles, prep, frames=frames, sensors=sensors, noise=noise,
                            input_margin=input_margin, pool_margin=pool_margin)
    seconds["load+crop"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    notes: list[str] = []
    meta: list[tuple[VehicleTrack, int]] = []
    refs: dict[str, tuple[np.ndarray, np.ndarray, RangeImages]] = {}
    band_refs: dict[str, np.ndarray] = {}
    perfect: dict[str, np.ndarray] = {}
    single_frame = 0
    for track in tracks.values():
        picks = track.input_frames(MIN_INPUT_POINTS, max_frames_per_vehicle)
        if not picks:
            continue
        voxel = multi_frame_reference(track, reference_points)
        if voxel is None:
            single_frame += 1
            continue
        aggregate = track.aggregate()
        refs[track.uuid] = (random_reference(aggregate, random_points, seed=track.instance_id), voxel,
                            range_images(track.pose_scans()))
        in_box = track.aggregate_in_box()   # empty only when every point lies in the crop margin: NaN below
        band_refs[track.uuid] = random_reference(in_box, random_points, seed=track.instance_id) if len(in_box) \
            else np.zeros((0, 3), np.float32)
        if noise is not None:   # a perfect completion: the aggregate itself (another random sample of it)
            perfect[track.uuid] = random_reference(aggregate, model.config.num_output, seed=track.instance_id + 1)
        meta += [(track, k) for k in picks]
    if single_frame:
        notes.append(f"{single_frame} vehicles seen in a single frame only were left out (no multi-frame reference)")
    seconds["references"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    partials = [t.points[k] for t, k in meta]
    sizes = np.array([t.boxes[k].size for t, k in meta], np.float64).reshape(-1, 3)
    clean = published_outputs(model, partials, sizes, max_batch=max_batch, asides=[t.asides[k] for t, k in meta])
    noisy_meta = [i for i, (t, k) in enumerate(meta) if noise is not None and t.noisy[k] is not None]
    noisy_in = [crop for i in noisy_meta if (crop := meta[i][0].noisy[meta[i][1]]) is not None]
    noisy = published_outputs(model, [v.normalized for v in noisy_in],
                              np.array([v.box.size for v in noisy_in], np.float64).reshape(-1, 3), max_batch=max_batch,
                              asides=[v.aside for v in noisy_in])
    noisy_nets = {i: (noisy.generated[j], noisy.raw[j], noisy.completion[j], noisy.published[j])
                  for j, i in enumerate(noisy_meta)}
    seconds["network"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    items: list[PandaSetItem] = []
    n_out = model.config.num_output
    for i, (track, k) in enumerate(meta):
        partial, box = track.points[k], track.boxes[k]
        ref_random, ref_voxel, images = refs[track.uuid]
        outputs = _method_outputs(partial, track.asides[k], box.size, n_out, clean.generated[i], clean.raw[i],
                                   clean.completion[i], clean.published[i])
        seen = len(track.reference[k])   # the bucket: the contract's count, whatever the input margin
        item = PandaSetItem(track.uuid, track.label, track.frames[k], track.sensors[k], seen, size_bin(seen), {}, {})
        low = in_ground_band(band_refs[track.uuid], box, prep.ground_clearance)   # the same for every method
        sides = low & near_a_side(band_refs[track.uuid], box)
        under = low & ~sides
        item.band_side_share = float(sides.sum() / low.sum()) if low.any() else math.nan
        for name in BASELINE_NAMES:
            out = outputs[name]
            to_out = nearest_sq(ref_random, out)
            item.coverage[name] = float(to_out.mean()) * COVERAGE_SCALE
            item.coverage_voxel[name] = float(nearest_sq(ref_voxel, out).mean()) * COVERAGE_SCALE
            item.fidelity[name] = float(nearest_sq(track.reference[k], out).mean()) * FIDELITY_SCALE
            two = two_sided(out, ref_random, images, TAU, to_out)
            item.precision[name], item.judged[name] = two.precision, two.judged_share
            item.recall[name], item.f_score[name] = two.recall, two.f_score
            item.output_points[name] = len(out)
            item.outside_crop[name] = float(outside_box(out, box, prep.crop_margin).mean())
            to_band = nearest_sq(band_refs[track.uuid], out)
            item.coverage_band[name] = float(to_band.mean()) * COVERAGE_SCALE if len(to_band) else math.nan
            for zone, values in ((low, item.band_coverage), (sides, item.band_sides), (under, item.band_under)):
                values[name] = float(to_band[zone].mean()) * COVERAGE_SCALE if zone.any() else math.nan
            item.fidelity_band[name] = (float(nearest_sq(track.in_box[k], out).mean()) * FIDELITY_SCALE
                                        if len(track.in_box[k]) else math.nan)
        if i in noisy_nets:
            crop = track.noisy[k]
            assert crop is not None   # k is in noisy_nets
            shaken = crop.box
            shaken_outputs = _method_outputs(crop.normalized, crop.aside, shaken.size, n_out, *noisy_nets[i])
            stacked = reframe(np.concatenate([shaken_outputs[n] for n in BASELINE_NAMES]), shaken, box)
            bounds = np.cumsum(np.array([0] + [len(shaken_outputs[n]) for n in BASELINE_NAMES]))
            for j, name in enumerate(BASELINE_NAMES):
                out = stacked[bounds[j]:bounds[j + 1]]
                item.noisy_coverage[name] = float(nearest_sq(ref_random, out).mean()) * COVERAGE_SCALE
            item.placement_floor = (placement_floor(ref_random, perfect[track.uuid], box, box),
                                    placement_floor(ref_random, perfect[track.uuid], shaken, box))
        items.append(item)
    seconds["metrics"] = time.perf_counter() - t3
    if noise is not None and len(noisy_meta) < len(meta):
        notes.append(f"box noise: {len(meta) - len(noisy_meta)} observations had no point in the noisy box and are "
                     "left out of the box-noise table (their clean figures too)")
    examples = _examples(items, meta, clean.published, refs, n_examples)
    worst = _worst(items, meta, clean.published, refs, n_examples)
    return PandaSetResult(items, len(refs), n_candidates, max_frames_per_vehicle, seconds, examples, notes, worst,
                          sensors, noise, random_points, reference_points, input_margin,
                          pool_margin if pool_margin > input_preprocessing(prep, input_margin).crop_margin else None)


def _method_outputs(partial: np.ndarray, aside: np.ndarray, size: Sequence[float], n_out: int, generation: np.ndarray,
                    raw: np.ndarray, completion: np.ndarray, merged: np.ndarray) -> dict[str, np.ndarray]:
    """Every method's output (`BASELINE_NAMES`) for one normalised partial, the points its crop kept aside `aside`
    (`preprocess.CroppedVehicle.aside`: measured points the network is not fed, pooled by the merge; the input and
    the box priors get them too) and its box `size`, given the network's generation-only, raw, evenly spaced and
    merged outputs."""
    measured = with_aside(partial, aside)
    return {"input": measured, "mirror": mirror_symmetry(measured),
            **prior_outputs(measured, np.asarray(size), n_out),
            "generation": generation, "ggd_raw": raw, "ggd": completion, "ggd_merge": merged}


def _render_item(item: PandaSetItem, partial: np.ndarray, completion: np.ndarray, reference: np.ndarray,
                 extra: str = "") -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    title = (f"{item.label[:18]} {item.uuid[:6]} f{item.frame:02d} {SENSOR_NAMES.get(item.sensor, item.sensor)}"
             + extra)
    return title, partial, completion, reference


def _examples(items: list[PandaSetItem], meta: list[tuple[VehicleTrack, int]], completion: np.ndarray,
              refs: dict[str, tuple[np.ndarray, np.ndarray, RangeImages]], n: int
              ) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """Up to `n` render items (title, input, published completion, voxel reference): each size bin in turn,
    one observation per vehicle, the vehicles with the largest aggregates first."""
    order = sorted(range(len(items)), key=lambda i: -sum(len(p) for p in meta[i][0].reference))
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
    return [_render_item(items[i], meta[i][0].points[meta[i][1]], completion[i], refs[items[i].uuid][1])
            for i in chosen]


def _worst(items: list[PandaSetItem], meta: list[tuple[VehicleTrack, int]], completion: np.ndarray,
           refs: dict[str, tuple[np.ndarray, np.ndarray, RangeImages]], n: int
           ) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """The `n` observations with the highest coverage error of the published completion (random reference), one
    per vehicle."""
    chosen: list[int] = []
    seen: set[str] = set()
    for i in sorted(range(len(items)), key=lambda i: -items[i].coverage["ggd_merge"]):
        if items[i].uuid not in seen and len(chosen) < n:
            chosen.append(i)
            seen.add(items[i].uuid)
    return [_render_item(items[i], meta[i][0].points[meta[i][1]], completion[i], refs[items[i].uuid][1],
                         f" cov {items[i].coverage['ggd_merge']:.2f}") for i in chosen]
