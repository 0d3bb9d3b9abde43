"""Completion pipeline: batching, skips, flags and the mapping back to the cloud frame."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gd_completion.geometry import Box3D, normalize
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.pipeline import LABEL_IDS, VehicleCompleter, completion_to_structured
from gd_completion.preprocess import Preprocessing
from gd_completion.sampling import resample_indices


def box_surface_points(box: Box3D, n: int, rng: np.random.Generator) -> np.ndarray:
    """Points on the two visible sides of a box (a crude partial scan) in the cloud frame."""
    length, width, height = box.size
    local = rng.uniform(-0.5, 0.5, (n, 3)) * [length, width, height]
    local[: n // 2, 1] = width / 2  # left side
    local[n // 2:, 0] = length / 2  # front
    cos, sin = math.cos(box.yaw), math.sin(box.yaw)
    world = local @ np.array([[cos, sin, 0], [-sin, cos, 0], [0, 0, 1]]) + box.center
    return world.astype(np.float32)


@pytest.fixture(scope="module")
def completer() -> VehicleCompleter:
    return VehicleCompleter(load_model(DEFAULT_WEIGHTS), preprocessing=Preprocessing(ground_clearance=0.0))


@pytest.fixture()
def scene() -> tuple[np.ndarray, list[Box3D]]:
    rng = np.random.default_rng(0)
    boxes = [
        Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7),
        Box3D((-6.0, -8.0, -0.5), (7.0, 2.4, 3.0), -1.2, "truck", 9),
        Box3D((20.0, -3.0, -0.9), (4.0, 1.8, 1.6), 0.0, "pedestrian", 11),
    ]
    clutter = rng.uniform(-40, 40, (5000, 3)).astype(np.float32)
    clutter[:, 2] = -1.7
    points = np.concatenate([box_surface_points(boxes[0], 3000, rng), box_surface_points(boxes[1], 400, rng),
                             box_surface_points(boxes[2], 500, rng), clutter])
    return points, boxes


def test_shipped_weights_exist() -> None:
    assert DEFAULT_WEIGHTS.is_file(), f"shipped checkpoint missing: {DEFAULT_WEIGHTS}"


def test_completes_vehicles_in_their_boxes(completer: VehicleCompleter, scene) -> None:
    points, boxes = scene
    result = completer.complete_frame(points, boxes)
    assert result.stats.completed == 2
    assert result.stats.ignored_labels == 1
    assert set(np.unique(result.instance_id)) == {7, 9}
    for box in boxes[:2]:
        rows = result.instance_id == box.instance_id
        assert set(np.unique(result.label[rows])) == {LABEL_IDS[box.label]}
        generated = result.points[rows & (result.generated == 1)]
        # the measured merge keeps measured points from a pool of the whole crop; they are published once, as measured
        assert 0 < len(generated) < completer.num_output
        local = normalize(generated, box) * box.size[0]
        inside = np.all(np.abs(local) <= np.array(box.size) / 2 + 0.5, axis=1)
        assert inside.mean() > 0.9, f"only {inside.mean():.0%} of completed points near box {box.instance_id}"
        measured = result.points[rows & (result.generated == 0)]
        assert len(measured) > 0
    car = (result.instance_id == 7) & (result.generated == 0)
    assert car.sum() > completer.num_input   # 3,000 points seen: more of them kept than the network was fed
    structured = completion_to_structured(result)
    assert structured.dtype.names == ("x", "y", "z", "instance_id", "label", "generated")
    np.testing.assert_array_equal(structured["x"], result.points[:, 0])


def test_batched_equals_single(completer: VehicleCompleter, scene) -> None:
    points, boxes = scene
    both = completer.complete_frame(points, boxes[:2])
    first = completer.complete_frame(points, boxes[:1])
    rows = both.instance_id == 7
    np.testing.assert_allclose(both.points[rows], first.points, atol=1e-4)


def test_skips_are_counted_not_raised(completer: VehicleCompleter, scene) -> None:
    points, boxes = scene
    bad_points = points.copy()
    bad_points[:10] = np.nan
    bad_points[10:15, 1] = np.inf
    degenerate = [Box3D((1.0, 1.0, 0.0), (0.0, 1.0, 1.0), 0.0, "car", 1),
                  Box3D((math.nan, 1.0, 0.0), (4.0, 1.0, 1.0), 0.0, "car", 2),
                  Box3D((30.0, 30.0, 0.0), (4.0, 2.0, 1.5), 0.0, "car", 3)]
    result = completer.complete_frame(bad_points, degenerate + boxes[:1])
    assert result.stats.nonfinite_points == 15
    assert result.stats.skipped["degenerate_box"] == 2
    assert result.stats.skipped["too_few_points"] == 1
    assert result.stats.completed == 1
    assert np.isfinite(result.points).all()


def test_empty_inputs(completer: VehicleCompleter) -> None:
    result = completer.complete_frame(np.zeros((0, 3), np.float32), [])
    assert result.points.shape == (0, 3) and result.stats.completed == 0


def test_resample_indices_down_and_up() -> None:
    rng = np.random.default_rng(1)
    big, small = rng.normal(size=(3000, 3)).astype(np.float32), rng.normal(size=(5, 3)).astype(np.float32)
    assert len(np.unique(resample_indices(3000, big, 1024))) == 1024  # FPS picks distinct points
    np.testing.assert_array_equal(resample_indices(5, small, 1024), np.arange(1024) % 5)


def test_box_sizes_reach_the_network(completer: VehicleCompleter, scene) -> None:
    """The shipped model is box-conditioned: the box sizes change its output, a missing or mismatched size
    list is a clear error, never a silent completion without the box."""
    assert completer.model.config.box_conditioning
    partial = (np.random.default_rng(3).random((300, 3), dtype=np.float32) - 0.5) * np.array([1, 0.4, 0.3], np.float32)
    narrow = completer.complete_normalized([partial], [(4.5, 1.8, 1.5)])
    wide = completer.complete_normalized([partial], [(4.5, 2.3, 1.9)])
    assert narrow.shape == (1, completer.num_output, 3) and not np.array_equal(narrow, wide)
    with pytest.raises(ValueError, match="box sizes"):
        completer.complete_normalized([partial, partial], [(4.5, 1.8, 1.5)])
    with pytest.raises(ValueError, match="box-conditioned"):
        completer.complete_normalized([partial])


@pytest.mark.parametrize(("include", "merge", "fusion", "fused_points"), [
    (True, True, False, False), (True, False, False, False), (False, True, False, False), (False, False, False, False),
    (True, True, True, False), (True, True, True, True), (False, True, True, False), (False, True, True, True),
    (True, False, True, False), (True, False, True, True), (False, False, True, False), (False, False, True, True),
])
def test_output_flags_over_every_combination(completer: VehicleCompleter, include, merge, fusion, fused_points) -> None:
    """One table over include_input_points x measured_merge x track fusion x publish_fused_points: a car seen from its
    left side, then from its front; the second frame's output holds the right points with the right flags."""
    from gd_completion.fusion import TrackFusion

    rng = np.random.default_rng(4)
    box = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    both = box_surface_points(box, 1600, rng)
    frames = [both[:800], both[800:]]            # the left side, then the front
    engine = VehicleCompleter(completer.model, preprocessing=Preprocessing(ground_clearance=0.0),
                              include_input_points=include, measured_merge=merge,
                              fusion=TrackFusion() if fusion else None, publish_fused_points=fused_points)
    for k, points in enumerate(frames):
        result = engine.complete_frame(points, [box], stamp_ns=(k + 1) * 100_000_000)
    n_out = engine.num_output
    measured = result.points[result.generated == 0]
    completion = result.points[result.generated == 1]
    expected = np.concatenate(frames) if fusion and fused_points else frames[1]   # what counts as measured
    if include:
        assert len(measured) >= len(frames[1]) if fusion and fused_points else len(measured) == len(frames[1])
        assert 0 < len(completion) < n_out if merge else len(completion) == n_out
    else:
        assert len(result.points) == n_out
        assert (len(measured) > 0) == merge       # without the merge nothing of the output is a measurement
    # every point flagged measured is a measured point (of this frame, or of the track with fused points)
    gap = np.sqrt(((measured[:, None, :] - expected[None]) ** 2).sum(-1)).min(1) if len(measured) else np.zeros(0)
    assert (gap < 0.05).all()   # the fused points pass through the track's frame (voxels, mean placement): cm
    if fusion and not fused_points and merge and not include:
        # the completion's points from the earlier frame (the left side) are not this frame's: generated=1
        left = normalize(frames[0], box)
        near_left = np.sqrt(((normalize(completion, box)[:, None] - left[None]) ** 2).sum(-1)).min(1) < 1e-3
        assert near_left.any()


