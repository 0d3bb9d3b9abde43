"""Measured merge: a vehicle's completion thinned together with its measured points and their mirror image.

The network's N_o points cover the whole vehicle, but only its N_c control points are copies of measured
points; a densely seen side is better described by the measurements themselves. The merge takes the
union of the measured points fed to the network (at most its input size), their mirror image about the
box's longitudinal plane (y -> -y) and the completion, and keeps N_o of them by farthest point sampling
(deterministic, starting at a measured point): measured points replace network points where they lie
densely, the network fills what is unseen, and the spacing stays even. The box-only analogue (mirror and
a template instead of the network) is the "mirror + template" prior of the evaluation.
"""
from __future__ import annotations

import numpy as np

from gd_completion.model.kernels import fps_pruned
from gd_completion.preprocess import network_input

MEASURED = 0    # source of a merged point: a measured point
GENERATED = 1   # ... or a generated one: the network's or the mirror image of a measured point


def mirrored(points: np.ndarray) -> np.ndarray:
    """Points of the normalised box frame mirrored about its longitudinal vertical plane (y -> -y)."""
    return np.asarray(points, np.float32) * np.array([1.0, -1.0, 1.0], np.float32)


def merge_measured(completion: np.ndarray, measured: np.ndarray, n: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float32, source (n,) uint8 MEASURED / GENERATED): farthest point sampling of the union
    of `measured` (M, 3), its mirror image and `completion` (N_o, 3), all in the normalised box frame;
    `n` defaults to N_o. Pass the measured points the network saw (`preprocess.network_input`, without
    repeats) to bound the cost: about 2 ms for 512 measured and 2,048 completion points on one core."""
    completion = np.asarray(completion, np.float32).reshape(-1, 3)
    measured = np.asarray(measured, np.float32).reshape(-1, 3)
    n = len(completion) if n is None else int(n)
    union = np.concatenate([measured, mirrored(measured), completion])
    if n > len(union):
        raise ValueError(f"cannot keep {n} of {len(union)} points")
    if n <= 0:
        return np.zeros((0, 3), np.float32), np.zeros(0, np.uint8)
    keep = fps_pruned(np.ascontiguousarray(union), n)
    if len(np.unique(keep)) < n:
        # every distinct point taken (FPS then repeats index 0): exact repeats in the union, e.g. a sparse
        # input's cycled control points. All distinct points, then the completion's repeated cyclically.
        distinct = np.sort(np.unique(union, axis=0, return_index=True)[1])
        network = distinct[distinct >= 2 * len(measured)]
        pool = network if len(network) else distinct
        keep = np.concatenate([distinct, pool[np.arange(n - len(distinct)) % len(pool)]])
    return union[keep], np.where(keep < len(measured), MEASURED, GENERATED).astype(np.uint8)


def merge_with_fed(completion: np.ndarray, partial: np.ndarray, num_input: int, fed: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """`merge_measured` with the measured points the network was fed: `fed` = `network_input(partial,
    num_input)` (computed when None), without the cyclic repeats of a partial smaller than `num_input`."""
    partial = np.asarray(partial, np.float32).reshape(-1, 3)
    fed = network_input(partial, num_input) if fed is None else fed
    return merge_measured(completion, fed[:min(len(partial), num_input)])
