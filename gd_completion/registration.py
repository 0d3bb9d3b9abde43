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

import numba
import numpy as np

from gd_completion.cell_grid import bucket_points
from gd_completion.limits import check_positive_fields
from gd_completion.sampling import evenly_strided

__all__ = ["AlignSettings", "PlanarTransform", "align_planar"]

MAX_GRID_CELLS = 1 << 22  # cells of the target grid at most (the cell grows beyond max_distance past it)


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


@numba.njit(cache=True, nogil=True)
def _icp_planar(source: np.ndarray, target: np.ndarray, max_distance: float, iterations: int
                ) -> tuple[float, float, float, int]:
    """(yaw, tx, ty, pairs) of the trimmed planar ICP of `source` onto `target` (float64 (n, 3), (m, 3))."""
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    h = max_distance
    for _ in range(64):  # grow the cell until the grid is small enough (a cell >= max_distance stays exact)
        total = 1
        for a in range(3):
            lo[a] = target[:, a].min()
            dims[a] = int((target[:, a].max() - lo[a]) / h) + 1
            total *= dims[a]
        if total <= MAX_GRID_CELLS:
            break
        h *= 2.0
    start, order = bucket_points(target, lo, np.full(3, h), dims)

    limit = max_distance * max_distance
    yaw, tx, ty, pairs = 0.0, 0.0, 0.0, 0
    k = np.empty(3, np.int64)
    q = np.empty(3)
    for _ in range(iterations):
        cs, sn = math.cos(yaw), math.sin(yaw)
        n = 0
        sax = say = sbx = sby = dot = cross = 0.0
        for i in range(source.shape[0]):
            q[0] = cs * source[i, 0] - sn * source[i, 1] + tx
            q[1] = sn * source[i, 0] + cs * source[i, 1] + ty
            q[2] = source[i, 2]
            outside = False
            for a in range(3):
                k[a] = int(math.floor((q[a] - lo[a]) / h))
                if k[a] < -1 or k[a] > dims[a]:
                    outside = True
            if outside:
                continue
            best, hit = limit, -1
            for x in range(max(k[0] - 1, 0), min(k[0] + 1, dims[0] - 1) + 1):
                for y in range(max(k[1] - 1, 0), min(k[1] + 1, dims[1] - 1) + 1):
                    for z in range(max(k[2] - 1, 0), min(k[2] + 1, dims[2] - 1) + 1):
                        c = (x * dims[1] + y) * dims[2] + z
                        for p in range(start[c], start[c + 1]):
                            j = order[p]
                            dx = target[j, 0] - q[0]
                            dy = target[j, 1] - q[1]
                            dz = target[j, 2] - q[2]
                            d = dx * dx + dy * dy + dz * dz
                            if d < best:
                                best, hit = d, j
            if hit < 0:
                continue
            ax, ay, bx, by = source[i, 0], source[i, 1], target[hit, 0], target[hit, 1]
            n += 1
            sax += ax
            say += ay
            sbx += bx
            sby += by
            dot += ax * bx + ay * by
            cross += ax * by - ay * bx
        pairs = n
        if n == 0:
            break
        # closed-form planar Procrustes on the centred pairs
        new_yaw = math.atan2(cross - (sax * sby - say * sbx) / n, dot - (sax * sbx + say * sby) / n)
        cs, sn = math.cos(new_yaw), math.sin(new_yaw)
        new_tx = (sbx - (cs * sax - sn * say)) / n
        new_ty = (sby - (sn * sax + cs * say)) / n
        moved = abs(new_yaw - yaw) + abs(new_tx - tx) + abs(new_ty - ty)
        yaw, tx, ty = new_yaw, new_tx, new_ty
        if moved < 1e-6:
            break
    return yaw, tx, ty, pairs


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
    yaw, tx, ty, pairs = _icp_planar(np.ascontiguousarray(source), np.ascontiguousarray(target),
                                     float(settings.max_distance), int(settings.iterations))
    transform = PlanarTransform(float(yaw), float(tx), float(ty), int(pairs))
    if pairs < max(settings.min_pairs, settings.min_overlap * len(source)) or transform.shift > settings.max_shift \
            or abs(math.degrees(transform.yaw)) > settings.max_yaw_deg:
        return None
    return transform
