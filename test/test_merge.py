"""The measured merge and its pruned FPS kernel."""
from __future__ import annotations

import numpy as np
import pytest

from gd_completion.kernels import FPS_LEAF, _fps_cloud, _morton_order, fps, fps_pruned
from gd_completion.merge import (
    MIRROR_WEIGHT,
    PLANE_LIMIT,
    PLANE_MIN_MOVE,
    POOL_VOXEL,
    SIDE_GAP,
    check_plane_share,
    merge_measured,
    merge_with_pool,
    mirror_plane_offset,
    mirrored,
)
from gd_completion.sampling import resample_indices, voxel_first_indices


def _plain_fps(xyz: np.ndarray, n: int) -> np.ndarray:
    out = np.empty(n, np.int64)
    _fps_cloud(xyz, n, out)
    return out


def _rows_of(points: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """Row of `cloud` equal to each of `points` (-1 where none)."""
    lookup = {row.tobytes(): i for i, row in enumerate(np.asarray(cloud, np.float32))}
    return np.array([lookup.get(p.tobytes(), -1) for p in np.asarray(points, np.float32)])


@pytest.mark.parametrize(("m", "n", "leaf"), [(300, 300, 32), (2600, 2048, 32), (5000, 512, 128), (700, 100, 1)])
def test_pruned_fps_returns_the_plain_scan(m, n, leaf):
    rng = np.random.default_rng(m)
    xyz = (rng.random((m, 3)) * np.array([1.0, 0.4, 0.35])).astype(np.float32)
    assert np.array_equal(fps_pruned(xyz, n, leaf), _plain_fps(xyz, n))


def test_pruned_fps_ties_repeats_and_degenerate_clouds_match_the_plain_scan():
    rng = np.random.default_rng(3)
    half = rng.integers(0, 4, (1500, 3)).astype(np.float32)      # a 4x4x4 lattice: exact distance ties
    xyz = np.concatenate([half, half])                             # every point twice
    picks = fps_pruned(xyz, 1200)
    assert np.array_equal(picks, _plain_fps(xyz, 1200))
    assert len(np.unique(xyz[picks[:64]], axis=0)) == 64           # all 64 lattice points before any repeat
    same = np.ones((50, 3), np.float32)                            # one point, 50 times: no span to order by
    assert np.array_equal(fps_pruned(same, 50), _plain_fps(same, 50))
    flat = np.stack([rng.random(400), np.zeros(400), np.zeros(400)], 1).astype(np.float32)
    assert np.array_equal(fps_pruned(flat, 400, 7), _plain_fps(flat, 400))


def test_batched_fps_prunes_finite_clouds_and_scans_broken_ones_plainly():
    rng = np.random.default_rng(5)
    clouds = (rng.random((3, 900, 3)) * np.array([1.0, 0.4, 0.35])).astype(np.float32)
    clouds[1, 17] = np.nan                                         # no Morton code: the plain scan answers
    clouds[2, :450] = clouds[2, 450:]                              # every point twice
    picks = fps(clouds, 600)
    for cloud, got in zip(clouds, picks):
        assert np.array_equal(got, _plain_fps(cloud, 600))


def test_pruned_fps_matches_the_plain_scan_on_overflowed_distances_and_leaf_edges():
    rng = np.random.default_rng(9)
    huge = (rng.random((200, 3)) - 0.5).astype(np.float32) * np.float32(1e20)   # squared distances overflow to inf
    two = np.array([[1e20, 0, 0], [-1e20, 0, 0]], np.float32)
    for cloud in (huge, two):
        for n in (1, 2, len(cloud)):
            assert np.array_equal(fps_pruned(cloud, n), _plain_fps(cloud, n))
        assert np.array_equal(fps(cloud[None], len(cloud))[0], _plain_fps(cloud, len(cloud)))
    assert fps(huge[None], 0).shape == (1, 0)
    with pytest.raises(ValueError, match="fps"):   # never an out-of-bounds write
        fps(huge[None, :3], 4)
    for m in (1, FPS_LEAF - 1, FPS_LEAF, FPS_LEAF + 1):   # one point, a leaf one short of full, full, one over
        cloud = (rng.random((m, 3))).astype(np.float32)
        for n in sorted({1, m}):
            assert np.array_equal(fps_pruned(cloud, n), _plain_fps(cloud, n))


def test_morton_order_is_the_stable_sort_of_interleaved_10_bit_codes():
    rng = np.random.default_rng(11)
    xyz = (rng.random((3000, 3)) * np.array([2.0, 0.5, 0.0])).astype(np.float32)   # z flat: code bits 0
    xyz[1000:1300] = xyz[:300]                                                     # equal codes: by index
    lo, span = xyz.min(0), xyz.max(0) - xyz.min(0)
    unit = ((xyz - lo) / np.where(span > 0, span, 1)).astype(np.float64)   # float32 quotient, float64 scale
    q = np.where(span > 0, unit * 1023.0, 0).astype(np.int64)
    codes = sum(((q[:, a] >> b) & 1) << (3 * b + a) for a in range(3) for b in range(10))
    assert np.array_equal(_morton_order(xyz), np.argsort(codes, kind="stable"))


def test_pruned_fps_with_a_leaf_larger_than_the_cloud_is_the_plain_scan():
    xyz = np.random.default_rng(12).random((300, 3)).astype(np.float32)
    for leaf in (299, 300, 10**6, 2**62):          # 2**62: index * leaf would overflow int64 unclamped
        assert np.array_equal(fps_pruned(xyz, 300, leaf), _plain_fps(xyz, 300))


@pytest.mark.parametrize(("shape", "n", "leaf"), [((10, 3), 0, 32), ((10, 3), 11, 32), ((0, 3), 1, 32),
                                                  ((10, 2), 5, 32), ((10, 3), 5, 0)])
def test_pruned_fps_refuses_bad_arguments(shape, n, leaf):
    with pytest.raises(ValueError, match="fps_pruned"):
        fps_pruned(np.zeros(shape, np.float32), n, leaf)


def test_merge_keeps_dense_measurements_and_fills_the_rest():
    rng = np.random.default_rng(0)
    side = np.stack([rng.uniform(-0.5, 0.5, 400), np.full(400, 0.2), rng.uniform(-0.15, 0.15, 400)],
                    1).astype(np.float32)
    completion = np.stack([rng.uniform(-0.5, 0.5, 2048), rng.choice([-0.2, 0.2], 2048),
                           rng.uniform(-0.15, 0.15, 2048)], 1).astype(np.float32) + 0.01   # offset network surface
    merged = merge_measured(completion, side)
    points, rows = merged.points, merged.measured_row
    assert points.shape == (2048, 3) and points.dtype == np.float32 and rows.dtype == np.int64
    # measured points are copied exactly, with their rows, and dominate the seen side
    assert np.array_equal(_rows_of(points, side), rows)
    assert 250 <= merged.is_measured.sum() <= 400
    near_mirror = np.abs(points[:, 1] + 0.2) < 1e-6                # the mirror image covers the other side
    assert near_mirror.sum() >= 250 and not merged.is_measured[near_mirror].any()
    assert len(np.unique(points, axis=0)) == 2048                  # farthest point sampling: no repeats


def _plain_weighted_fps(xyz: np.ndarray, n: int, weights: np.ndarray) -> np.ndarray:
    """The weighted scan written out: float32 squared distances times the weights, ties to the lowest index."""
    xyz, weights = xyz.astype(np.float32), weights.astype(np.float32)
    dist = np.full(len(xyz), np.inf, np.float32)
    out = [0]
    for _ in range(n - 1):
        d = ((xyz - xyz[out[-1]]) ** 2).sum(1, dtype=np.float32) * weights
        dist = np.minimum(dist, d)
        out.append(int(np.argmax(dist)))
    return np.array(out)


@pytest.mark.parametrize(("m", "n", "leaf"), [(500, 300, 32), (3000, 2048, 64), (800, 800, 7)])
def test_weighted_pruned_fps_returns_the_weighted_scan(m, n, leaf):
    rng = np.random.default_rng(m + 1)
    xyz = (rng.random((m, 3)) * np.array([1.0, 0.4, 0.35])).astype(np.float32)
    weights = rng.choice(np.array([1.0, 0.5, 0.25], np.float32), m)
    assert np.array_equal(fps_pruned(xyz, n, leaf, weights), _plain_weighted_fps(xyz, n, weights))
    assert np.array_equal(fps_pruned(xyz, n, leaf, np.ones(m, np.float32)), _plain_fps(xyz, n))
    for bad in (np.zeros(m), np.full(m, 1.5), np.ones(m - 1), np.full(m, np.nan)):
        with pytest.raises(ValueError, match="weights"):
            fps_pruned(xyz, n, leaf, bad)


def test_lower_weights_keep_more_of_the_seen_side():
    """With the mirror's and the network's points weighing w, the seen side keeps more points per area than the other
    the lower w is: about as many at w = 1 (an even thinning), about 1 / w times as many at 0.5 (the shipped mirror
    weight: the test below), more again at 0.25."""
    rng = np.random.default_rng(5)
    side = np.stack([rng.uniform(-0.5, 0.5, 6000), np.full(6000, 0.2), rng.uniform(-0.15, 0.15, 6000)],
                    1).astype(np.float32)
    completion = np.stack([rng.uniform(-0.5, 0.5, 2048), np.full(2048, -0.2), rng.uniform(-0.15, 0.15, 2048)],
                          1).astype(np.float32)
    ratios = []
    for weight in (1.0, 0.5, 0.25):
        merged = merge_with_pool(completion, side, network_weight=weight, mirror_weight=weight)
        unseen = np.abs(merged.points[:, 1] + 0.2) < 1e-6
        assert merged.is_measured.sum() + unseen.sum() == 2048
        ratios.append(merged.is_measured.sum() / unseen.sum())
    assert 0.8 <= ratios[0] <= 1.2 and 1.6 <= ratios[1] <= 2.4 and ratios[2] > 1.1 * ratios[1]


def test_a_densely_seen_side_keeps_its_measurements_at_twice_the_density():
    """A side seen by 6,000 points, the other side covered by their mirror image and the network: the weighted merge
    keeps about 1 / MIRROR_WEIGHT (2) times as many points per area on the seen side as on the other, all of them
    exact copies of measured rows, so the measured points lie nearer the output than after an even (unweighted)
    thinning of the same union (mean squared distance)."""
    rng = np.random.default_rng(4)
    side = np.stack([rng.uniform(-0.5, 0.5, 6000), np.full(6000, 0.2), rng.uniform(-0.15, 0.15, 6000)],
                    1).astype(np.float32)
    completion = np.stack([rng.uniform(-0.5, 0.5, 2048), rng.choice([-0.2, 0.2], 2048),
                           rng.uniform(-0.15, 0.15, 2048)], 1).astype(np.float32)
    merged = merge_with_pool(completion, side)
    kept = merged.measured_row[merged.is_measured]
    assert np.array_equal(merged.points[merged.is_measured], side[kept])
    unseen = np.abs(merged.points[:, 1] + 0.2) < 1e-6
    ratio = merged.is_measured.sum() / unseen.sum()   # seen side (measured) against the other (mirror or network)
    assert 0.8 / MIRROR_WEIGHT <= ratio <= 1.2 / MIRROR_WEIGHT
    pool = side[voxel_first_indices(side, POOL_VOXEL)]
    union = np.concatenate([pool, mirrored(pool), completion])
    even = union[fps_pruned(union, 2048)]
    gap = lambda out: ((side[:, None] - out[None]) ** 2).sum(-1).min(1).mean()   # noqa: E731
    assert gap(merged.points) < 0.75 * gap(even)


def test_merge_with_pool_keeps_one_fused_point_per_voxel_and_stays_put_as_frames_arrive():
    rng = np.random.default_rng(2)
    completion = rng.uniform(-0.5, 0.5, (2048, 3)).astype(np.float32) * np.array([1, 0.4, 0.3], np.float32)
    side = lambda m: np.stack([rng.uniform(-0.5, 0.5, m), rng.normal(0.2, 0.003, m),   # noqa: E731
                               rng.uniform(-0.15, 0.15, m)], 1).astype(np.float32)
    fused = side(6000)                 # a track's fused partial: far more points than the network's 512
    merged = merge_with_pool(completion, fused)
    pool = voxel_first_indices(fused, POOL_VOXEL)
    kept = merged.measured_row[merged.is_measured]
    assert np.array_equal(merged.points[merged.is_measured], fused[kept])   # exact copies, rows into the partial
    fed_rows = resample_indices(len(fused), fused, 512)                       # what the network saw
    assert len(pool) > 512 and np.isin(kept, pool).all() and not np.isin(kept, fed_rows).all()
    assert len(kept) > 512            # more measured points than the network was fed
    # a new frame appended (the partial lists the oldest frame first): the old voxels keep their point
    grown = np.concatenate([fused, side(3000)])
    np.testing.assert_array_equal(voxel_first_indices(grown, POOL_VOXEL)[:len(pool)], pool)


@pytest.mark.parametrize("scale", [0.01, 1.0, 40.0, 1e6, 1e13])
def test_voxel_first_indices_match_unique_voxel_rows(scale):
    rng = np.random.default_rng(int(np.log10(scale)) + 20)
    points = (rng.normal(size=(3000, 3)) * scale).astype(np.float32)
    points = np.concatenate([points, points[::7]])       # repeats: their first occurrence counts
    keys = np.floor(points.astype(np.float64) / 0.02)
    expected = np.sort(np.unique(keys, axis=0, return_index=True)[1])   # huge spans take this path themselves
    np.testing.assert_array_equal(voxel_first_indices(points, 0.02), expected)


def test_voxel_first_indices_at_the_edges_of_exact_integer_keys():
    # spans whose product of strides a float64 would round (2**27 + 1 and 2**27 + 5 voxels), and keys beyond 2**53
    wide = np.array([[0, 0, 0], [1, 0, 0], [0, 2 ** 27, 2 ** 27 + 4]], np.float64)   # codes 2**54 + 6 * 2**27 + 4
    huge = np.array([[-(2.0 ** 60), 0, 0], [0, 0, 0], [1, 0, 0]])
    for points in (wide, huge):
        keys = np.floor(points / 1.0)
        expected = np.sort(np.unique(keys, axis=0, return_index=True)[1])
        np.testing.assert_array_equal(voxel_first_indices(points, 1.0), expected)
    assert len(voxel_first_indices(huge, 1.0)) == 3 and len(voxel_first_indices(wide, 1.0)) == 3


def test_merge_refuses_bad_input():
    with pytest.raises(ValueError, match="cannot keep 100"):
        merge_measured(np.zeros((10, 3), np.float32), np.zeros((5, 3), np.float32), 100)
    broken = np.zeros((64, 3), np.float32)
    broken[5] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        merge_measured(broken, np.ones((10, 3), np.float32), 64)
    for weights in ({"network_weight": 0.0}, {"mirror_weight": 1.5}, {"network_weight": float("nan")}):
        with pytest.raises(ValueError, match="merge weights"):
            merge_measured(np.zeros((10, 3), np.float32), np.ones((5, 3), np.float32), 8, **weights)


def test_merge_takes_each_distinct_point_once():
    rng = np.random.default_rng(2)
    measured = rng.uniform(-0.3, 0.3, (30, 3)).astype(np.float32)
    completion = np.concatenate([np.tile(measured, (4, 1)), rng.uniform(-0.5, 0.5, (136, 3))]).astype(np.float32)
    merged = merge_measured(completion, measured, 150)           # 30 + 30 mirrored + 136 distinct: 196
    assert len(np.unique(merged.points, axis=0)) == 150
    merged = merge_measured(completion, measured, 256)           # more than the 196 distinct points
    assert len(np.unique(merged.points, axis=0)) == 196 and len(merged.points) == 256
    assert merged.is_measured.sum() == 30                        # each measured point once: repeats are the network's
    only_measured = merge_measured(measured, measured, 70)        # nothing new from the network: mirror repeated
    assert only_measured.is_measured.sum() == 30 and len(only_measured.points) == 70


def test_the_pool_takes_the_ground_band_and_indexes_it_after_the_partial():
    """Ground-band points (tyres the network is not fed) are pooled like measured points: kept where nothing else
    lies, their `measured_row` counting on after the partial's rows."""
    rng = np.random.default_rng(12)
    partial = (rng.random((600, 3)) * np.array([1.0, 0.02, 0.3]) + np.array([-0.5, 0.2, -0.1])).astype(np.float32)
    completion = (rng.random((2048, 3)) * np.array([1.0, 0.4, 0.3]) - np.array([0.5, 0.2, 0.1])).astype(np.float32)
    band = np.array([[0.3, 0.2, -0.16], [-0.3, 0.2, -0.16], [0.31, 0.19, -0.165]], np.float32)   # two tyres' bottoms
    merged = merge_with_pool(completion, partial, aside=band)
    from_band = merged.measured_row >= len(partial)
    assert from_band.sum() >= 2
    np.testing.assert_array_equal(merged.points[from_band], band[merged.measured_row[from_band] - len(partial)])
    kept = merged.measured_row[merged.is_measured & ~from_band]
    np.testing.assert_array_equal(merged.points[merged.is_measured & ~from_band], partial[kept])
    assert not (merge_with_pool(completion, partial).measured_row >= len(partial)).any()


SIZE = (4.5, 1.8, 1.5)   # a car's box (m): width 0.4 and height 1/3 of the length


def _side(offset: float, sign: float = 1.0, n: int = 400, seed: int = 0) -> np.ndarray:
    """A vehicle's flat side panel seen by the sensor on the `sign` side, its plane of symmetry `offset` across the
    box (normalised frame; the side lies SIDE_GAP off the box's side, as measured sides do)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.45, 0.45, n)
    z = rng.uniform(-0.08, 0.05, n)
    y = offset + sign * (SIZE[1] / SIZE[0] / 2 + SIDE_GAP)
    return np.stack([x, np.full(n, y), z], 1).astype(np.float32)


@pytest.mark.parametrize(("offset", "sign"), [(0.03, 1.0), (-0.025, 1.0), (0.035, -1.0), (-0.05, -1.0)])
def test_the_mirror_plane_is_found_from_the_seen_side_and_the_width(offset, sign):
    """A box off across the vehicle by `offset`: the seen side (either) and the box's width place the plane there;
    `share` takes that part of it."""
    side = _side(offset, sign)
    assert mirror_plane_offset(side, SIZE, share=1.0) == pytest.approx(offset, abs=1e-5)
    assert mirror_plane_offset(side, SIZE, share=0.5) == pytest.approx(offset / 2, abs=1e-5)


@pytest.mark.parametrize("offset", [0.0, 0.012, -0.018])
def test_the_mirror_plane_stays_for_a_move_within_the_estimates_error(offset):
    """An offset under PLANE_MIN_MOVE (a tight box's, or the estimate's own error) leaves the box's plane; just
    over it, the plane moves."""
    assert mirror_plane_offset(_side(offset), SIZE, share=1.0) == 0.0
    over = PLANE_MIN_MOVE + 0.002
    assert mirror_plane_offset(_side(over), SIZE, share=1.0) == pytest.approx(over, abs=1e-5)


@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_mirror_plane_moves_from_its_minimum_move_on(sign, side):
    """The boundary: an offset a hair under PLANE_MIN_MOVE keeps the box's plane, one a hair over moves it all the
    way (no share of it is lost to the threshold), either way across the box, whichever side was seen."""
    under, over = sign * (PLANE_MIN_MOVE - 2e-4), sign * (PLANE_MIN_MOVE + 2e-4)
    assert mirror_plane_offset(_side(under, side), SIZE, share=1.0) == 0.0
    assert mirror_plane_offset(_side(over, side), SIZE, share=1.0) == pytest.approx(over, abs=1e-5)
    assert mirror_plane_offset(_side(over, side), SIZE, share=0.5) == pytest.approx(over / 2, abs=1e-5)


def test_the_mirror_plane_stays_where_no_side_is_seen_clearly():
    """Both sides seen alike, too few points, no box size or a share of 0: the box's own plane (0); a far move is
    capped."""
    both = np.concatenate([_side(0.03, 1.0), _side(0.03, -1.0, seed=1)])
    assert mirror_plane_offset(both, SIZE, share=1.0) == 0.0
    assert mirror_plane_offset(_side(0.03, n=10), SIZE, share=1.0) == 0.0
    assert mirror_plane_offset(_side(0.03), None, share=1.0) == 0.0
    assert mirror_plane_offset(_side(0.03), SIZE, share=0.0) == 0.0
    rear = _side(0.03)
    rear[:, 0] = 0.48   # the rear face's edge only: nothing in the middle of the vehicle
    assert mirror_plane_offset(rear, SIZE, share=1.0) == 0.0
    assert mirror_plane_offset(_side(0.2), SIZE, share=1.0) == pytest.approx(PLANE_LIMIT)
    for size in ((0.0, 1.8, 1.5), (4.5, float("nan"), 1.5), (4.5, 1.8), (-4.5, 1.8, 1.5)):
        assert mirror_plane_offset(_side(0.03), size, share=1.0) == 0.0
    assert check_plane_share(0.5) == 0.5
    with pytest.raises(ValueError, match="mirror plane share"):
        check_plane_share(1.5)


def test_the_mirror_plane_reads_the_side_at_body_height_only():
    """Points above the body (a roof rack, a mirror's top) or below it (the sills, the road) farther out than the
    side do not move the plane: only body height counts (in box heights over the length)."""
    side = _side(0.03)
    rng = np.random.default_rng(5)
    outliers = np.stack([rng.uniform(-0.25, 0.25, 300), np.full(300, 0.3), rng.choice([-0.16, 0.1], 300)], 1)
    cloud = np.concatenate([side, outliers.astype(np.float32)])
    assert mirror_plane_offset(cloud, SIZE, share=1.0) == pytest.approx(0.03, abs=1e-5)


def test_the_merge_mirrors_about_the_plane_the_side_gives():
    """With the box's size the pooled mirror image lies about y = the found offset, not about the box's plane."""
    side = _side(0.04)
    completion = np.full((8, 3), 2.0, np.float32)
    offset = mirror_plane_offset(side, SIZE, share=1.0)
    assert offset != 0.0 and mirror_plane_offset(side, SIZE) == offset   # on by default (PLANE_SHARE 1)
    merged = merge_measured(completion, side, 2 * len(side) + 1, mirror_offset=offset)   # every distinct point
    mirror = ~merged.is_measured & (merged.points[:, 1] < 0)
    assert mirror.sum() == len(side)
    np.testing.assert_allclose(merged.points[mirror, 1], 2 * offset - side[0, 1], atol=1e-5)
    plain = merge_measured(completion, side, 2 * len(side) + 1)
    np.testing.assert_allclose(plain.points[~plain.is_measured & (plain.points[:, 1] < 0), 1], -side[0, 1], atol=1e-6)
    pool = side[voxel_first_indices(side, POOL_VOXEL)]
    np.testing.assert_array_equal(merge_with_pool(completion, side, size=SIZE, plane_share=1.0).points,
                                  merge_measured(completion, pool, mirror_offset=offset).points)
    np.testing.assert_array_equal(mirrored(side, 0.05)[:, 1], np.float32(0.1) - side[:, 1])