def test_refined_boxes_come_out_with_the_published_ids(completer: VehicleCompleter, shared_data) -> None:
    """Each completed vehicle's refined box (the box refiner's estimate of the true box) comes out with its id and
    label; on KITTI cars whose boxes are shifted 0.3 m along and turned 0.1 rad it lies nearer the annotated box
    than the shifted box does."""
    from kitti_frames import read_frame as read_kitti

    from gd_completion.model.box_refiner import box_from_frame

    training = shared_data / "kitti-object-sample" / "training"
    shifted_error, refined_error = [], []
    for index in ("000001", "000003", "000004"):
        frame = read_kitti(training, index)
        truth = {b.instance_id: b for b in frame.boxes}
        moved = [Box3D((b.center[0] + 0.3 * math.cos(b.yaw), b.center[1] + 0.3 * math.sin(b.yaw), b.center[2]),
                       b.size, b.yaw + 0.1, b.label, b.instance_id) for b in frame.boxes]
        result = completer.complete_frame(frame.points[:, :3], moved)
        assert [b.instance_id for b in result.boxes] == sorted(set(result.instance_id.tolist()),
                                                               key=result.instance_id.tolist().index)
        for box in result.boxes:
            given = next(b for b in moved if b.instance_id == box.instance_id)
            assert box.label == given.label and box != given
            shifted_error.append(math.dist(given.center, truth[box.instance_id].center))
            refined_error.append(math.dist(box.center, truth[box.instance_id].center))
    assert len(refined_error) >= 3
    assert np.mean(refined_error) < np.mean(shifted_error)
    # the frame vector's convention: zero is the given box, and a shift of one box length moves the centre by it
    box = Box3D((1.0, 2.0, 0.5), (4.0, 1.8, 1.5), math.pi / 2, "car", 7)
    assert box_from_frame(box, np.zeros(7)) == Box3D((1.0, 2.0, 0.5), (4.0, 1.8, 1.5), math.pi / 2, "car", 7)
    moved_box = box_from_frame(box, np.array([0.25, 0.0, 0.0, 0.1, math.log(1.1), 0.0, 0.0]))
    assert np.allclose(moved_box.center, (1.0, 3.0, 0.5)) and math.isclose(moved_box.yaw, math.pi / 2 + 0.1)
    assert math.isclose(moved_box.size[0], 4.4) and moved_box.instance_id == 7


