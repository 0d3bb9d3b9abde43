"""The measured merge and its pruned FPS kernel."""
from __future__ import annotations

import numpy as np
import pytest

from gd_completion.merge import GENERATED, MEASURED, merge_measured, merge_with_fed, mirrored
from gd_completion.model.kernels import _fps_cloud, fps_pruned
from gd_completion.preprocess import network_input


def _plain_fps(xyz: np.ndarray, n: int) -> np.ndarray:
    out = np.empty(n, np.int64)
    _fps_cloud(xyz, n, out)
    return out


@pytest.mark.parametrize(("m", "n", "leaf"), [(300, 300, 32), (2600, 2048, 32), (5000, 512, 128), (700, 100, 1)])
def test_pruned_fps_returns_the_plain_scan(m, n, leaf):
    rng = np.random.default_rng(m)
    xyz = (rng.random((m, 3)) * np.array([1.0, 0.4, 0.35])).astype(np.float32)
    assert np.array_equal(fps_pruned(xyz, n, leaf), _plain_fps(xyz, n))


def test_pruned_fps_ties_and_repeats_match_the_plain_scan():
    rng = np.random.default_rng(3)
    half = rng.integers(0, 4, (1500, 3)).astype(np.float32)      # a 4x4x4 lattice: exact distance ties
    xyz = np.concatenate([half, half])                             # every point twice
    picks = fps_pruned(xyz, 1200)
    assert np.array_equal(picks, _plain_fps(xyz, 1200))
    assert len(np.unique(xyz[picks[:64]], axis=0)) == 64           # all 64 lattice points before any repeat


def test_merge_keeps_dense_measurements_and_fills_the_rest():
    rng = np.random.default_rng(0)
    side = np.stack([rng.uniform(-0.5, 0.5, 400), np.full(400, 0.2), rng.uniform(-0.15, 0.15, 400)], 1)
    completion = np.stack([rng.uniform(-0.5, 0.5, 2048), rng.choice([-0.2, 0.2], 2048),
                           rng.uniform(-0.15, 0.15, 2048)], 1).astype(np.float32) + 0.01   # offset network surface
    points, source = merge_measured(completion, side)
    assert points.shape == (2048, 3) and points.dtype == np.float32 and source.dtype == np.uint8
    measured = source == MEASURED
    # measured points are copied exactly and dominate the seen side; the mirror image covers the other side
    assert np.isin(points[measured].view("f4,f4,f4"), side.astype(np.float32).view("f4,f4,f4")).all()
    assert 250 <= measured.sum() <= 400
    near_mirror = np.abs(points[:, 1] + 0.2) < 1e-6
    assert near_mirror.sum() >= 250 and (source[near_mirror] == GENERATED).all()
    assert len(np.unique(points, axis=0)) == 2048                  # farthest point sampling: no repeats


def test_merge_with_fed_uses_the_network_input_without_repeats():
    rng = np.random.default_rng(1)
    sparse = rng.uniform(-0.3, 0.3, (60, 3)).astype(np.float32)
    completion = rng.uniform(-0.5, 0.5, (256, 3)).astype(np.float32)
    points, source = merge_with_fed(completion, sparse, 128)
    assert points.shape == (256, 3) and (source == MEASURED).sum() <= 60
    dense = rng.uniform(-0.3, 0.3, (2000, 3)).astype(np.float32)
    fed = network_input(dense, 128)
    points, source = merge_with_fed(completion, dense, 128)
    kept = points[source == MEASURED]
    assert np.isin(kept.view("f4,f4,f4"), fed.view("f4,f4,f4")).all() and 0 < len(kept) <= 128
    assert np.array_equal(mirrored(fed)[:, 1], -fed[:, 1])


def test_merge_refuses_more_points_than_it_has():
    with pytest.raises(ValueError, match="cannot keep 100"):
        merge_measured(np.zeros((10, 3), np.float32), np.zeros((5, 3), np.float32), 100)


def test_merge_takes_each_distinct_point_once():
    rng = np.random.default_rng(2)
    measured = rng.uniform(-0.3, 0.3, (30, 3)).astype(np.float32)
    completion = np.concatenate([np.tile(measured, (4, 1)), rng.uniform(-0.5, 0.5, (136, 3))]).astype(np.float32)
    points, source = merge_measured(completion, measured, 150)    # 30 + 30 mirrored + 136 distinct: 196
    assert len(np.unique(points, axis=0)) == 150 and (source == MEASURED).sum() <= 30
    points, source = merge_measured(completion, measured, 256)    # more than the 196 distinct points
    assert len(np.unique(points, axis=0)) == 196 and len(points) == 256
    assert (source == MEASURED).sum() <= 30                           # the repeats are the completion's
