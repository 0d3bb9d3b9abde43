"""Training samples from a labelled real drive (PandaSet layout): its moving vehicles cropped with the annotated and
with detector-like boxes.

- `drive_frames`: box-refiner samples, each crop with the true box in the frame of the box it was cropped with.
- `drive_pairs`: completion samples, each crop with the vehicle's multi-frame aggregate (every frame and sensor of
  its track, each in its own annotated box frame) in the frame of the box it was cropped with: a partial reference,
  what the sensors saw of that vehicle over the drive.

The synthetic pairs teach on simulated scans; a labelled drive of a real sensor shows real vehicles (glass, mirrors,
rounded bodies, the annotators' box conventions). Only vehicles never marked stationary are used, because the
PandaSet evaluation (`evaluation.pandaset_eval`) scores the parked ones: a network adapted on a drive is still scored
on vehicles it never saw (of the same drive and sensors).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Self

import numpy as np

from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.errors import DataFormatError
from gd_completion.evaluation.box_noise import BoxNoise, reframe
from gd_completion.evaluation.pandaset_eval import (
    MIN_INPUT_POINTS,
    SENSORS,
    VehicleTrack,
    collect_tracks,
    in_ground_band,
    near_a_side,
    random_reference,
    stationary_vehicles,
    vehicle_tracks,
)
from gd_completion.geometry import Box3D, normalize
from gd_completion.preprocess import Preprocessing, network_input

log = logging.getLogger(__name__)

DRIVE_REFERENCE_POINTS = 4096   # points of a drive pair's reference (twice N_o, as the synthetic targets' gt_points)


@dataclass(frozen=True)
class DriveSettings:
    """A labelled drive for training (a recipe's `drive`, refiner or completion network): the folder (PandaSet
    layout), noisy crops per annotated crop, the scale of the evaluation's box-noise sigmas from the first draw to the
    last, the first draw's seed (draw k: seed + k), the share of its vehicles held out for validation and (completion
    pairs) whether the reference keeps the ground band."""

    pandaset: str
    draws: int = 4
    sigma_scale: tuple[float, float] = (0.8, 1.4)
    seed: int = 7001
    val_share: float = 0.2
    ground_band: bool = False   # `drive_pairs`: the reference keeps the ground band's tyres and sills (`band_sides`)

    def __post_init__(self) -> None:
        if not isinstance(self.pandaset, str) or not (Path(self.pandaset) / "lidar").is_dir():
            raise ValueError(f"pandaset={self.pandaset!r} must name a drive folder holding lidar/")
        if isinstance(self.draws, bool) or not isinstance(self.draws, int) or self.draws < 0:
            raise ValueError(f"draws={self.draws!r} must be an integer >= 0")
        scale = self.sigma_scale
        if (not isinstance(scale, (list, tuple)) or len(scale) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in scale)
                or not 0.0 <= scale[0] <= scale[1]):
            raise ValueError(f"sigma_scale={scale!r} must be two finite factors 0 <= low <= high")
        object.__setattr__(self, "sigma_scale", (float(scale[0]), float(scale[1])))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ValueError(f"seed={self.seed!r} must be an integer")
        if (isinstance(self.val_share, bool) or not isinstance(self.val_share, (int, float))
                or not 0.0 < self.val_share < 1.0):
            raise ValueError(f"val_share={self.val_share!r} must be in (0, 1)")
        if not isinstance(self.ground_band, bool):
            raise ValueError(f"ground_band={self.ground_band!r} must be true or false")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DriveSettings:
        """From a recipe's `drive` object; ValueError naming unknown or missing keys and bad values."""
        if not isinstance(values, dict):
            raise ValueError("drive must be an object")
        unknown = sorted(set(values) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(f"unknown drive keys {unknown}")
        if "pandaset" not in values:
            raise ValueError("drive needs pandaset (a labelled drive folder)")
        return cls(**values)


class _TrackSamples:
    """Samples of a drive's vehicles (a frozen dataclass of (S, ...) arrays, one of them `track`): their count, a
    subset, and a split that holds whole vehicles out."""

    track: np.ndarray

    def __len__(self) -> int:
        return len(self.track)

    def subset(self, keep: np.ndarray) -> Self:
        """The samples where the boolean mask `keep` is true."""
        return type(self)(*(getattr(self, f.name)[keep] for f in fields(self)))  # type: ignore[arg-type]

    def split(self, val_share: float, seed: int = 0) -> tuple[Self, Self]:
        """(training, validation) with whole vehicles held out: `val_share` of the tracks (at least one) drawn with
        `seed` validate (`held_out`)."""
        validate = held_out(self.track, val_share, seed)
        return self.subset(~validate), self.subset(validate)


@dataclass(frozen=True)
class DriveFrames(_TrackSamples):
    """Refiner samples: network inputs normalised by the box used, that box's size, the true box in its frame."""

    partial: np.ndarray   # (S, n_input, 3) float32
    size: np.ndarray      # (S, 3) float32: length, width, height of the box used
    target: np.ndarray    # (S, 7) float32: `box_refiner.BoxFrame` vector of the true box in the used box's frame
    track: np.ndarray     # (S,) int64: the vehicle's track id


@dataclass(frozen=True)
class DrivePairs(_TrackSamples):
    """Completion samples: network inputs normalised by the box used, that box's size, and the vehicle's multi-frame
    aggregate in the same frame."""

    partial: np.ndarray     # (S, n_input, 3) float32
    size: np.ndarray        # (S, 3) float32: length, width, height of the box used
    reference: np.ndarray   # (S, R, 3) float32: the track's aggregate in the used box's frame
    track: np.ndarray       # (S,) int64: the vehicle's track id


def held_out(track: np.ndarray, val_share: float, seed: int) -> np.ndarray:
    """Mask of the samples of `val_share` of the tracks (at least one, never all) drawn with `seed`."""
    if not 0.0 < val_share < 1.0:
        raise ValueError(f"val_share={val_share} must be in (0, 1)")
    tracks = np.unique(track)
    if len(tracks) < 2:
        raise DataFormatError(f"a drive's samples hold {len(tracks)} vehicle(s): too few to split")
    count = min(len(tracks) - 1, max(1, round(val_share * len(tracks))))
    return np.isin(track, np.random.default_rng(seed).choice(tracks, size=count, replace=False))


def true_frame(true: Box3D, used: Box3D) -> np.ndarray:
    """(7,) float32 `BoxFrame` vector of the `true` box in the normalised frame of the box `used` (as
    `box_refiner.frame_targets` for synthetic pairs): its centre, heading offset and log size factors."""
    offset = normalize(np.array([true.center], np.float64), used)[0]
    yaw = (true.yaw - used.yaw + math.pi) % (2.0 * math.pi) - math.pi
    scale = np.log(np.asarray(true.size, np.float64) / np.asarray(used.size, np.float64))
    return np.concatenate([offset, [yaw], scale]).astype(np.float32)


def moving_vehicles(sequence: PandaSetSequence, sensors: Sequence[int] = SENSORS) -> dict[str, str]:
    """uuid -> class of every vehicle track of the drive that is never marked stationary (cuboid sensor id -1 or
    one of `sensors`)."""
    parked = stationary_vehicles(sequence, sensors)
    return {uuid: label for uuid, label in vehicle_tracks(sequence, sensors).items() if uuid not in parked}


def drive_frames(drive: DriveSettings, *, n_input: int = 512, preprocessing: Preprocessing | None = None,
                 sensors: Sequence[int] = SENSORS, noise: BoxNoise | None = None,
                 frames: Iterable[int] | None = None) -> DriveFrames:
    """Refiner samples of the `drive`'s moving vehicles, every frame (or `frames`) and sensor: each crop with at least
    MIN_INPUT_POINTS points once with its annotated box (target: the identity) and `drive.draws` times with a noisy
    box (`evaluation.box_noise.noisy_box`, the sigmas of `noise` (default the evaluation's) scaled from
    `drive.sigma_scale[0]` to `[1]` over the draws, draw k seeded `drive.seed + k`), cropped through `preprocessing`
    (the contract of the checkpoint whose refiner trains) and brought to `n_input` points."""
    sequence, vehicles, prep = _moving(drive, preprocessing, sensors)
    frames = None if frames is None else list(frames)
    parts: list[tuple[np.ndarray, tuple[float, ...], np.ndarray, int]] = []
    for k, shaken in enumerate(_draws(drive, noise)):
        for track in collect_tracks(sequence, vehicles, prep, frames=frames, sensors=sensors, noise=shaken).values():
            if k == 0:
                parts += [(network_input(points, n_input), box.size, np.zeros(7, np.float32), track.instance_id)
                          for points, box in zip(track.points, track.boxes) if len(points) >= MIN_INPUT_POINTS]
            parts += [(network_input(crop.normalized, n_input), crop.box.size, true_frame(box, crop.box),
                       track.instance_id)
                      for crop, box in zip(track.noisy, track.boxes)
                      if crop is not None and len(crop.normalized) >= MIN_INPUT_POINTS]
    if not parts:
        raise DataFormatError(f"{drive.pandaset}: no moving vehicle with {MIN_INPUT_POINTS} points in its box")
    partial, size, target, track_id = zip(*parts)
    return DriveFrames(np.stack(partial).astype(np.float32), np.array(size, np.float32), np.stack(target),
                       np.array(track_id, np.int64))


def drive_pairs(drive: DriveSettings, *, n_input: int = 512, reference_points: int = DRIVE_REFERENCE_POINTS,
                preprocessing: Preprocessing | None = None, sensors: Sequence[int] = SENSORS,
                noise: BoxNoise | None = None, frames: Iterable[int] | None = None) -> DrivePairs:
    """Completion samples of the `drive`'s moving vehicles seen in at least two frames (of `frames`, default every
    frame; every sensor): each crop as `drive_frames` makes them (annotated box, then `drive.draws` noisy boxes),
    with `reference_points` points drawn at random (seeded by the track; repeated when the aggregate has fewer) from
    the track's aggregate: the contract's crops of every entry (`VehicleTrack.aggregate`) or, with
    `drive.ground_band`, the points inside the exact boxes but the road under the body (`band_sides`), taken from the
    annotated box's frame into the frame of the box used (`box_noise.reframe`). A vehicle whose aggregate holds no point
    is skipped, and the skips counted in a warning."""
    if isinstance(reference_points, bool) or not isinstance(reference_points, int) or reference_points < 1:
        raise ValueError(f"reference_points={reference_points!r} must be an integer >= 1")
    sequence, vehicles, prep = _moving(drive, preprocessing, sensors)
    frames = None if frames is None else list(frames)
    parts: list[tuple[np.ndarray, tuple[float, ...], np.ndarray, int]] = []
    references: dict[int, np.ndarray | None] = {}   # the same in every pass: the annotated boxes' aggregate
    for k, shaken in enumerate(_draws(drive, noise)):
        tracks = collect_tracks(sequence, vehicles, prep, frames=frames, sensors=sensors, noise=shaken, pool_margin=0.0)
        for track in tracks.values():
            if len(set(track.frames)) < 2:
                continue
            if track.instance_id not in references:
                references[track.instance_id] = pair_reference(track, drive.ground_band, prep.ground_clearance,
                                                               reference_points)
            reference = references[track.instance_id]
            if reference is None:
                continue
            if k == 0:
                parts += [(network_input(points, n_input), box.size, reference, track.instance_id)
                          for points, box in zip(track.points, track.boxes) if len(points) >= MIN_INPUT_POINTS]
            parts += [(network_input(crop.normalized, n_input), crop.box.size, reframe(reference, box, crop.box),
                       track.instance_id)
                      for crop, box in zip(track.noisy, track.boxes)
                      if crop is not None and len(crop.normalized) >= MIN_INPUT_POINTS]
    empty = sum(r is None for r in references.values())
    if empty:
        log.warning("%s: %d moving vehicle(s) skipped, no point of theirs in the reference", drive.pandaset, empty)
    if not parts:
        raise DataFormatError(f"{drive.pandaset}: no moving vehicle seen in two frames with {MIN_INPUT_POINTS} points "
                              "in its box")
    partial, size, reference, track_id = zip(*parts)
    return DrivePairs(np.stack(partial).astype(np.float32), np.array(size, np.float32),
                      np.stack(reference).astype(np.float32), np.array(track_id, np.int64))


def pair_reference(track: VehicleTrack, ground_band: bool, ground_clearance: float, count: int
                   ) -> np.ndarray | None:
    """A drive pair's reference of `track` (`track_reference` of its aggregate, or with `ground_band` of
    `band_sides`), or None when that aggregate holds no point."""
    aggregate = band_sides(track, ground_clearance) if ground_band else track.aggregate()
    return track_reference(aggregate, count, track.instance_id) if len(aggregate) else None


def band_sides(track: VehicleTrack, ground_clearance: float) -> np.ndarray:
    """The track's points inside its exact boxes (`VehicleTrack.in_box`) but those of the ground band (the lowest
    `ground_clearance` metres) farther than `BAND_SIDE_ZONE` from the box's left and right sides: the band's tyres,
    wheel arches and sills are vehicle, the road seen under the body is not."""
    kept = [points[~in_ground_band(points, box, ground_clearance) | near_a_side(points, box)]
            for points, box in zip(track.in_box, track.boxes)]
    return np.concatenate(kept).astype(np.float32, copy=False) if kept else np.zeros((0, 3), np.float32)


def track_reference(aggregate: np.ndarray, count: int, seed: int) -> np.ndarray:
    """`count` points of a track's `aggregate` drawn at random with `seed`: each once while it has enough, then
    random repeats."""
    reference = random_reference(aggregate, count, seed=seed)
    if len(reference) < count:
        extra = np.random.default_rng(seed).choice(len(reference), count - len(reference))
        reference = np.concatenate([reference, reference[extra]])
    return reference


def _moving(drive: DriveSettings, preprocessing: Preprocessing | None, sensors: Sequence[int]
            ) -> tuple[PandaSetSequence, dict[str, str], Preprocessing]:
    """The drive, its moving vehicles as `sensors` mark them (DataFormatError without any) and the contract with
    every crop kept."""
    sequence = PandaSetSequence(drive.pandaset)
    vehicles = moving_vehicles(sequence, sensors)
    if not vehicles:
        raise DataFormatError(f"{drive.pandaset}: no moving vehicle tracks")
    return sequence, vehicles, replace(preprocessing or Preprocessing(), min_points=1)


def _draws(drive: DriveSettings, noise: BoxNoise | None) -> list[BoxNoise | None]:
    """The box noise of each pass: None (the annotated boxes only) without draws, else `drive.draws` noises, the
    sigmas of `noise` (default the evaluation's) scaled from `drive.sigma_scale[0]` to `[1]`, draw k seeded
    `drive.seed + k` (the first pass also takes the annotated boxes)."""
    base = noise or BoxNoise()
    factors = np.linspace(*drive.sigma_scale, drive.draws)
    return [replace(base, centre_xy=base.centre_xy * f, centre_z=base.centre_z * f, size=base.size * f,
                    yaw_deg=base.yaw_deg * f, seed=drive.seed + k) for k, f in enumerate(factors)] or [None]
