"""Track identity and completion reuse: the association (PandaSet with its ids hidden), reuse decisions, a cached
completion placed by a moved box, and the frame budget's scheduler."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from test_pipeline import box_surface_points, car_with_tyres, in_band

from gd_completion.association import AssociationSettings, BoxAssociator, track_identity
from gd_completion.geometry import Box3D, normalize
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.pipeline import VehicleCompleter
from gd_completion.preprocess import Preprocessing
from gd_completion.reuse import CompletionCache, ReuseSettings

SECOND = 1_000_000_000


# -- association ---------------------------------------------------------------------------------------

def test_association_follows_moving_and_parked_boxes_and_starts_new_tracks() -> None:
    associator = BoxAssociator()
    ids = []
    for k in range(6):
        boxes = [Box3D((10.0 + 1.2 * k, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car"),     # 12 m/s along x
                 Box3D((5.0, 8.0, 0.0), (4.4, 1.8, 1.5), 0.0, "car"),                 # parked
                 Box3D((5.0, 8.0 + 6.0, 0.0), (10.0, 2.5, 3.5), 0.0, "truck")]       # parked truck beside it
        if k >= 3:
            boxes.append(Box3D((-20.0, -5.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car"))     # appears at frame 3
        ids.append([b.instance_id for b in associator.assign(k * SECOND // 10, boxes)])
    assert len({row[0] for row in ids}) == len({row[1] for row in ids}) == len({row[2] for row in ids}) == 1
    assert len({ids[0][0], ids[0][1], ids[0][2]}) == 3
    assert ids[3][3] not in ids[0] and len({row[3] for row in ids[3:]}) == 1
    assert associator.counters["association_started"] == 4


def test_association_gates_label_size_and_distance() -> None:
    associator = BoxAssociator(AssociationSettings(max_distance=1.0))
    first = associator.assign(0, [Box3D((0.0, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car")])[0].instance_id
    later = [Box3D((0.1, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "truck"),   # another label
             Box3D((0.0, 0.1, 0.0), (9.0, 2.5, 3.5), 0.0, "car"),     # twice the size
             Box3D((4.0, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car")]     # beyond 1 m + a quarter of its length
    assert first not in [b.instance_id for b in associator.assign(SECOND // 10, later)]


def test_association_restarts_when_time_goes_back_and_modes() -> None:
    associator = BoxAssociator()
    box = Box3D((0.0, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car", 77)
    a = associator.assign(5 * SECOND, [box])[0].instance_id
    b = associator.assign(1 * SECOND, [box])[0].instance_id
    assert a != b
    assert track_identity("message", [box], 0, associator)[0].instance_id == 77
    assert track_identity("off", [box], 0, associator)[0].instance_id == -1
    with pytest.raises(ValueError, match="track id mode"):
        track_identity("tracker", [box], 0, associator)


def test_unknown_track_id_modes_are_refused(model) -> None:
    from gd_completion.ros.params import PARAMETERS, ParameterError, validate

    with pytest.raises(ValueError, match="track_ids='tracker' must be one of"):
        VehicleCompleter(model, track_ids="tracker")
    values = {name: default for name, (default, _, _) in PARAMETERS.items()}
    with pytest.raises(ParameterError, match="parameter track_ids='uuid' must be one of"):
        validate({**values, "track_ids": "uuid"})
    assert validate(values).settings.reuse is not None
    assert validate({**values, "reuse": False}).settings.reuse is None


def test_association_agrees_with_pandaset_ids_hidden(shared_data) -> None:
    from gd_completion.evaluation.association_eval import association_agreement

    result = association_agreement(shared_data / "pandaset-002")
    assert result.frames == 76 and result.boxes > 2500
    assert result.kept >= 0.97, result
    assert result.wrong <= 0.01, result
    assert result.purity >= 0.95, result


# -- reuse decisions -----------------------------------------------------------------------------------

def _side(n: int = 400, seed: int = 0) -> np.ndarray:
    """Normalised points of a car's left side (length 1 = 4.5 m)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.5, 0.5, (n, 3)) * [1.0, 0.4, 0.33]
    pts[:, 1] = 0.2
    return pts.astype(np.float32)


