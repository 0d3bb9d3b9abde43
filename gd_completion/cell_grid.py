"""Points bucketed by the cell of a uniform grid (numba counting sort): the shared step of the grid searches
(`model.kernels`' kNN graph, `registration`'s ICP, `evaluation.nearest`)."""
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
