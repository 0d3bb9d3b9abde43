"""Box-refiner samples from a labelled real drive (PandaSet layout): its moving vehicles cropped with detector-like
box errors, each with the true box in the frame of the box it was cropped with.

The synthetic pairs teach the box refiner (`model.box_refiner`) on simulated scans; a labelled drive of a real
sensor shows it real vehicles (glass, mirrors, rounded bodies, the annotators' box conventions). Only vehicles never
marked stationary are used, because the PandaSet evaluation (`evaluation.pandaset_eval`) scores the parked ones: a
refiner adapted on a drive is still scored on vehicles it never saw (of the same drive and sensors).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.errors import DataFormatError
from gd_completion.evaluation.box_noise import BoxNoise
from gd_completion.evaluation.pandaset_eval import (
    MIN_INPUT_POINTS,
    SENSORS,
    collect_tracks,
    stationary_vehicles,
    vehicle_tracks,
)
from gd_completion.geometry import Box3D, normalize
from gd_completion.preprocess import Preprocessing, network_input


@dataclass(frozen=True)
class DriveSettings:
    """A labelled drive for refiner training (a refiner recipe's `drive`): the folder (PandaSet layout), noisy crops
    per annotated crop, the scale of the evaluation's box-noise sigmas from the first draw to the last, the first
    draw's seed (draw k: seed + k) and the share of its vehicles held out for validation."""

    pandaset: str
    draws: int = 4
    sigma_scale: tuple[float, float] = (0.8, 1.4)
    seed: int = 7001
    val_share: float = 0.2

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


@dataclass(frozen=True)
class DriveFrames:
    """Refiner samples: network inputs normalised by the box used, that box's size, the true box in its frame."""

    partial: np.ndarray   # (S, n_input, 3) float32
    size: np.ndarray      # (S, 3) float32: length, width, height of the box used
    target: np.ndarray    # (S, 7) float32: `box_refiner.BoxFrame` vector of the true box in the used box's frame
    track: np.ndarray     # (S,) int64: the vehicle's track id

    def __len__(self) -> int:
        return len(self.track)

    def subset(self, keep: np.ndarray) -> DriveFrames:
        """The samples where the boolean mask `keep` is true."""
        return DriveFrames(self.partial[keep], self.size[keep], self.target[keep], self.track[keep])

    def split(self, val_share: float, seed: int = 0) -> tuple[DriveFrames, DriveFrames]:
        """(training, validation) with whole vehicles held out: `val_share` of the tracks (at least one) drawn with
        `seed` validate."""
        if not 0.0 < val_share < 1.0:
            raise ValueError(f"val_share={val_share} must be in (0, 1)")
        tracks = np.unique(self.track)
        if len(tracks) < 2:
            raise DataFormatError(f"a drive's refiner samples hold {len(tracks)} vehicle(s): too few to split")
        count = min(len(tracks) - 1, max(1, round(val_share * len(tracks))))
        held = np.random.default_rng(seed).choice(tracks, size=count, replace=False)
        validate = np.isin(self.track, held)
        return self.subset(~validate), self.subset(validate)


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
    base = noise or BoxNoise()
    sequence = PandaSetSequence(drive.pandaset)
    vehicles = moving_vehicles(sequence, sensors)
    frames = None if frames is None else list(frames)
    if not vehicles:
        raise DataFormatError(f"{drive.pandaset}: no moving vehicle tracks")
    prep = replace(preprocessing or Preprocessing(), min_points=1)
    parts: list[tuple[np.ndarray, tuple[float, ...], np.ndarray, int]] = []
    factors = list(np.linspace(*drive.sigma_scale, drive.draws))   # one draw: the low factor; none: []
    for k, factor in enumerate(factors or [None]):   # no draw: one pass for the annotated boxes
        shaken = None if factor is None else replace(
            base, centre_xy=base.centre_xy * factor, centre_z=base.centre_z * factor, size=base.size * factor,
            yaw_deg=base.yaw_deg * factor, seed=drive.seed + k)
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
