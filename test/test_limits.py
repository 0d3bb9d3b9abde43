"""Per-frame limits: hostile boxes are screened and counted, the work of one frame is bounded."""
from __future__ import annotations

import threading
from collections import Counter

import numpy as np
import pytest

from gd_completion.geometry import Box3D
from gd_completion.limits import FrameLimits, implausible, screen_boxes
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.pipeline import VehicleCompleter

CAR = (4.5, 1.8, 1.5)


def car(x: float, y: float, iid: int, size: tuple[float, float, float] = CAR) -> Box3D:
    return Box3D((x, y, size[2] / 2), size, 0.0, "car", iid)


def car_points(box: Box3D, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    local = rng.uniform(-0.5, 0.5, (n, 3)) * box.size
    local[:, 1] = box.size[1] / 2          # one visible side, inside the box and above the ground cut
    local[:, 2] *= 0.8
    return (local + box.center).astype(np.float32)


@pytest.fixture(scope="module")
def model():
    return load_model(DEFAULT_WEIGHTS)


def test_implausible_sizes():
    limits = FrameLimits()
    assert not implausible(car(0, 0, 1), limits)
    assert not implausible(car(0, 0, 1, (18.0, 2.6, 4.0)), limits)            # an articulated truck
    assert implausible(car(0, 0, 1, (4500.0, 1800.0, 1500.0)), limits)        # millimetres
    assert implausible(car(0, 0, 1, (1e4, 1e4, 1e4)), limits)
    assert implausible(car(0, 0, 1, (0.2, 0.2, 0.2)), limits)
    assert implausible(car(0, 0, 1, (4.5, 7.0, 1.5)), limits)
    with pytest.raises(ValueError, match="positive"):
        FrameLimits(max_boxes=0)
    for bad in (float("nan"), -1.0, 0.0):
        with pytest.raises(ValueError, match="positive"):
            FrameLimits(time_budget_s=bad)
    with pytest.raises(ValueError, match="positive"):
        FrameLimits(max_box_length=float("inf"))      # only the time budget may be unlimited


def test_screen_duplicates_and_count_nearest_first():
    boxes = [car(30.0, 0.0, 1), car(10.0, 0.0, 2), car(10.1, 0.05, 3), car(20.0, 5.0, 4),
             car(0, 0, 5, (4500.0, 1800.0, 1500.0))] + [car(10.0, 0.0, 100 + i) for i in range(200)]
    kept, skipped = screen_boxes(boxes, FrameLimits(max_boxes=2))
    assert [boxes[i].instance_id for i in kept] == [2, 4]                     # nearest first
    assert Counter(reason for _, reason in skipped) == {"implausible_box": 1, "duplicate_box": 201,
                                                         "too_many_boxes": 1}
    assert (4, "implausible_box") in skipped and (0, "too_many_boxes") in skipped and (2, "duplicate_box") in skipped
    kept, skipped = screen_boxes(boxes, FrameLimits())
    assert [boxes[i].instance_id for i in kept] == [2, 4, 1]
    assert sorted(kept + [i for i, _ in skipped]) == list(range(len(boxes)))   # every box kept or skipped once
    assert screen_boxes([], FrameLimits()) == ([], [])


def test_hostile_frame_is_bounded_and_counted(model):
    boxes = [car(12.0, 4.0, 1), car(6.0, -3.0, 2)]
    points = np.concatenate([car_points(b, 400, i) for i, b in enumerate(boxes)])
    hostile = (boxes + [car(6.0, -3.0, 50 + i) for i in range(200)]                # duplicates
               + [car(0.0, 0.0, 90, (1e4, 1e4, 1e4)), car(0.0, 0.0, 91, (4500.0, 1800.0, 1500.0))])
    completer = VehicleCompleter(model)
    result = completer.complete_frame(points, hostile)
    assert result.stats.completed == 2
    assert result.stats.skipped == {"duplicate_box": 200, "implausible_box": 2}
    assert {box.instance_id for box, reason in result.stats.skipped_boxes if reason == "implausible_box"} == {90, 91}
    assert sorted(set(result.instance_id.tolist())) == [1, 2]
    generated = result.generated == 1             # the merge keeps some measured points; none is published twice
    assert 2 * (2048 - 400) <= generated.sum() < 2 * 2048 and len(result.points) == 800 + generated.sum()
    assert len(np.unique(result.points, axis=0)) == len(result.points)
    assert list(dict.fromkeys(result.instance_id.tolist())) == [1, 2]      # output in message order


def test_point_time_output_and_cancel_limits(model):
    boxes = [car(12.0, 4.0, 1), car(6.0, -3.0, 2), car(25.0, 8.0, 3)]
    points = np.concatenate([car_points(b, n, i) for i, (b, n) in enumerate(zip(boxes, (300, 3000, 300)))])
    crowded = VehicleCompleter(model, limits=FrameLimits(max_points_per_vehicle=1000)).complete_frame(points, boxes)
    assert crowded.stats.completed == 2 and crowded.stats.skipped == {"too_many_points": 1}
    capped = VehicleCompleter(model, limits=FrameLimits(max_output_points=3000 + 2048 + 10))
    result = capped.complete_frame(points, boxes)        # the nearest vehicle (3000 + 2048 points) only
    assert set(result.instance_id.tolist()) == {2} and result.stats.skipped == {"output_limit": 2}
    late = VehicleCompleter(model, limits=FrameLimits(time_budget_s=1e-9), threads=2)
    result = late.complete_frame(points, boxes)
    assert result.stats.completed == 0 and result.stats.skipped == {"time_budget": 3}
    late.close()
    stop = threading.Event()
    stop.set()
    result = VehicleCompleter(model).complete_frame(points, boxes, cancel=stop)
    assert result.stats.completed == 0 and result.stats.skipped == {"cancelled": 3}
    assert len(result.points) == 0


def test_offline_limits_have_no_time_budget(model):
    from gd_completion.limits import OFFLINE_LIMITS

    assert OFFLINE_LIMITS.time_budget_s == float("inf")
    assert OFFLINE_LIMITS.max_boxes == FrameLimits().max_boxes
    boxes = [car(12.0, 4.0, 1), car(6.0, -3.0, 2)]
    points = np.concatenate([car_points(b, 300, i) for i, b in enumerate(boxes)])
    result = VehicleCompleter(model, limits=OFFLINE_LIMITS).complete_frame(points, boxes)
    assert result.stats.completed == 2 and not result.stats.skipped
