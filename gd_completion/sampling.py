"""Sampling of point sets, one place for every caller: farthest point sampling to the network's input size
(`resample_indices`), one point per voxel (`voxel_first_indices`), evenly strided subsets (`strided_indices`).

A leaf: it depends on the compiled kernels only (no torch; loaded on first use), so the preprocessing contract,
the merge, the track fusion, the registration, the reuse cache and the evaluation can all call it.
"""
from __future__ import annotations

import numpy as np

__all__ = ["evenly_strided", "resample_indices", "strided_indices", "voxel_downsample", "voxel_first_indices"]


def resample_indices(count: int, points: np.ndarray, n: int) -> np.ndarray:
    """Indices giving exactly `n` of `count` points: farthest point sampling down (starting at point 0, the
    compiled kernel `model.ops.farthest_point_sample` uses on the CPU), cyclic repetition up."""
    if count <= 0:
        raise ValueError("cannot resample an empty cloud")
    if count <= n:
        return np.arange(n) % count
    from gd_completion import kernels  # numba on first use: `completer --help` stays light

    cloud = np.ascontiguousarray(points[:count], dtype=np.float32)[None]
    return kernels.fps(cloud, n)[0].astype(np.int64)


def voxel_first_indices(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Ascending indices of the first point (in input order) of each `voxel_size` voxel of `points` (M, 3),
    all finite."""
    if len(points) == 0:
        return np.zeros(0, np.intp)
    keys = np.floor(np.asarray(points, dtype=np.float64) / voxel_size)   # integer-valued floats
    low = keys.min(axis=0)
    span = keys.max(axis=0) - low + 1
    if np.abs(keys).max() >= 2.0 ** 52 or float(np.prod(span)) >= 2.0 ** 62:
        # keys beyond exact float64 integers, or one integer code per voxel would overflow: unique rows
        return np.sort(np.unique(keys, axis=0, return_index=True)[1])
    shifted, strides = (keys - low).astype(np.int64), span.astype(np.int64)
    code = (shifted[:, 0] * strides[1] + shifted[:, 1]) * strides[2] + shifted[:, 2]
    return np.sort(np.unique(code, return_index=True)[1])


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """The first point (in input order) of each `voxel_size` voxel of `points` (M, 3), order kept."""
    return points[voxel_first_indices(points, voxel_size)]


def strided_indices(count: int, n: int) -> np.ndarray:
    """At most `n` evenly spaced indices of `count` items, ascending (all of them when `count` <= `n`)."""
    if count <= n:
        return np.arange(count)
    return np.linspace(0, count - 1, n).round().astype(np.intp)


def evenly_strided(points: np.ndarray, n: int) -> np.ndarray:
    """At most `n` evenly spaced rows of `points` (`points` itself when it has no more)."""
    return points if len(points) <= n else points[strided_indices(len(points), n)]
