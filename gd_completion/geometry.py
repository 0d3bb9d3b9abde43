"""3D vehicle boxes: validation, vectorised cropping and the PCN/KITTI normalisation (pure numpy)."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gd_completion.errors import BoxError

__all__ = [
    "Box3D", "box_problem", "boxes_to_array", "box_corners", "crop_boxes",
    "normalize", "denormalize", "finite_mask",
]

# Largest number of grid cells crop_boxes uses for its prefilter.
_MAX_CELLS = 1 << 20


def _triple(value: Sequence[float], what: str) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise BoxError(f"Box3D {what} must be three numbers, got {value!r}") from exc
    if len(out) != 3:
        raise BoxError(f"Box3D {what} must be three numbers, got {len(out)}: {value!r}")
    return out


@dataclass(frozen=True)
class Box3D:
    """An oriented 3D box: `center` (x, y, z), `size` (length along heading, width, height), `yaw` about +z.

    yaw = 0 points the length along +x; angles in radians, sizes in metres. Values are stored as floats
    and are not checked here: use `box_problem` before using a box from outside.
    """

    center: tuple[float, ...]   # (x, y, z); any 3 numbers are stored as a tuple of 3 floats
    size: tuple[float, ...]     # (length, width, height)
    yaw: float = 0.0
    label: str = "car"
    instance_id: int = -1

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _triple(self.center, "center"))
        object.__setattr__(self, "size", _triple(self.size, "size"))
        object.__setattr__(self, "yaw", float(self.yaw))
        object.__setattr__(self, "instance_id", int(self.instance_id))


def box_problem(box: Box3D) -> str | None:
    """Why `box` is unusable (non-finite centre/size/yaw, non-positive size), or None if it is fine."""
    if not all(math.isfinite(v) for v in box.center):
        return f"non-finite centre {box.center}"
    if not all(math.isfinite(v) for v in box.size):
        return f"non-finite size {box.size}"
    if not math.isfinite(box.yaw):
        return f"non-finite yaw {box.yaw}"
    if not all(v > 0.0 for v in box.size):
        return f"non-positive size {box.size}"
    return None


def boxes_to_array(boxes: Sequence[Box3D]) -> np.ndarray:
    """(K, 7) float64 rows (cx, cy, cz, length, width, height, yaw)."""
    out = np.empty((len(boxes), 7), dtype=np.float64)
    for i, b in enumerate(boxes):
        out[i, :3] = b.center
        out[i, 3:6] = b.size
        out[i, 6] = b.yaw
    return out


def box_corners(box: Box3D) -> np.ndarray:
    """(8, 3) float64 corners: bottom face then top face, each front-left, front-right, rear-right, rear-left."""
    l, w, h = (s / 2.0 for s in box.size)
    local = np.array([[l, w, -h], [l, -w, -h], [-l, -w, -h], [-l, w, -h],
                      [l, w, h], [l, -w, h], [-l, -w, h], [-l, w, h]], dtype=np.float64)
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ rot.T + np.asarray(box.center)


def finite_mask(points: np.ndarray) -> np.ndarray:
    """Bool (N,): rows of `points` (N, 3) whose coordinates are all finite."""
    finite = np.isfinite(_check_points(points))
    return finite[:, 0] & finite[:, 1] & finite[:, 2]   # 8x faster than .all(axis=1) on 3 columns


def _check_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    return points


def _check_boxes(boxes: Sequence[Box3D]) -> np.ndarray:
    for i, b in enumerate(boxes):
        reason = box_problem(b)
        if reason is not None:
            raise BoxError(f"box {i} ({b.label}, instance {b.instance_id}) is unusable: {reason}")
    return boxes_to_array(boxes)


def crop_boxes(points: np.ndarray, boxes: Sequence[Box3D], margin: float = 0.0) -> list[np.ndarray]:
    """For each box, the ascending indices (intp) of `points` (N, 3) inside the box grown by `margin` metres.

    Points on a face count as inside; non-finite points are never inside. Vectorised over all boxes:
    a coarse xy grid marks the cells any box touches, the points in those cells are tested against every
    box's axis-aligned bounds, and the surviving (point, box) pairs go through one exact transform.
    Raises BoxError for an unusable box or a non-finite margin.
    """
    points = _check_points(points)
    margin = float(margin)
    if not math.isfinite(margin):
        raise BoxError(f"crop margin must be finite, got {margin}")
    arr = _check_boxes(boxes)
    k = arr.shape[0]
    if k == 0:
        return []
    if points.shape[0] == 0:
        return [np.empty(0, dtype=np.intp) for _ in range(k)]

    center = arr[:, :3]
    half = arr[:, 3:6] / 2.0 + margin  # (K, 3) half length, width, height of the grown box
    cos, sin = np.cos(arr[:, 6]), np.sin(arr[:, 6])
    # Axis-aligned bounds of each grown, rotated box (a superset; the exact test comes last).
    ext = np.stack([np.abs(cos) * half[:, 0] + np.abs(sin) * half[:, 1],
                    np.abs(sin) * half[:, 0] + np.abs(cos) * half[:, 1], half[:, 2]], axis=1)
    usable = (half > 0).all(axis=1)
    if not usable.any():
        return [np.empty(0, dtype=np.intp) for _ in range(k)]
    ext = ext * (1 + 1e-9) + 1e-6  # keep the prefilter conservative under rounding
    lo, hi = center - ext, center + ext

    box_idx, pt = _grid_pairs(points, lo, hi, np.flatnonzero(usable))
    if pt.size == 0:
        return [np.empty(0, dtype=np.intp) for _ in range(k)]
    d = points[pt].astype(np.float64) - center[box_idx]
    c, s = cos[box_idx], sin[box_idx]
    hb = half[box_idx]
    inside = ((np.abs(c * d[:, 0] + s * d[:, 1]) <= hb[:, 0])
              & (np.abs(-s * d[:, 0] + c * d[:, 1]) <= hb[:, 1])
              & (np.abs(d[:, 2]) <= hb[:, 2]))
    box_idx, pt = box_idx[inside], pt[inside]
    order = np.argsort(box_idx, kind="stable")  # by box, points stay ascending
    counts = np.bincount(box_idx, minlength=k)
    return np.split(pt[order], np.cumsum(counts)[:-1])


def _grid_pairs(points: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (box, point) pairs: points in an xy grid cell touched by box bounds [lo, hi] (K, 3).

    Only boxes `which` take part; points come out ascending. A superset of the true pairs.
    """
    lo_w, hi_w = lo[which], hi[which]
    x0, y0 = lo_w[:, 0].min(), lo_w[:, 1].min()
    span_x, span_y = hi_w[:, 0].max() - x0, hi_w[:, 1].max() - y0
    # Cell about a third of the median box extent, coarser if the grid would be too large.
    cell = max(float(np.median(np.minimum(hi_w[:, 0] - lo_w[:, 0], hi_w[:, 1] - lo_w[:, 1]))) / 3.0, 0.05)
    cell = max(cell, math.sqrt(span_x * span_y / _MAX_CELLS), span_x / 4096, span_y / 4096)
    nx, ny = int(span_x // cell) + 1, int(span_y // cell) + 1

    # Every (cell, box) pair of each box's cell rectangle, vectorised over boxes.
    ix0 = np.clip(((lo[:, 0] - x0) // cell), 0, nx - 1).astype(np.intp)
    ix1 = np.clip(((hi[:, 0] - x0) // cell), 0, nx - 1).astype(np.intp) + 1
    iy0 = np.clip(((lo[:, 1] - y0) // cell), 0, ny - 1).astype(np.intp)
    iy1 = np.clip(((hi[:, 1] - y0) // cell), 0, ny - 1).astype(np.intp) + 1
    rows = np.where(np.isin(np.arange(lo.shape[0]), which), iy1 - iy0, 0)
    n_cells = (ix1 - ix0) * rows
    pair_box = np.repeat(np.arange(lo.shape[0]), n_cells)
    j = np.arange(pair_box.size) - np.repeat(np.cumsum(n_cells) - n_cells, n_cells)
    pair_cell = (ix0[pair_box] + j // rows[pair_box]) * ny + iy0[pair_box] + j % rows[pair_box]
    order = np.argsort(pair_cell, kind="stable")
    pair_box = pair_box[order]
    per_cell = np.bincount(pair_cell, minlength=nx * ny)
    first = np.cumsum(per_cell) - per_cell

    fx = (points[:, 0] - x0) * (1.0 / cell)
    fy = (points[:, 1] - y0) * (1.0 / cell)
    z = points[:, 2]
    ok = (fx >= 0) & (fx < nx) & (fy >= 0) & (fy < ny)  # NaN fails every comparison
    ok &= (z >= lo_w[:, 2].min()) & (z <= hi_w[:, 2].max())
    idx = np.flatnonzero(ok)
    cell_of = fx[idx].astype(np.intp) * ny + fy[idx].astype(np.intp)
    n_boxes = per_cell[cell_of]
    hit = n_boxes > 0
    idx, cell_of, n_boxes = idx[hit], cell_of[hit], n_boxes[hit]
    pt = np.repeat(idx, n_boxes)
    k = np.arange(pt.size) - np.repeat(np.cumsum(n_boxes) - n_boxes, n_boxes)
    box = pair_box[np.repeat(first[cell_of], n_boxes) + k]
    return box, pt.astype(np.intp, copy=False)


def _rotation_xy(box: Box3D) -> tuple[float, float]:
    return math.cos(box.yaw), math.sin(box.yaw)


def _require_usable_box(box: Box3D, action: str) -> None:
    reason = box_problem(box)
    if reason is not None:
        raise BoxError(f"cannot {action} with box ({box.label}, instance {box.instance_id}): {reason}")


def normalize(points: np.ndarray, box: Box3D) -> np.ndarray:
    """PCN KITTI normalisation: subtract the box centre, rotate by -yaw, divide by the box length -> float32."""
    points = _check_points(points)
    _require_usable_box(box, "normalise")
    c, s = _rotation_xy(box)
    d = points.astype(np.float64) - np.asarray(box.center)
    out = np.empty(d.shape, dtype=np.float64)
    out[:, 0] = c * d[:, 0] + s * d[:, 1]
    out[:, 1] = -s * d[:, 0] + c * d[:, 1]
    out[:, 2] = d[:, 2]
    out /= box.size[0]
    return out.astype(np.float32)


def denormalize(points: np.ndarray, box: Box3D) -> np.ndarray:
    """Inverse of `normalize`: scale by the box length, rotate by +yaw, add the centre -> float32."""
    points = _check_points(points)
    _require_usable_box(box, "denormalise")
    c, s = _rotation_xy(box)
    p = points.astype(np.float64) * box.size[0]
    out = np.empty(p.shape, dtype=np.float64)
    out[:, 0] = c * p[:, 0] - s * p[:, 1]
    out[:, 1] = s * p[:, 0] + c * p[:, 1]
    out[:, 2] = p[:, 2]
    out += np.asarray(box.center)
    return out.astype(np.float32)
