"""Points bucketed by the cell of a uniform grid (numba counting sort): the shared step of the grid searches
(`kernels`' kNN graph, `registration`'s ICP, `evaluation.nearest`). Each search chooses its own cell
size and grid extent; the cell of a point and the bucketing are the same code for all three."""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def bucket_by_cell(cell: np.ndarray, total: int) -> tuple[np.ndarray, np.ndarray]:
    """(start (total + 1,), order (n,)) for the cell index (n,) int64 of each point, cells in [0, total):
    the points of cell c are order[start[c]:start[c + 1]], in input order."""
    n = cell.shape[0]
    start = np.zeros(total + 1, np.int64)
    for j in range(n):
        start[cell[j] + 1] += 1
    for c in range(total):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for j in range(n):
        order[fill[cell[j]]] = j
        fill[cell[j]] += 1
    return start, order


@numba.njit(cache=True, nogil=True)
def bucket_points(points: np.ndarray, lo: np.ndarray, width: np.ndarray, dims: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """`bucket_by_cell` of `points` (n, 3) on the grid of `dims` (3,) int64 cells of `width` (3,) from `lo` (3,),
    both float64, cells numbered row-major (x slowest): a point's cell on each axis is
    min(int((p - lo) / width), dims - 1) (points at or above `lo`; an infinite width puts every point in cell 0)."""
    n = points.shape[0]
    cell = np.empty(n, np.int64)
    for j in range(n):
        c = 0
        for a in range(3):
            c = c * dims[a] + min(int((points[j, a] - lo[a]) / width[a]), dims[a] - 1)
        cell[j] = c
    return bucket_by_cell(cell, dims[0] * dims[1] * dims[2])
