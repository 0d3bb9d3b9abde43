"""Even spacing (gd_completion.spacing): points move along their own surface, their spacing evens out."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gd_completion.spacing import SpacingSettings, _plane, _two_hop_nearest, even_spacing


def clumped_square(seed: int = 0) -> np.ndarray:
    """600 points on the unit square z = 0: half in four tight clumps, half uniform."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.2, 0.8, (4, 2))
    clumps = (centres[rng.integers(4, size=300)] + rng.normal(0.0, 0.02, (300, 2)))
    spread = rng.uniform(0.0, 1.0, (300, 2))
    xy = np.concatenate([clumps, spread])
    return np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)


def nn_distances(points: np.ndarray) -> np.ndarray:
    return cKDTree(points).query(points, 2)[0][:, 1]


def coverage(points: np.ndarray, surface: np.ndarray) -> float:
    """Mean squared distance of a dense sample of the true surface to the nearest point."""
    return float((cKDTree(points).query(surface)[0] ** 2).mean())


def test_clumped_points_on_a_plane_spread_out_and_stay_on_it() -> None:
    points = clumped_square()
    spaced = even_spacing(points)
    assert spaced.shape == points.shape and spaced.dtype == np.float32
    assert np.abs(spaced[:, 2]).max() < 1e-6                       # pushed within the plane only
    before, after = nn_distances(points), nn_distances(spaced)
    assert after.std() / after.mean() < 0.85 * before.std() / before.mean()   # more even (0.77x)
    assert after.min() > 2 * before.min()
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60)), -1).reshape(-1, 2)
    surface = np.column_stack([grid, np.zeros(len(grid))])
    assert coverage(spaced, surface) < 0.9 * coverage(points, surface)   # 0.80x


def test_points_on_a_sphere_stay_on_it_while_spreading() -> None:
    rng = np.random.default_rng(1)
    v = rng.normal(size=(1500, 3))
    v[:700] = v[:700] * [1.0, 0.2, 0.2] + [2.0, 0.0, 0.0]           # a clump around +x
    points = (0.5 * v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)
    spaced = even_spacing(points)
    radius = np.linalg.norm(spaced, axis=1)
    assert np.abs(radius - 0.5).max() < 0.01                        # 2 % of the radius
    before, after = nn_distances(points), nn_distances(spaced)
    assert after.std() / after.mean() < 0.9 * before.std() / before.mean()   # 0.80x


def test_flattening_thins_a_noisy_shell() -> None:
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(0, 1, (800, 2)), rng.normal(0.0, 0.01, 800)]).astype(np.float32)
    flat = even_spacing(points, SpacingSettings(iterations=0, flatten=0.5))
    assert np.abs(flat[:, :2] - points[:, :2]).max() < 0.01                # moved along the fitted normal only
    assert flat[:, 2].std() < 0.75 * points[:, 2].std()


def test_repeated_points_separate() -> None:
    points = clumped_square()
    points[1::2] = points[0::2]                                     # every point twice
    spaced = even_spacing(points)
    assert nn_distances(points).min() == 0.0
    assert nn_distances(spaced).min() > 0.0
    assert np.abs(spaced[:, 2]).max() < 1e-6


def test_nothing_to_do_returns_the_points() -> None:
    points = clumped_square()
    assert np.array_equal(even_spacing(points, SpacingSettings(iterations=0, flatten=0.0)), points)
    two = points[:2]
    assert np.array_equal(even_spacing(two), two)


def test_batches_are_spaced_cloud_by_cloud() -> None:
    batch = np.stack([clumped_square(s) for s in range(3)])
    out = even_spacing(batch)
    assert out.shape == batch.shape
    for b in range(3):
        assert np.array_equal(out[b], even_spacing(batch[b]))


def knn_graph(points: np.ndarray, k: int = 8) -> np.ndarray:
    return cKDTree(points).query(points, k + 1)[1][:, 1:]


