"""Track fusion: a tracked vehicle's points from all of its frames, bounded per track and in tracks."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from test_preprocess import Recording

from gd_completion.fusion import FusionLimits, TrackFusion
from gd_completion.geometry import Box3D, normalize
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.pipeline import FrameStats, VehicleCompleter
from gd_completion.preprocess import CroppedVehicle, Preprocessing, crop_vehicles
from gd_completion.sampling import voxel_downsample

SIZE = (4.5, 1.8, 1.5)
SIDES = ("front", "left", "rear", "right", "top")
SECOND = 1_000_000_000


def side_points(side: str, spacing: float, offset: float) -> np.ndarray:
    """A grid of points (box frame, metres, `SIZE` box) on one side, `spacing` apart, shifted by `offset`."""
    half = np.array(SIZE) / 2
    axis = {"front": 0, "rear": 0, "left": 1, "right": 1, "top": 2}[side]
    sign = -1.0 if side in ("rear", "right") else 1.0
    free = [a for a in range(3) if a != axis]
    grids = [np.arange(-half[a] + 0.01 + offset, half[a] - 0.01, spacing) for a in free]
    u, v = np.meshgrid(*grids, indexing="ij")
    out = np.empty((u.size, 3))
    out[:, free[0]], out[:, free[1]], out[:, axis] = u.ravel(), v.ravel(), sign * half[axis]
    return out


def to_cloud(local: np.ndarray, box: Box3D) -> np.ndarray:
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    return (local @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + box.center).astype(np.float32)


def moving_track(frames: int = 10, spacing: float = 0.08, iid: int = 5) -> list[tuple[np.ndarray, Box3D]]:
    """A box-shaped car driving along a left-hand curve, each frame seeing another side: (points, box)."""
    rng = np.random.default_rng(1)
    out = []
    for k in range(frames):
        yaw = 0.15 * k
        box = Box3D((8.0 + 1.5 * k * math.cos(yaw), -3.0 + 1.5 * k * math.sin(yaw), -0.8), SIZE, yaw, "car", iid)
        local = side_points(SIDES[k % len(SIDES)], spacing, float(rng.uniform(0, spacing / 2)))
        out.append((to_cloud(local, box), box))
    return out


def vehicle(iid: int, metres: np.ndarray, size: tuple[float, float, float] = SIZE) -> CroppedVehicle:
    """A CroppedVehicle at the origin (yaw 0) from box-frame points in metres."""
    box = Box3D((0.0, 0.0, 0.0), size, 0.0, "car", iid)
    metres = np.asarray(metres, np.float32)
    return CroppedVehicle(box, metres, normalize(metres, box))


def distinct(n: int, start: float = 0.0) -> np.ndarray:
    """n points 5 cm apart along x (each its own 2 cm voxel)."""
    pts = np.zeros((n, 3), np.float32)
    pts[:, 0] = start + 0.05 * np.arange(n)
    return pts


def side_of(metres: np.ndarray) -> np.ndarray:
    """Index into SIDES of the side each box-frame point (metres) lies on."""
    half = np.array(SIZE) / 2
    on = np.isclose(metres, half, atol=1e-3), np.isclose(metres, -half, atol=1e-3)
    return np.select([on[0][:, 0], on[0][:, 1], on[1][:, 0], on[1][:, 1], on[0][:, 2]], range(5), -1)


def test_limits_are_validated() -> None:
    FusionLimits()
    FusionLimits(align=None)
    for bad in ({"max_tracks": 0}, {"max_points_per_track": -1}, {"voxel_size": math.nan},
                {"expiry_s": math.inf}, {"size_change": 0.0}, {"max_frames_per_track": 2.5}, {"align": True}):
        with pytest.raises(ValueError):
            FusionLimits(**bad)


def test_moving_vehicle_fuses_every_side() -> None:
    prep = Preprocessing(ground_clearance=0.0)
    fusion = TrackFusion(FusionLimits(align=None))   # the exact union (alignment: test_box_jitter_is_aligned)
    singles: list[np.ndarray] = []
    for k, (points, box) in enumerate(moving_track()):
        vehicles, too_few = crop_vehicles(points, [box], prep)
        assert not too_few and len(vehicles[0].measured) == len(points)
        singles.append(vehicles[0].normalized)
        (fused,) = fusion.update(k * SECOND // 10, vehicles)
        assert fused.box is box and fused.measured is vehicles[0].measured
        expected = np.concatenate(singles)                # union of every frame, oldest first
        np.testing.assert_allclose(fused.normalized, expected, rtol=0, atol=1e-6)
        assert fused.normalized.dtype == np.float32
    sides = set(side_of(fused.normalized * SIZE[0]))
    assert sides == set(range(5))                         # every visible side
    assert all(len(set(side_of(s * SIZE[0]))) == 1 for s in singles)
    # The fused points lie on the current (last) box in the cloud frame.
    cloud = fusion.fused_measured(fused)
    assert cloud.shape == fused.normalized.shape and cloud.dtype == np.float32
    local = normalize(cloud, box).astype(np.float64) * SIZE[0]
    assert np.all(np.abs(np.abs(local) / (np.array(SIZE) / 2)).max(axis=1) == pytest.approx(1.0, abs=1e-4))
    np.testing.assert_array_equal(side_of(local), side_of(fused.normalized * SIZE[0]))
    assert fusion.counters == {"tracks_alive": 1, "tracks_expired": 0, "tracks_reset": 0, "tracks_evicted": 0,
                               "frames_aligned": 0, "alignments_refused": 0}


def test_box_jitter_is_aligned() -> None:
    """A parked car seen from the same side in every frame, a fresh sampling each time, its box jittering by
    known shifts and turns: aligned, the frames coincide and the fused partial lies in the mean box placement;
    without alignment it is blurred by the jitter."""
    from test_registration import seen_part

    from gd_completion.evaluation.nearest import nearest_sq

    rng = np.random.default_rng(3)
    true_centre, true_yaw = np.array([12.0, 4.0, -0.8]), 0.4
    car = Box3D(tuple(true_centre), SIZE, true_yaw, "car", 9)
    jitter = np.column_stack([rng.normal(0, 0.04, (12, 2)), np.radians(rng.normal(0, 1.0, 12))])
    boxes = [replace(car, center=(true_centre[0] + dx, true_centre[1] + dy, true_centre[2]), yaw=true_yaw + dyaw)
             for dx, dy, dyaw in jitter]
    clouds = [to_cloud(seen_part(np.random.default_rng(10 + k), 800), car) for k in range(len(boxes))]
    mean_box = replace(car, center=tuple(np.mean([b.center for b in boxes], axis=0)),
                       yaw=float(np.mean([b.yaw for b in boxes])))
    truth = normalize(to_cloud(seen_part(np.random.default_rng(99), 200_000), car), mean_box) * SIZE[0]

    def blur(limits: FusionLimits) -> tuple[float, dict[str, int]]:
        fusion = TrackFusion(limits)
        for k, (cloud, box) in enumerate(zip(clouds, boxes)):
            (fused,) = fusion.update(k, [CroppedVehicle(box, cloud, normalize(cloud, box))])
        metres = fused.normalized.astype(np.float64) * SIZE[0]
        gap = np.sqrt(nearest_sq(metres, truth))
        return float(np.median(gap)), fusion.counters

    aligned, counters = blur(FusionLimits())
    plain, plain_counters = blur(FusionLimits(align=None))
    assert counters["frames_aligned"] == len(boxes) - 1 and counters["alignments_refused"] == 0
    assert plain_counters["frames_aligned"] == 0
    assert plain > 0.01 and aligned < 0.008 and aligned < plain / 2   # metres, median


def test_current_source_names_the_measured_rows_of_this_frame() -> None:
    """The fused partial's last rows are this frame's points after voxel thinning and the per-frame bound:
    `current_source` gives the row of `measured` each one came from."""
    fusion = TrackFusion(FusionLimits(align=None, max_points_per_track=30))
    first = np.concatenate([distinct(10), distinct(10, start=0.001)])      # second half: same voxels, dropped
    (v1,) = fusion.update(0, [vehicle(4, first)])
    np.testing.assert_array_equal(v1.current_source, np.arange(10))
    assert v1.current_rows == 10 and len(v1.normalized) == 10
    second = distinct(60, start=2.0)                                        # alone over the bound: thinned to 30
    (v2,) = fusion.update(1, [vehicle(4, second)])
    assert v2.current_rows == 30 and len(v2.normalized) == 30               # the first frame dropped
    np.testing.assert_allclose(v2.normalized[-30:] * SIZE[0], second[v2.current_source], atol=1e-5)
    assert v2.current_source[0] == 0 and v2.current_source[-1] == 59 and np.all(np.diff(v2.current_source) > 0)


def test_own_points_keep_their_measured_place_without_include_input_points() -> None:
    """Track fusion with alignment, include_input_points off: the completion's copies of this frame's points
    (generated=0) are published where this frame measured them, each the measured point it copies, not in the
    track's mean placement (a few centimetres off under box jitter)."""
    from test_registration import seen_part

    from gd_completion.geometry import denormalize
    from gd_completion.pipeline import FrameStats

    rng = np.random.default_rng(5)
    car = Box3D((12.0, 4.0, -0.8), SIZE, 0.4, "car", 9)
    completer = VehicleCompleter(load_model(DEFAULT_WEIGHTS), preprocessing=Preprocessing(ground_clearance=0.0),
                                 fusion=TrackFusion(), include_input_points=False)
    twin = TrackFusion()   # fed the same frames: the fused partial the completer saw
    for k in range(6):
        dx, dy, dyaw = *rng.normal(0, 0.05, 2), np.radians(rng.normal(0, 1.5))
        box = replace(car, center=(12.0 + dx, 4.0 + dy, -0.8), yaw=0.4 + dyaw)
        cloud = to_cloud(seen_part(np.random.default_rng(20 + k), 800), car)
        result = completer.complete_frame(cloud, [box], stamp_ns=k * SECOND // 10)
        (fused,) = twin.update(k * SECOND // 10, completer.prepare(cloud, [box], FrameStats()))
    assert completer.fusion.counters["frames_aligned"] >= 4
    completion, rows, _ = completer._complete_one(fused.normalized, box.size, True, fused.aside)
    aside = rows >= len(fused.normalized)   # this frame's points beside the crop (the pool margin), as measured
    own = (rows >= len(fused.normalized) - fused.current_rows) & ~aside
    assert own.sum() > 20 and (result.generated == 0).sum() == own.sum() + aside.sum()
    published = result.points[own].astype(np.float64)           # the completion's order, own rows in place
    copied = fused.measured[fused.current_source[rows[own] - (len(fused.normalized) - fused.current_rows)]]
    np.testing.assert_allclose(published, copied, atol=1e-4)    # each the very point it copies, as measured
    placed = denormalize(completion[own], box)                  # where the track's placement put them
    assert np.linalg.norm(placed - published, axis=1).max() > 0.005   # the jitter this corrects
    np.testing.assert_allclose(result.points[~own], denormalize(completion[~own], box), atol=1e-4)


def test_voxel_downsampling_keeps_first_point_per_voxel() -> None:
    pts = np.array([[0.001, 0, 0], [0.5, 0, 0], [0.015, 0.005, 0.0], [0.021, 0, 0], [0.51, 0, 0]], np.float32)
    np.testing.assert_array_equal(voxel_downsample(pts, 0.02), pts[[0, 1, 3]])
    assert voxel_downsample(np.zeros((0, 3), np.float32), 0.02).shape == (0, 3)
    (fused,) = TrackFusion().update(0, [vehicle(1, pts)])
    np.testing.assert_allclose(fused.normalized * SIZE[0], pts[[0, 1, 3]], atol=1e-6)
    # Frames are downsampled each on their own: the same points again are kept again.
    (fused,) = TrackFusion(FusionLimits(voxel_size=1.0)).update(0, [vehicle(1, pts)])
    assert len(fused.normalized) == 1


def test_points_bound_drops_oldest_frames() -> None:
    fusion = TrackFusion(FusionLimits(max_points_per_track=100))
    frames = [distinct(30, start=2.0 * k) for k in range(5)]
    for k, pts in enumerate(frames):
        (fused,) = fusion.update(k, [vehicle(1, pts)])
    # the last 3 frames, oldest first
    np.testing.assert_allclose(fused.normalized * SIZE[0], np.concatenate(frames[-3:]), atol=1e-6)
    # One frame alone over the bound is thinned evenly to it.
    (fused,) = fusion.update(10, [vehicle(2, distinct(250))])
    assert len(fused.normalized) == 100
    np.testing.assert_allclose(fused.normalized[[0, -1]] * SIZE[0], distinct(250)[[0, -1]], atol=1e-6)


def test_frames_bound_drops_oldest_frames() -> None:
    fusion = TrackFusion(FusionLimits(max_frames_per_track=3))
    frames = [distinct(4, start=2.0 * k) for k in range(6)]
    for k, pts in enumerate(frames):
        (fused,) = fusion.update(k, [vehicle(1, pts)])
        assert len(fused.normalized) == 4 * min(k + 1, 3)
    # the last 3 frames, oldest first
    np.testing.assert_allclose(fused.normalized * SIZE[0], np.concatenate(frames[-3:]), atol=1e-6)


def test_tracks_bound_evicts_least_recently_seen() -> None:
    fusion = TrackFusion(FusionLimits(max_tracks=2))
    fusion.update(0, [vehicle(1, distinct(3)), vehicle(2, distinct(3))])
    fusion.update(1, [vehicle(1, distinct(3, 1.0))])
    fusion.update(2, [vehicle(3, distinct(3))])            # 2 is the least recently seen
    assert fusion.counters["tracks_evicted"] == 1 and fusion.counters["tracks_alive"] == 2
    (again,) = fusion.update(3, [vehicle(2, distinct(5))])  # a fresh track; 1 (seen at 1) goes
    assert len(again.normalized) == 5
    (one,) = fusion.update(4, [vehicle(1, distinct(2))])
    assert len(one.normalized) == 2                          # 1 was evicted: fresh too
    assert fusion.counters == {"tracks_alive": 2, "tracks_expired": 0, "tracks_reset": 0, "tracks_evicted": 3,
                               "frames_aligned": 0, "alignments_refused": 1}   # 3 points: too few to align


def test_expiry_by_stamp() -> None:
    fusion = TrackFusion(FusionLimits(expiry_s=1.0))
    fusion.update(0, [vehicle(1, distinct(3))])
    fusion.update(SECOND // 2, [vehicle(2, distinct(3))])
    assert fusion.expire(SECOND) == 0                        # exactly expiry_s: still alive
    assert fusion.expire(12 * SECOND // 10) == 1
    assert fusion.counters["tracks_alive"] == 1 and fusion.counters["tracks_expired"] == 1
    # A stale track met again before `expire` ran starts afresh.
    (fused,) = fusion.update(3 * SECOND, [vehicle(2, distinct(4, 1.0))])
    assert len(fused.normalized) == 4 and fusion.counters["tracks_expired"] == 2
    # A stamp going back (a replay restarted) drops every track.
    (fused,) = fusion.update(SECOND, [vehicle(2, distinct(2))])
    assert len(fused.normalized) == 2 and fusion.counters["tracks_expired"] == 3


def test_size_jump_resets_track_small_change_keeps_metres() -> None:
    fusion = TrackFusion()
    old = distinct(3)
    fusion.update(0, [vehicle(1, old)])
    bigger = (SIZE[0] * 1.1, SIZE[1], SIZE[2])               # 10 %: the same vehicle, a refined box
    new = distinct(2, 1.0)
    (fused,) = fusion.update(1, [vehicle(1, new, bigger)])
    np.testing.assert_allclose(fused.normalized, np.concatenate([old, new]) / bigger[0], atol=1e-6)
    assert fusion.counters["tracks_reset"] == 0
    other = (bigger[0], bigger[1], bigger[2] * 1.3)          # 30 % taller: another object with the same id
    (fused,) = fusion.update(2, [vehicle(1, distinct(4, 2.0), other)])
    assert len(fused.normalized) == 4 and fusion.counters["tracks_reset"] == 1


def test_untracked_and_repeated_ids_pass_through() -> None:
    fusion = TrackFusion()
    a, b, c = vehicle(-1, distinct(3)), vehicle(4, distinct(3)), vehicle(4, distinct(5))
    out = fusion.update(0, [a, b, c])
    assert out[0] is a and out[2] is c and out[1] is not b
    assert fusion.counters["tracks_alive"] == 1
    np.testing.assert_array_equal(fusion.fused_measured(a), a.measured)




def test_pipeline_completes_a_track_from_its_fused_partial() -> None:
    model = Recording(load_model(DEFAULT_WEIGHTS))
    prep = Preprocessing(ground_clearance=0.0)
    fusion = TrackFusion()
    completer = VehicleCompleter(model, preprocessing=prep, fusion=fusion, publish_fused_points=True)
    plain = VehicleCompleter(model, preprocessing=prep)
    track = moving_track(frames=4, spacing=0.22)
    assert sum(len(p) for p, _ in track) < model.config.num_input   # inputs repeat points: unique = fused
    totals = []
    for k, (points, box) in enumerate(track):
        result = completer.complete_frame(points, [box], stamp_ns=k * SECOND // 10)
        assert result.stats.completed == 1
        seen = model.inputs[-1][0].numpy()
        totals.append(len(np.unique(seen, axis=0)))
        fused_cloud = result.points[result.generated == 0]
        assert len(fused_cloud) == totals[-1]
        local = normalize(fused_cloud, box).astype(np.float64) * SIZE[0]
        assert len(set(side_of(local))) == k + 1                      # the published points: every side so far
    assert totals == list(np.cumsum([len(p) for p, _ in track]))
    # Without a stamp, or without fusion, the frame is completed from its own points: the same bytes.
    points, box = track[-1]
    a, b = completer.complete_frame(points, [box]), plain.complete_frame(points, [box])
    for field in ("points", "instance_id", "label", "generated"):
        assert getattr(a, field).tobytes() == getattr(b, field).tobytes()
    assert fusion.counters["tracks_alive"] == 1


def test_untracked_and_tracked_vehicles_are_merged_with_their_measured_pool() -> None:
    """With fusion on, a vehicle without a track id is merged with a pool of its own crop, and a track with a pool
    of its fused partial (the same merge, `merge.merge_with_pool`); both keep more measured points than the network
    was fed."""
    from gd_completion.geometry import denormalize
    from gd_completion.merge import merge_with_pool

    model = load_model(DEFAULT_WEIGHTS)
    prep = Preprocessing(ground_clearance=0.0)
    points, box = moving_track(frames=1, spacing=0.05)[0]
    for iid, pooled in ((-1, False), (box.instance_id, True)):
        completer = VehicleCompleter(model, preprocessing=prep, fusion=TrackFusion(), include_input_points=False)
        tracked = replace(box, instance_id=iid)
        (own,) = completer.prepare(points, [tracked], FrameStats())
        assert len(own.measured) > model.config.num_input
        result = completer.complete_frame(points, [tracked], stamp_ns=SECOND)
        partial = own.normalized if not pooled else TrackFusion().update(SECOND, [own])[0].normalized
        network = completer._complete_one(partial, box.size, False)[0]
        merged = merge_with_pool(network, partial)
        assert merged.is_measured.sum() > model.config.num_input
        expected = denormalize(merged.points, box)
        if not pooled:
            np.testing.assert_allclose(result.points, expected, atol=1e-4)
        else:   # a track's own points are published where this frame measured them: compare the others
            generated = result.generated == 1
            np.testing.assert_allclose(result.points[generated], expected[generated], atol=1e-4)


@pytest.mark.parametrize("include", [True, False])
@pytest.mark.parametrize("fused_points", [True, False])
def test_merged_measured_points_are_published_once(include: bool, fused_points: bool) -> None:
    """Every setting of include_input_points x publish_fused_points with track fusion and the measured merge:
    no published point twice, the completion's points all published, generated=0 only for the points measured
    in this frame (or fused, when those are published)."""
    from gd_completion.geometry import denormalize
    from gd_completion.pipeline import FrameStats

    model = load_model(DEFAULT_WEIGHTS)
    prep = Preprocessing(ground_clearance=0.0)
    fusion = TrackFusion()
    completer = VehicleCompleter(model, preprocessing=prep, fusion=fusion, publish_fused_points=fused_points,
                                 include_input_points=include)
    twin = TrackFusion()   # fed the same frames: the fused partial the completer saw
    for k, (points, box) in enumerate(track := moving_track(frames=3, spacing=0.22)):
        result = completer.complete_frame(points, [box], stamp_ns=k * SECOND // 10)
        vehicle = twin.update(k * SECOND // 10, completer.prepare(points, [box], FrameStats()))[0]
    assert len(track) == 3 and len(np.unique(result.points, axis=0)) == len(result.points)
    # the completion of the last frame, recomputed from the same fused partial (the network is deterministic)
    completion, rows, _ = completer._complete_one(vehicle.normalized, box.size, True)
    own_from = 0 if fused_points else len(vehicle.normalized) - vehicle.current_rows   # this frame's: the last rows
    own = rows >= own_from
    expected = denormalize(completion, box).astype(np.float32)
    if not include and not fused_points:   # this frame's copies are published where it measured them
        expected[own] = vehicle.measured[vehicle.current_source[rows[own] - own_from]]
    nearest = np.min(np.linalg.norm(expected[:, None, :] - result.points[None, :, :], axis=-1), axis=1)
    assert nearest.max() < 1e-4                                 # every completion point is published
    measured_now = result.points[result.generated == 0]
    if include:
        reference = fusion.fused_measured(vehicle) if fused_points else vehicle.measured
        assert len(measured_now) == len(reference)             # the measured points, each once
    assert 0 < own.sum() and (fused_points or ((rows >= 0) & (rows < own_from)).any())   # both kinds occur
    if not include:
        assert len(result.points) == len(completion) and (result.generated == 0).sum() == own.sum()


def test_parallel_alignment_gives_the_same_tracks() -> None:
    """Aligning a frame's vehicles on a thread pool (the pipeline's vehicle threads) changes nothing: the same fused
    partials, current rows and counters as one after the other."""
    from concurrent.futures import ThreadPoolExecutor

    from test_registration import seen_part

    rng = np.random.default_rng(5)
    cars = [Box3D((10.0 + 7 * i, 4.0 - 3 * i, -0.8), SIZE, 0.3 * i, "car", 20 + i) for i in range(4)]
    frames = []
    for k in range(6):
        jittered = [replace(b, center=(b.center[0] + rng.normal(0, 0.04), b.center[1] + rng.normal(0, 0.04),
                                       b.center[2]), yaw=b.yaw + np.radians(rng.normal(0, 1.0))) for b in cars]
        clouds = [to_cloud(seen_part(np.random.default_rng(100 * k + i), 600), car) for i, car in enumerate(cars)]
        frames.append([CroppedVehicle(box, cloud, normalize(cloud, box)) for box, cloud in zip(jittered, clouds)])
    serial, parallel = TrackFusion(), TrackFusion()
    with ThreadPoolExecutor(2) as pool:
        for k, vehicles in enumerate(frames):
            a = serial.update(k, vehicles)
            b = parallel.update(k, vehicles, executor=pool)
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x.normalized, y.normalized)
                np.testing.assert_array_equal(x.current_source, y.current_source)
    assert serial.counters == parallel.counters and serial.counters["frames_aligned"] > 10


def test_a_track_pools_its_frames_ground_band_but_not_their_surround() -> None:
    """The fused vehicle keeps this frame's ground band (tyres: measured, pooled by the merge) but not the points beside
    its crop (the surround changes from frame to frame; the frames' own crops bring back what a box cuts off)."""
    band = np.array([[0.1, 0.2, -0.32]], np.float32)
    surround = np.array([[0.55, 0.0, 0.0], [0.56, 0.05, 0.1]], np.float32)
    frame = replace(vehicle(4, distinct(30)), band=band, surround=surround)
    assert len(frame.aside) == 3
    (fused,) = TrackFusion().update(0, [frame])
    np.testing.assert_array_equal(fused.band, band)
    assert fused.surround.shape == (0, 3) and len(fused.aside) == 1
