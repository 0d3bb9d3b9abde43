"""Two-sided real-data metric: precision of output points where the reference observed the vehicle, F-score@tau.

"Observed" (normalised box frame, vehicle length = 1). The multi-frame aggregate is the union of per-frame
scans of the vehicle, each taken from a known sensor pose. For at most MAX_POSES of the frames in which the
Pandar64 saw the vehicle (evenly spaced; frames with >= 50 in-box points when there are any; poses.json holds
that lidar's pose, the PandarGT has none of its own) the sensor position is moved into the box frame and that
frame's in-box points are binned in a spherical range image around it (ANGLE_BIN_DEG bins in azimuth and
elevation), keeping per bin the *largest* measured range r: along that bin the sensor saw free space up to
r (and a surface at r). An output point p is *judged* when, for at least one pose s, the bin in p's
direction holds a return with r >= |p - s| - tau: the sensor looked at p's location or through it (p is on
a seen surface or in free space in front of one). Points never judged (behind every seen surface,
underneath, or in directions with no in-box return from any pose, e.g. above the roof) are left out.
The largest range per bin (not the smallest) keeps grazing surfaces (a roof seen from 2 m height) judged:
within one 0.4 deg bin their returns spread in range by more than tau. Each pose's image holds only its
own frame's points, so surfaces that only other poses saw never count as seen from this one.
Precision = judged points within tau of the reference / judged points; recall = reference points within tau
of the output; F-score = 2PR / (P + R). tau = TAU = 0.02 (2 % of the vehicle length).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .nearest import nearest_sq

TAU = 0.02
ANGLE_BIN_DEG = 0.4
MAX_POSES = 16
# The report's definition: the docstring's, with the constants' values.
OBSERVED_DEFINITION = " ".join(__doc__.split("\n\n", 1)[1].split()).replace(
    "MAX_POSES", str(MAX_POSES)).replace("ANGLE_BIN_DEG bins", f"{ANGLE_BIN_DEG} deg bins").replace(
    "tau = TAU = 0.02", f"tau = {TAU}")


@dataclass(frozen=True)
class RangeImages:
    """Per pose, the largest measured range per (elevation, azimuth) bin (-inf: no return)."""

    sensors: np.ndarray   # (P, 3) sensor positions, normalised box frame
    ranges: np.ndarray    # (P, n_el * n_az) float32
    bin_deg: float


def _bins(points: np.ndarray, sensors: np.ndarray, bin_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(bin index (P, N), range (P, N)) of `points` (N, 3) seen from each sensor (P, 3)."""
    v = points[None, :, :].astype(np.float64) - sensors[:, None, :].astype(np.float64)
    r = np.linalg.norm(v, axis=-1)
    step = np.radians(bin_deg)
    n_az = int(round(2 * np.pi / step))
    az = np.floor((np.arctan2(v[..., 1], v[..., 0]) + np.pi) / step).astype(np.int64) % n_az
    el = np.floor((np.arcsin(np.clip(v[..., 2] / np.maximum(r, 1e-12), -1, 1)) + np.pi / 2) / step).astype(np.int64)
    return el * n_az + az, r


def range_images(scans: Sequence[tuple[np.ndarray, np.ndarray]], bin_deg: float = ANGLE_BIN_DEG) -> RangeImages:
    """Range images of (sensor position (3,), that pose's points (M, 3)) scans, all in the normalised box frame."""
    n_el, n_az = int(round(180.0 / bin_deg)) + 1, int(round(360.0 / bin_deg))
    sensors = np.array([np.asarray(s, np.float64).reshape(3) for s, _ in scans]).reshape(-1, 3)
    images = np.full((len(scans), n_el * n_az), -np.inf, np.float32)
    for k, (_, points) in enumerate(scans):
        idx, r = _bins(np.asarray(points, np.float32).reshape(-1, 3), sensors[k:k + 1], bin_deg)
        np.maximum.at(images[k], idx[0], r[0].astype(np.float32))
    return RangeImages(sensors, images, bin_deg)


def judged(points: np.ndarray, images: RangeImages, tau: float = TAU) -> np.ndarray:
    """Bool (N,): points some pose looked at or through (see the module docstring)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    if len(images.sensors) == 0 or len(points) == 0:
        return np.zeros(len(points), bool)
    idx, r = _bins(points, images.sensors, images.bin_deg)
    return np.any(np.take_along_axis(images.ranges, idx, axis=1) >= r - tau, axis=0)


@dataclass(frozen=True)
class TwoSided:
    """Precision (judged points only), the judged share of the output, recall and F-score at tau."""

    precision: float
    judged_share: float
    recall: float
    f_score: float


def two_sided(output: np.ndarray, reference: np.ndarray, images: RangeImages, tau: float = TAU,
              reference_to_output: np.ndarray | None = None) -> TwoSided:
    """Precision, judged share, recall and F-score@tau of one output against its reference.

    `reference_to_output`: squared reference -> output distances when already computed (coverage)."""
    output = np.asarray(output, np.float32).reshape(-1, 3)
    seen = judged(output, images, tau)
    close = nearest_sq(output[seen], reference) <= tau * tau
    precision = float(close.mean()) if len(close) else float("nan")
    if reference_to_output is None:
        reference_to_output = nearest_sq(reference, output)
    recall = float(np.mean(reference_to_output <= tau * tau))
    total = precision + recall
    f = 2 * precision * recall / total if total > 0 else (float("nan") if np.isnan(precision) else 0.0)
    return TwoSided(precision, float(seen.mean()) if len(seen) else float("nan"), recall, f)


def pose_subset(count: int, max_poses: int = MAX_POSES) -> np.ndarray:
    """Indices of at most `max_poses` of `count` poses, evenly spaced (all when fewer)."""
    if count <= max_poses:
        return np.arange(count)
    return np.unique(np.round(np.linspace(0, count - 1, max_poses)).astype(int))
