"""Rigid alignment in the ground plane (x, y, yaw) of one frame's points to a track's fused points.

Track fusion stores each frame's points in the frame of that frame's box; a tracker's or annotator's box
jitters by a few centimetres and a fraction of a degree from frame to frame, which blurs the fused cloud
by as much. `align_planar` removes that jitter: a trimmed point-to-point ICP (nearest target point within
`max_distance` in 3D, closed-form planar rigid fit per iteration) over a uniform grid of cell size
`max_distance`, on at most `max_source_points` / `max_target_points` evenly strided points, for at most
`iterations` iterations: bounded cost whatever the track's size. A fit with fewer than `min_pairs`
correspondences or fewer than `min_overlap` of the frame's points matched (a frame that shows a new side
touches the old ones only along an edge, which would drag it), or one that moves the frame by more than
`max_shift` / `max_yaw_deg` (not jitter: a wrong match), is refused (None), and the frame is kept as its
box placed it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gd_completion.limits import check_positive_fields
from gd_completion.sampling import evenly_strided

__all__ = ["AlignSettings", "PlanarTransform", "align_planar"]



@dataclass(frozen=True)
class AlignSettings:
    """Bounds of `align_planar` (metres in the box frame; every value positive)."""

    max_distance: float = 0.2      # a source point farther than this from every target point is not matched
    iterations: int = 20           # ICP iterations at most (it stops earlier once converged)
    min_pairs: int = 30            # fewer matched points than this: no alignment
    min_overlap: float = 0.5       # a smaller share of the frame's (strided) points matched: no alignment
    max_shift: float = 0.3         # a fit shifting the frame by more than this is refused
    max_yaw_deg: float = 5.0       # a fit turning the frame by more than this is refused
    max_source_points: int = 512   # the new frame's points used for the fit at most (evenly strided)
    max_target_points: int = 2048  # the track's points used for the fit at most (evenly strided)

    def __post_init__(self) -> None:
        check_positive_fields(self)
        if self.min_overlap > 1:
            raise ValueError(f"AlignSettings.min_overlap={self.min_overlap!r} must be at most 1")


@dataclass(frozen=True)
class PlanarTransform:
    """p -> R(yaw) p + (tx, ty, 0): a rotation about the z axis, then a shift in x and y."""

    yaw: float
    tx: float
    ty: float
    pairs: int = 0  # matched points of the last iteration

    @property
    def shift(self) -> float:
        return math.hypot(self.tx, self.ty)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) points moved by the transform, float32."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        out = points.copy()
        out[:, 0] = c * points[:, 0] - s * points[:, 1] + self.tx
        out[:, 1] = s * points[:, 0] + c * points[:, 1] + self.ty
        return out.astype(np.float32)

    def undo(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) points moved by the inverse transform, R(-yaw) (p - t), float64."""
        out = np.array(points, dtype=np.float64).reshape(-1, 3)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        x, y = out[:, 0] - self.tx, out[:, 1] - self.ty
        out[:, 0], out[:, 1] = c * x + s * y, -s * x + c * y
        return out


def align_planar(source: np.ndarray, target: np.ndarray, settings: AlignSettings | None = None
                 ) -> PlanarTransform | None:
    """The planar rigid transform that moves `source` (M, 3) onto `target` (P, 3) (metres), or None when
    the fit is refused (too few matches, or a shift or turn beyond the settings' bounds)."""
    settings = settings or AlignSettings()
    source = evenly_strided(np.asarray(source, dtype=np.float64).reshape(-1, 3), settings.max_source_points)
    target = evenly_strided(np.asarray(target, dtype=np.float64).reshape(-1, 3), settings.max_target_points)
    if min(len(source), len(target)) < settings.min_pairs \
            or not (np.isfinite(source).all() and np.isfinite(target).all()):
        return None
    from gd_completion.kernels import icp_planar  # numba: imported at first use, not by the settings' readers

    yaw, tx, ty, pairs = icp_planar(np.ascontiguousarray(source), np.ascontiguousarray(target),
                                     float(settings.max_distance), int(settings.iterations))
    transform = PlanarTransform(float(yaw), float(tx), float(ty), int(pairs))
    if pairs < max(settings.min_pairs, settings.min_overlap * len(source)) or transform.shift > settings.max_shift \
            or abs(math.degrees(transform.yaw)) > settings.max_yaw_deg:
        return None
    return transform