def car_with_tyres(box: Box3D, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(the body of a car's left side above the ground cut, its two left tyres' bottoms in the lowest 0.1 m of the
    box, inside its footprint), in the cloud frame."""
    side = box_surface_points(box, 1200, rng)[:600]
    side = side[normalize(side, box)[:, 2] * box.size[0] > -box.size[2] / 2 + 0.15]
    along = np.concatenate([rng.uniform(-0.3, 0.3, (40, 1)) + x for x in (1.4, -1.4)])
    local = np.concatenate([along, np.full((80, 1), box.size[1] / 2 - 0.05), rng.uniform(0.01, 0.08, (80, 1))], 1)
    cos, sin = math.cos(box.yaw), math.sin(box.yaw)
    tyres = (local - [0, 0, box.size[2] / 2]) @ np.array([[cos, sin, 0], [-sin, cos, 0], [0, 0, 1]]) + box.center
    return side, tyres.astype(np.float32)


def in_band(points: np.ndarray, box: Box3D) -> np.ndarray:
    """Bool: points in the box's lowest 0.1 m."""
    return normalize(points, box)[:, 2] * box.size[0] < -box.size[2] / 2 + 0.1 - 1e-4


@pytest.mark.parametrize(("include", "merge"), [(True, True), (False, True), (True, False)])
def test_tyres_below_the_ground_cut_are_published_as_measured_points(completer: VehicleCompleter, include,
                                                                    merge) -> None:
    """A car's left side and its tyres' bottoms (in the lowest 0.1 m, which the network is not fed): with the
    measured merge the tyre points come out as they were measured (generated=0, once each); without it, not at
    all, as before."""
    box = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    side, tyres = car_with_tyres(box, np.random.default_rng(21))
    engine = VehicleCompleter(completer.model, include_input_points=include, measured_merge=merge)
    result = engine.complete_frame(np.concatenate([side, tyres]), [box])
    low = in_band(result.points, box)
    gap = np.sqrt(((result.points[low][:, None] - tyres[None]) ** 2).sum(-1)).min(1) if low.any() else np.zeros(0)
    as_measured = low & (result.generated == 0)
    if merge:
        assert as_measured.sum() >= 10                                # tyre points, as measured
        assert (gap[(result.generated == 0)[low]] < 1e-4).all()
        assert len(np.unique(result.points[as_measured], axis=0)) == as_measured.sum()
        assert len(result.points[result.generated == 0]) >= len(side) * include + as_measured.sum()
    else:
        assert not as_measured.any()


def test_points_kept_aside_must_match_the_partials(completer: VehicleCompleter) -> None:
    """A list of the points kept aside (ground band, surround) that does not match the partial clouds is refused with
    one clear error, not zipped short (a vehicle silently completed without its band, or dropped)."""
    from gd_completion.evaluation.baselines import published_outputs

    partial = np.random.default_rng(0).random((300, 3)).astype(np.float32) - 0.5
    with pytest.raises(ValueError, match="1 partial clouds but 0 sets of points kept aside"):
        completer.complete_normalized([partial], [(4.5, 1.8, 1.5)], asides=[])
    with pytest.raises(ValueError, match="1 partial clouds but 2 sets of points kept aside"):
        published_outputs(completer.model, [partial], [(4.5, 1.8, 1.5)], asides=[partial[:3], partial[:3]])


def test_even_spacing_is_the_same_in_the_pipeline_and_the_evaluation() -> None:
    from gd_completion.evaluation.baselines import network_forward, published_outputs
    from gd_completion.spacing import even_spacing

    model = load_model(DEFAULT_WEIGHTS)
    rng = np.random.default_rng(3)
    boxes = [Box3D((0.0, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car", 1), Box3D((0.0, 0.0, 0.0), (6.0, 2.2, 2.6), 0.0,
                                                                          "truck", 2)]
    partials = [normalize(box_surface_points(b, n, rng), b).astype(np.float32) for b, n in zip(boxes, (700, 300))]
    sizes = [b.size for b in boxes]
    _, raw, graph = network_forward(model, partials, np.array(sizes))
    spaced = even_spacing(raw, graph=graph)
    unmerged = VehicleCompleter(model, measured_merge=False)
    np.testing.assert_array_equal(unmerged.complete_normalized(partials, sizes), spaced)
    unmerged.even_spacing = False   # the node's live parameter
    np.testing.assert_array_equal(unmerged.complete_normalized(partials, sizes), raw)
    evaluated = published_outputs(model, partials, np.array(sizes))
    np.testing.assert_array_equal(evaluated.raw, raw)
    np.testing.assert_array_equal(evaluated.completion, spaced)
    merged = VehicleCompleter(model).complete_normalized(partials, sizes)
    np.testing.assert_array_equal(merged, evaluated.published)
    unspaced = published_outputs(model, partials, np.array(sizes), spacing=None)   # the evaluation with it off
    np.testing.assert_array_equal(unspaced.completion, raw)
    unmerged.measured_merge, unmerged.even_spacing = True, False
    np.testing.assert_array_equal(unmerged.complete_normalized(partials, sizes), unspaced.published)
    # spacing moves the network's points: their nearest-neighbour spacing is more even than the raw P_o's
    variation = [(lambda d: d.std() / d.mean())(cKDTree(c).query(c, 2)[0][:, 1]) for c in (raw[0], spaced[0])]
    assert variation[1] < 0.9 * variation[0], variation


@pytest.mark.parametrize("pool_margin", [0.4, 0.0])
def test_a_loose_box_keeps_the_end_it_cuts_off_within_the_pool_margin(completer: VehicleCompleter,
                                                                      pool_margin: float) -> None:
    """A car whose box is 0.25 m short of its front: the front's points beyond the crop margin are published as they
    were measured (generated=0, once each) with a pool margin of 0.4 m, and none of them without one; the points
    fed to the network and published as its measured points stay the crop's."""
    car = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    heading = np.array([math.cos(car.yaw), math.sin(car.yaw), 0.0])
    loose = Box3D(tuple(np.array(car.center) - 0.125 * heading), (4.25, 1.8, 1.5), car.yaw, "car", 7)
    points = box_surface_points(car, 3000, np.random.default_rng(5))
    points = points[normalize(points, car)[:, 2] * car.size[0] > -car.size[2] / 2 + 0.15]   # above the ground cut
    past = normalize(points, loose)[:, 0] * loose.size[0] > loose.size[0] / 2 + 0.1   # beyond the loose crop's end
    assert past.sum() >= 20
    engine = VehicleCompleter(completer.model, pool_margin=pool_margin)
    result = engine.complete_frame(points, [loose])
    measured = result.points[result.generated == 0]
    gap = cKDTree(points[past]).query(measured)[0]
    on_the_end = measured[gap < 1e-4]
    if pool_margin:
        assert len(on_the_end) >= 10 and len(np.unique(on_the_end, axis=0)) == len(on_the_end)
    else:
        assert not len(on_the_end)
    assert not (cKDTree(points[past]).query(result.points[result.generated == 1])[0] < 1e-6).any()
    for bad in (-0.1, math.nan):   # refused when the completer is built, not on every frame
        with pytest.raises(ValueError, match="pool_margin"):
            VehicleCompleter(completer.model, pool_margin=bad)