def test_reuse_decisions() -> None:
    size = (4.5, 1.8, 1.5)
    cache = CompletionCache(ReuseSettings(new_points=0.25, distance=0.2, size_change=0.05, max_age_s=1.0))
    first = cache.decide(1, 0, size, _side())
    assert first.due and first.reason == "none" and first.cached is None
    cache.store(1, 0, size, np.zeros((8, 3), np.float32), np.zeros(8, bool), _side())
    again = cache.decide(1, SECOND // 10, size, _side(seed=1))   # the same side sampled anew
    assert not again.due and again.cached is not None and again.urgency < 1
    front = _side(seed=2)
    front[:, 0], front[:, 1] = 0.5, front[:, 1] * 0 + np.linspace(-0.2, 0.2, len(front))   # the front: not seen
    assert cache.decide(1, SECOND // 10, size, np.concatenate([_side(seed=3), front])).reason == "new_points"
    assert cache.decide(1, SECOND // 10, (4.9, 1.8, 1.5), _side(seed=1)).reason == "size"
    assert cache.decide(1, 2 * SECOND, size, _side(seed=1)).reason == "age"


def test_reuse_cache_expires_and_resets() -> None:
    cache = CompletionCache(ReuseSettings(expiry_s=1.0, max_tracks=2))
    for key in (1, 2, 3):
        cache.store(key, 0, (4.5, 1.8, 1.5), np.zeros((4, 3), np.float32), np.zeros(4, bool), _side())
    assert len(cache) == 2                      # the least recently used dropped
    assert cache.expire(SECOND // 2) == 0
    assert cache.expire(2 * SECOND) == 2        # unseen for more than expiry_s
    cache.store(4, 3 * SECOND, (4.5, 1.8, 1.5), np.zeros((4, 3), np.float32), np.zeros(4, bool), _side())
    assert cache.expire(SECOND) == 1 and len(cache) == 0   # time went back: a replay restarted


def test_reuse_settings_refuse_bad_values() -> None:
    for bad in ({"new_points": 0.0}, {"new_points": 1.5}, {"distance": -1.0}, {"budget_s": 0.0},
                {"max_age_s": math.nan}, {"max_tracks": 1.5}):
        with pytest.raises(ValueError):
            ReuseSettings(**bad)


# -- the pipeline with reuse ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def model():
    return load_model(DEFAULT_WEIGHTS)


def _completer(model, **options) -> VehicleCompleter:
    return VehicleCompleter(model, preprocessing=Preprocessing(ground_clearance=0.0), **options)


def _moved(box: Box3D, points: np.ndarray, dx: float, dyaw: float) -> tuple[Box3D, np.ndarray]:
    """The box and its points moved rigidly: rotated by `dyaw` about the origin, then shifted by `dx` along x."""
    c, s = math.cos(dyaw), math.sin(dyaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    centre = rot @ np.asarray(box.center) + [dx, 0, 0]
    return replace(box, center=tuple(centre), yaw=box.yaw + dyaw), (points @ rot.T + [dx, 0, 0]).astype(np.float32)


def test_cached_completion_is_placed_by_the_moved_box(model) -> None:
    rng = np.random.default_rng(0)
    box = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    points = box_surface_points(box, 1500, rng)
    completer = _completer(model, reuse=ReuseSettings(max_age_s=10.0), track_ids="message")
    first = completer.complete_frame(points, [box], stamp_ns=SECOND)
    moved_box, moved_points = _moved(box, points, 0.8, 0.05)
    second = completer.complete_frame(moved_points, [moved_box], stamp_ns=SECOND + SECOND // 10)
    assert (first.stats.completions_run, first.stats.completions_reused) == (1, 0)
    assert (second.stats.completions_run, second.stats.completions_reused) == (0, 1)
    a, b = first.points[first.generated == 1], second.points[second.generated == 1]
    assert len(a) == len(b) > 1000
    np.testing.assert_allclose(normalize(a, box), normalize(b, moved_box), atol=1e-4)
    # beside it, this frame's measured points (generated=0), not the first frame's
    np.testing.assert_allclose(np.sort(second.points[second.generated == 0], axis=0), np.sort(moved_points, axis=0),
                               atol=1e-5)
    # without reuse the same frame is completed afresh
    fresh = _completer(model, track_ids="message").complete_frame(moved_points, [moved_box], stamp_ns=SECOND)
    assert fresh.stats.completions_run == 1 and fresh.stats.completions_reused == 0


def test_a_reused_completion_keeps_its_tyres(model) -> None:
    """The tyre points a fresh completion published as measured (the ground band, generated=0) come back with a
    reused completion, as generated=1 (that frame's tyres, not this one's), whatever the measured points do."""
    box = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    side, tyres = car_with_tyres(box, np.random.default_rng(5))
    frame = np.concatenate([side, tyres])
    completer = VehicleCompleter(model, reuse=ReuseSettings(max_age_s=10.0), track_ids="message")
    first = completer.complete_frame(frame, [box], stamp_ns=SECOND)
    second = completer.complete_frame(frame, [box], stamp_ns=SECOND + SECOND // 10)
    assert (second.stats.completions_run, second.stats.completions_reused) == (0, 1)
    kept = first.points[in_band(first.points, box) & (first.generated == 0)]
    assert len(kept) >= 10
    gap = np.sqrt(((kept[:, None] - second.points[None]) ** 2).sum(-1))
    assert (gap.min(1) < 1e-5).all()                                   # every tyre point is published again
    assert (second.generated[gap.argmin(1)] == 1).all()                # as a reused completion's point


def test_new_points_rerun_the_network(model) -> None:
    rng = np.random.default_rng(1)
    box = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    side = box_surface_points(box, 1500, rng)[:750]   # the left side only
    both = box_surface_points(box, 1500, rng)        # left side and front
    completer = _completer(model, reuse=ReuseSettings(max_age_s=10.0), track_ids="message")
    completer.complete_frame(side, [box], stamp_ns=SECOND)
    again = completer.complete_frame(both, [box], stamp_ns=SECOND + SECOND // 10)
    assert again.stats.completions_run == 1


def _street(n: int) -> tuple[np.ndarray, list[Box3D]]:
    rng = np.random.default_rng(2)
    boxes = [Box3D((8.0 + 6.0 * (k % 6), -12.0 + 8.0 * (k // 6), -0.9), (4.5, 1.8, 1.5), 0.1 * k, "car", 100 + k)
             for k in range(n)]
    return np.concatenate([box_surface_points(b, 300, rng) for b in boxes]), boxes


def test_scheduler_never_drops_a_known_vehicle_and_respects_the_budget(model) -> None:
    points, boxes = _street(12)
    completer = _completer(model, reuse=ReuseSettings(budget_s=1.0, max_age_s=0.25), track_ids="associate")
    completer._vehicle_seconds = 10.0   # one vehicle is expected to take 10 s: the 1 s budget admits only the first
    known: set[int] = set()
    for k in range(14):
        completer._vehicle_seconds = 10.0
        result = completer.complete_frame(points, boxes, stamp_ns=SECOND + k * SECOND // 10)
        stats = result.stats
        assert stats.completions_run == 1                   # the budget: the first due vehicle only
        present = {int(i) for i in np.unique(result.instance_id)}
        assert known <= present                             # every vehicle completed before is published
        assert stats.completed + stats.skipped["deferred"] == len(boxes)
        known = present
    assert len(known) == len(boxes)                         # never-completed ones came in, one per frame
    # the ages ran out (0.25 s): the due vehicles are re-completed in turn, the others still published from cache
    assert stats.completions_deferred > 0 and stats.completions_reused == len(boxes) - 1


def test_without_budget_every_due_vehicle_runs(model) -> None:
    points, boxes = _street(6)
    completer = _completer(model, reuse=ReuseSettings(), track_ids="associate")
    completer._vehicle_seconds = 10.0
    first = completer.complete_frame(points, boxes, stamp_ns=SECOND)
    second = completer.complete_frame(points, boxes, stamp_ns=SECOND + SECOND // 10)
    assert first.stats.completions_run == 6 and second.stats.completions_reused == 6
    assert len(first.points) == len(second.points)


def test_bad_boxes_are_skipped_before_the_association(model) -> None:
    """NaN and zero-size boxes beside a real car, with the association and reuse on: counted skips, the car still
    completed under its own id, and the association is never fed the bad boxes (no NaN in its cost matrix)."""
    rng = np.random.default_rng(3)
    car = Box3D((10.0, 3.0, -0.9), (4.5, 1.8, 1.5), 0.3, "car", 7)
    bad = [Box3D((math.nan, 0.0, 0.0), (4.5, 1.8, 1.5), 0.0, "car", 8),
           Box3D((5.0, 5.0, 0.0), (0.0, 1.8, 1.5), 0.0, "car", 9)]
    completer = _completer(model, reuse=ReuseSettings(), track_ids="associate")
    for k in range(3):
        result = completer.complete_frame(box_surface_points(car, 800, rng), [*bad, car], stamp_ns=k * SECOND // 10)
        assert result.stats.skipped["degenerate_box"] == 2
        assert set(np.unique(result.instance_id)) == {7}
    assert completer.associator.counters["association_started"] == 1
