"""Detector-like box noise for the robustness evaluation: Gaussian errors of centre, size and yaw, seeded."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from gd_completion.errors import EvaluationError
from gd_completion.geometry import Box3D, denormalize, normalize

BOX_NOISE_SEED = 2024


@dataclass(frozen=True)
class BoxNoise:
    """Standard deviations: centre x/y and z (metres), relative size (each of length, width, height), yaw (deg)."""

    centre_xy: float = 0.15
    centre_z: float = 0.05
    size: float = 0.05
    yaw_deg: float = 4.0
    seed: int = BOX_NOISE_SEED

    def __post_init__(self) -> None:
        for name in ("centre_xy", "centre_z", "size", "yaw_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise EvaluationError(f"box noise: {name} = {value} must be a finite standard deviation >= 0")

    def describe(self) -> str:
        return (f"sigma {self.centre_xy} m centre x/y, {self.centre_z} m centre z, {100 * self.size:g} % "
                f"size (each dimension), {self.yaw_deg} deg yaw; seed {self.seed}")


def noisy_box(box: Box3D, noise: BoxNoise, key: tuple[int, ...]) -> Box3D:
    """`box` with noise drawn from default_rng((noise.seed, *key)): the same key gives the same box whatever
    else is evaluated (e.g. key = (track id, frame, sensor)). Sizes stay positive (factor >= 0.5)."""
    rng = np.random.default_rng((noise.seed, *(int(k) for k in key)))
    d = rng.standard_normal(7)
    centre = np.asarray(box.center, np.float64) + d[:3] * np.array([noise.centre_xy, noise.centre_xy, noise.centre_z])
    size = np.asarray(box.size, np.float64) * np.maximum(1.0 + noise.size * d[3:6], 0.5)
    yaw = (box.yaw + math.radians(noise.yaw_deg) * d[6] + math.pi) % (2 * math.pi) - math.pi
    return replace(box, center=tuple(float(c) for c in centre), size=tuple(float(s) for s in size), yaw=float(yaw))


def reframe(points: np.ndarray, source: Box3D, target: Box3D) -> np.ndarray:
    """Points normalised in `source`'s frame -> normalised in `target`'s frame (through the shared frame)."""
    return normalize(denormalize(np.asarray(points, np.float32).reshape(-1, 3), source), target).astype(np.float32)