def test_two_hops_find_the_nearest_in_ascending_order() -> None:
    points = clumped_square(4)
    points[:, 2] = np.random.default_rng(4).normal(0.0, 0.01, len(points))
    found = _two_hop_nearest(points, knn_graph(points), 16)
    exact = knn_graph(points, 16)
    padded = found == np.arange(len(points))[:, None]                       # fewer than 16 found: itself after them
    assert padded.any() and not (np.diff(padded.astype(int), axis=1) < 0).any()
    dist = np.where(padded, 1e9, np.linalg.norm(points[found] - points[:, None], axis=2))
    assert (np.diff(dist, axis=1) >= 0).all()                               # ascending
    assert np.mean([len(set(a) & set(b)) / 16 for a, b in zip(found, exact)]) > 0.9
    # a point whose graph row holds only itself gets itself (no neighbour), and is not pushed
    graph = knn_graph(points)
    graph[graph == 7] = graph[0, 0]   # nobody points at 7
    graph[7] = 7                      # and 7 at nobody else
    assert (_two_hop_nearest(points, graph, 16)[7] == 7).all()
    assert np.array_equal(even_spacing(points, SpacingSettings(flatten=0.0), graph=graph)[7], points[7])


def test_the_graph_path_spreads_like_the_search() -> None:
    points = clumped_square(5)
    spaced = even_spacing(points, graph=knn_graph(points))
    assert np.abs(spaced[:, 2]).max() < 1e-6
    before, after = nn_distances(points), nn_distances(spaced)
    assert after.std() / after.mean() < 0.85 * before.std() / before.mean()
    twice = np.repeat(points[:300], 2, axis=0)                               # repeated points, graph path
    assert nn_distances(even_spacing(twice, graph=knn_graph(twice))).min() > 0.0


def test_small_and_degenerate_clouds() -> None:
    rng = np.random.default_rng(6)
    for n in (3, 5, 9, 17, 20):
        cloud = rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32)
        out = even_spacing(cloud)
        assert out.shape == (n, 3) and np.isfinite(out).all()
        assert np.abs(out - cloud).max() < 1.0
    same = np.full((50, 3), 0.25, np.float32)                               # one point, repeated
    assert np.array_equal(even_spacing(same), same)
    line = np.column_stack([np.linspace(0, 1, 40), np.zeros(40), np.zeros(40)]).astype(np.float32)
    out = even_spacing(line)                                                # no plane anywhere: the line stays one
    assert np.isfinite(out).all() and np.abs(out[:, 1:]).max() < 1e-6


def test_plane_normal_is_the_smallest_eigenvector() -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(200, 3)) * [1.0, 0.5, 0.05]
    points = points @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    nbr = cKDTree(points).query(points, 17)[1][:, 1:]
    centre, normal = np.zeros(3), np.zeros(3)
    for i in range(0, 200, 7):
        _plane(points, nbr, i, centre, normal)
        hood = points[np.concatenate([[i], nbr[i]])]
        values, vectors = np.linalg.eigh(np.cov(hood.T))
        assert np.allclose(centre, hood.mean(0))
        assert abs(abs(normal @ vectors[:, 0]) - 1.0) < 1e-6
    line = np.column_stack([np.arange(20.0), np.zeros(20), np.zeros(20)])   # no plane through a line
    _plane(line, np.tile(np.arange(1, 17), (20, 1)), 0, centre, normal)
    assert not normal.any()
    angle = np.linspace(0, 2 * np.pi, 17)[:-1]                              # a round disc: two equal eigenvalues
    disc = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(16)]) @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    disc = np.vstack([np.zeros(3), disc])
    _plane(disc, np.arange(1, 17)[None], 0, centre, normal)
    plane_normal = np.cross(disc[1], disc[5])
    assert abs(abs(normal @ plane_normal) / np.linalg.norm(plane_normal) - 1.0) < 1e-9
    assert normal[np.argmax(np.abs(normal))] > 0                             # one sign per plane
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)   # isotropic
    _plane(np.vstack([np.zeros(3), cube]), np.arange(1, 9)[None], 0, centre, normal)
    assert not normal.any()


def test_bad_input_is_refused() -> None:
    points = clumped_square()
    points[5, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        even_spacing(points)
    with pytest.raises(ValueError, match="must be"):
        even_spacing(np.zeros((10, 2), np.float32))
    with pytest.raises(ValueError):
        SpacingSettings(step=2.0)
    with pytest.raises(ValueError):
        SpacingSettings(neighbours=0)
