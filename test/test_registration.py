"""Planar rigid alignment of a frame to a track's points (registration.align_planar): recovery and refusals."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gd_completion.registration import AlignSettings, PlanarTransform, align_planar
from gd_completion.synth.meshio import sample_surface
from gd_completion.synth.vehicles import generate_vehicle


def seen_part(rng: np.random.Generator, n: int) -> np.ndarray:
    """`n` surface points of one sedan (the same shape for every seed of `rng`) on its left and rear halves:
    the L-shaped part a lidar behind and left of it sees."""
    mesh = generate_vehicle(np.random.default_rng(7), "sedan")
    points = sample_surface(mesh, 4 * n, rng)
    return points[(points[:, 1] > 0) | (points[:, 0] < -1.5)][:n]


@pytest.mark.parametrize(("yaw_deg", "tx", "ty"), [(0.0, 0.0, 0.0), (2.0, 0.08, -0.05), (-3.5, -0.15, 0.1)])
def test_recovers_a_planar_transform(yaw_deg: float, tx: float, ty: float) -> None:
    target = seen_part(np.random.default_rng(1), 3000)
    truth = PlanarTransform(math.radians(yaw_deg), tx, ty)
    # a fresh sampling of the same surface, moved by the inverse: aligning it must give `truth` back
    inverse = PlanarTransform(-truth.yaw, 0.0, 0.0)
    source = inverse.apply(seen_part(np.random.default_rng(2), 1500) - np.array([tx, ty, 0.0]))
    found = align_planar(source, target)
    assert found is not None and found.pairs >= 256
    assert math.degrees(abs(found.yaw - truth.yaw)) < 0.4   # point-to-point: limited by the sampling
    assert math.hypot(found.tx - tx, found.ty - ty) < 0.015
    moved = found.apply(source)
    assert moved.dtype == np.float32 and moved.shape == source.shape


def test_refuses_what_is_not_jitter() -> None:
    target = seen_part(np.random.default_rng(1), 3000)
    source = seen_part(np.random.default_rng(2), 1500)
    assert align_planar(source[:20], target) is None                          # fewer than min_pairs points
    assert align_planar(source + np.array([5.0, 0.0, 0.0]), target) is None   # nothing within max_distance
    strict = AlignSettings(max_shift=0.05)
    assert align_planar(source - np.array([0.15, 0.0, 0.0]), target, strict) is None   # beyond max_shift
    assert align_planar(source - np.array([0.15, 0.0, 0.0]), target) is not None
    bad = source.copy()
    bad[3] = np.nan
    assert align_planar(bad, target) is None


def test_a_new_side_touching_only_along_an_edge_is_refused() -> None:
    """Two faces of a box meeting at an edge: the points near the edge match, the rest do not (< min_overlap)."""
    u, v = np.meshgrid(np.arange(0.0, 1.8, 0.05), np.arange(0.0, 1.5, 0.05), indexing="ij")
    rear = np.stack([np.zeros(u.size), u.ravel(), v.ravel()], 1)              # the plane x = 0
    left = np.stack([u.ravel() * 2.5, np.full(u.size, 1.8), v.ravel()], 1)    # the plane y = 1.8, x >= 0
    assert align_planar(left, rear) is None
    assert align_planar(left, rear, AlignSettings(min_overlap=0.01)) is not None   # an edge would drag it


def test_target_with_far_outliers_uses_a_coarser_grid() -> None:
    target = seen_part(np.random.default_rng(1), 3000)
    target[::500] = [[1e4, -1e4, 50.0]]     # a few points far away: the grid grows its cells, stays exact
    source = seen_part(np.random.default_rng(2), 1500) - np.array([0.06, 0.0, 0.0])
    found = align_planar(source, target)
    assert found is not None and math.hypot(found.tx - 0.06, found.ty) < 0.015


@pytest.mark.parametrize("bad", [{"max_distance": 0.0}, {"iterations": 2.5}, {"min_overlap": 1.5},
                                 {"max_yaw_deg": math.inf}, {"max_source_points": True}])
def test_settings_are_validated(bad: dict) -> None:
    with pytest.raises(ValueError):
        AlignSettings(**bad)


def test_undo_inverts_apply() -> None:
    points = seen_part(np.random.default_rng(4), 200)
    transform = PlanarTransform(math.radians(3.0), 0.12, -0.07)
    back = transform.undo(transform.apply(points))
    assert back.dtype == np.float64
    np.testing.assert_allclose(back, points, atol=1e-6)
    assert np.abs(transform.apply(points) - points).max() > 0.05   # it did move them
