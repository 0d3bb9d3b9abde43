"""Samples from a labelled real drive: the refiner's true frame against the synthetic pairs' convention, the
completion pairs' references in the frame of the box used, PandaSet-002's moving vehicles only (the evaluation's
parked ones never), whole vehicles held out, recipes checked before any data."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from gd_completion.drive_frames import (
    DRIVE_REFERENCE_POINTS,
    DriveFrames,
    DrivePairs,
    DriveSettings,
    drive_frames,
    drive_pairs,
    moving_vehicles,
    pair_reference,
    track_reference,
    true_frame,
)
from gd_completion.errors import DataFormatError
from gd_completion.evaluation.nearest import nearest_sq
from gd_completion.evaluation.pandaset_eval import BAND_SIDE_ZONE, PandaSetSequence, VehicleTrack, stationary_vehicles
from gd_completion.geometry import Box3D, normalize
from gd_completion.model.box_refiner import BoxFrame, frame_targets, to_frame
from gd_completion.tools.train_refiner import read_recipe
from gd_completion.train_refiner import FrameData


def test_true_frame_is_the_synthetic_pairs_target_and_maps_the_noisy_crop_onto_the_true_box():
    rng = np.random.default_rng(3)
    for _ in range(20):
        centre, yaw = rng.uniform(-20, 20, 3), rng.uniform(-math.pi, math.pi)
        true_size = rng.uniform([3.5, 1.6, 1.3], [6.0, 2.2, 2.5])
        noise = np.concatenate([rng.normal(0, 0.3, 3), np.exp(rng.normal(0, 0.08, 3)), rng.normal(0, 0.1, 1)])
        true = Box3D(tuple(centre), tuple(true_size), yaw, "car", 1)
        used = Box3D(tuple(centre + noise[:3]), tuple(true_size * noise[3:6]), yaw + noise[6], "car", 1)
        target = true_frame(true, used)
        expected = frame_targets(noise[None], np.array([yaw]), (true_size * noise[3:6])[None], true_size[None])[0]
        np.testing.assert_allclose(target, expected, atol=1e-5)
        points = centre + rng.uniform(-1.5, 1.5, (200, 3))
        placed = to_frame(torch.from_numpy(normalize(points, used))[None],
                          BoxFrame.from_vector(torch.from_numpy(target)[None]))[0].numpy()
        np.testing.assert_allclose(placed, normalize(points, true), atol=1e-4)
    # headings either side of +-pi: the offset is the short way round
    across = true_frame(Box3D((0.0, 0.0, 0.0), (4.0, 2.0, 1.5), 3.1), Box3D((0.0, 0.0, 0.0), (4.0, 2.0, 1.5), -3.1))
    assert across[3] == pytest.approx(6.2 - 2 * math.pi, abs=1e-6)


FRAMES = range(0, 30)   # a part of the drive keeps the test light


@pytest.fixture(scope="module")
def drive(shared_data) -> DriveFrames:
    settings = DriveSettings(str(shared_data / "pandaset-002"), draws=2, sigma_scale=(1.0, 1.0), seed=11)
    return drive_frames(settings, frames=FRAMES)


def test_a_drive_gives_its_moving_vehicles_once_exact_and_once_per_draw(shared_data, drive):
    sequence = PandaSetSequence(shared_data / "pandaset-002")
    parked = {sequence.track_ids[u] for u in stationary_vehicles(sequence, (0, 1))}
    moving = {sequence.track_ids[u] for u in moving_vehicles(sequence)}
    assert moving and not moving & parked
    assert set(drive.track.tolist()) <= moving and not set(drive.track.tolist()) & parked
    exact = (drive.target == 0).all(1)
    assert drive.partial.shape[1:] == (512, 3) and np.isfinite(drive.partial).all()
    # two draws of every exact crop (a few fall below the point minimum): neither one draw nor exact crops twice
    assert 1.5 * exact.sum() < (~exact).sum() <= 2 * exact.sum()
    assert len(np.unique(drive.target[~exact], axis=0)) == (~exact).sum()   # the draws differ (their own seeds)
    offset = drive.target[~exact, :2] * drive.size[~exact, :1]          # metres, in the noisy box's axes
    assert np.sqrt((offset ** 2).mean()) == pytest.approx(0.15, rel=0.15)
    assert np.degrees(np.sqrt((drive.target[~exact, 3] ** 2).mean())) == pytest.approx(4.0, rel=0.15)
    train, val = drive.split(0.2, seed=0)
    assert len(train) + len(val) == len(drive) and not set(train.track.tolist()) & set(val.track.tolist())
    assert len(np.unique(val.track)) == round(0.2 * len(np.unique(drive.track)))
    data = FrameData.concat([FrameData.from_drive(train), FrameData.from_drive(val)])
    assert len(data) == len(drive) and torch.equal(data.target[:len(train)], torch.from_numpy(train.target))


def test_a_split_holds_out_whole_vehicles():
    track = np.repeat([4, 7, 9], [5, 3, 2])
    frames = DriveFrames(np.zeros((10, 8, 3), np.float32), np.ones((10, 3), np.float32), np.zeros((10, 7), np.float32),
                         track)
    train, val = frames.split(0.34, seed=1)
    assert len(np.unique(val.track)) == 1 and set(train.track.tolist()).isdisjoint(val.track.tolist())
    assert len(train) + len(val) == 10
    with pytest.raises(ValueError, match="val_share"):
        frames.split(1.0)
    with pytest.raises(DataFormatError, match="too few"):
        frames.subset(track == 4).split(0.5)


@pytest.mark.parametrize("drive_entry, message", [
    ({"draws": 2}, "needs pandaset"), ({"pandaset": "P", "bogus": 1}, r"unknown drive keys \['bogus'\]"),
    ({"pandaset": "P", "val_share": 1.5}, "val_share"), ({"pandaset": "P", "draws": -1}, "draws"),
    ({"pandaset": "P", "draws": 2.5}, "draws"), ({"pandaset": "P", "draws": True}, "draws"),
    ({"pandaset": "P", "sigma_scale": [1.4, 0.8]}, "sigma_scale"),
    ({"pandaset": "P", "sigma_scale": [1]}, "sigma_scale"),
    ({"pandaset": "P", "seed": 1.5}, "seed"), ({"pandaset": "absent"}, "lidar/"), ([], "object"),
    ({"pandaset": "P", "ground_band": True}, "ground_band applies to completion training only")])
def test_a_refiner_recipe_drive_is_checked_before_any_data(tmp_path, shared_data, drive_entry, message):
    """Every `drive` value is checked when the recipe is read, before any folder or data is made."""
    if isinstance(drive_entry, dict) and drive_entry.get("pandaset") == "P":
        drive_entry = {**drive_entry, "pandaset": str(shared_data / "pandaset-002")}
    recipe = tmp_path / "recipe.json"
    recipe.write_text(json.dumps({"base": "x.pt", "data": ["y.json"], "drive": drive_entry}))
    with pytest.raises(DataFormatError, match=f"recipe.json: drive: .*{message}"):
        read_recipe(recipe)
    good = {"base": "x.pt", "data": ["y.json"], "drive": {"pandaset": str(shared_data / "pandaset-002"), "draws": 2}}
    recipe.write_text(json.dumps(good))
    assert read_recipe(recipe)["drive"] == DriveSettings(str(shared_data / "pandaset-002"), draws=2)


@pytest.fixture(scope="module")
def pairs(shared_data) -> DrivePairs:
    return drive_pairs(DriveSettings(str(shared_data / "pandaset-002"), draws=1, sigma_scale=(1.0, 1.0), seed=11),
                       frames=FRAMES)


def test_drive_pairs_give_each_crop_its_vehicles_aggregate_in_the_frame_of_the_box_used(shared_data, pairs):
    """Completion pairs: moving vehicles seen in two frames or more, every exact crop with its track's one reference,
    every noisy crop with that reference taken into the noisy box's frame (its points sit on it there, not in the
    annotated box's frame)."""
    sequence = PandaSetSequence(shared_data / "pandaset-002")
    parked = {sequence.track_ids[u] for u in stationary_vehicles(sequence, (0, 1))}
    assert not set(pairs.track.tolist()) & parked and len(np.unique(pairs.track)) >= 5
    assert pairs.partial.shape[1:] == (512, 3) and pairs.reference.shape[1:] == (DRIVE_REFERENCE_POINTS, 3)
    own_exact, own_noisy, annotated_frame = [], [], []
    for track in np.unique(pairs.track):
        rows = np.flatnonzero(pairs.track == track)
        first = pairs.reference[rows[0]]   # the first pass starts with the annotated boxes
        for row in rows:
            fidelity = nearest_sq(pairs.partial[row], pairs.reference[row]).mean()
            if np.array_equal(pairs.reference[row], first):
                own_exact.append(fidelity)
            else:
                own_noisy.append(fidelity)
                annotated_frame.append(nearest_sq(pairs.partial[row], first).mean())
    assert 0.9 * len(own_exact) <= len(own_noisy) <= len(own_exact)   # one draw per exact crop, a few too sparse
    assert np.mean(own_exact) < 1.5e-4 and np.mean(own_noisy) < 0.5 * np.mean(annotated_frame)
    train, val = pairs.split(0.2, seed=0)
    assert len(train) + len(val) == len(pairs) and not set(train.track.tolist()) & set(val.track.tolist())


def test_drive_pairs_keep_the_ground_bands_sides_only_when_asked(shared_data):
    folder = str(shared_data / "pandaset-002")
    plain = drive_pairs(DriveSettings(folder, draws=0), frames=FRAMES, reference_points=512)
    band = drive_pairs(DriveSettings(folder, draws=0, ground_band=True), frames=FRAMES, reference_points=512)
    assert np.array_equal(plain.partial, band.partial) and plain.reference.shape == (len(plain), 512, 3)
    low = (-0.5 * plain.size[:, 2] + 0.1) / plain.size[:, 0]   # the ground cut, normalised
    assert not (plain.reference[..., 2] < low[:, None] - 1e-6).any()
    in_band = band.reference[..., 2] < low[:, None]
    assert in_band.mean() > 0.02
    side = np.abs(band.reference[..., 1]) * band.size[:, :1] >= band.size[:, 1:2] / 2 - BAND_SIDE_ZONE - 1e-5
    assert side[in_band].all()   # tyres, arches and sills: the road seen under the body is not vehicle
    with pytest.raises(ValueError, match="reference_points"):
        drive_pairs(DriveSettings(folder, draws=0), frames=FRAMES, reference_points=0)
    with pytest.raises(ValueError, match="ground_band"):
        DriveSettings(folder, ground_band="yes")


def test_a_track_reference_draws_each_point_once_before_repeating():
    aggregate = np.arange(30, dtype=np.float32).reshape(10, 3)
    many = track_reference(aggregate, 25, seed=1)
    assert many.shape == (25, 3) and {tuple(p) for p in many} == {tuple(p) for p in aggregate}
    few = track_reference(aggregate, 4, seed=1)
    assert len({tuple(p) for p in few}) == 4


@pytest.mark.parametrize("make", [drive_frames, drive_pairs])
def test_a_drive_picks_its_moving_vehicles_with_the_sensors_it_is_given(shared_data, monkeypatch, make):
    """Stationary for one sensor's cuboids is not stationary for another's: the sensors reach `moving_vehicles`."""
    import gd_completion.drive_frames as module

    asked = []

    def recorded(sequence, sensors=(0, 1)):
        asked.append(tuple(sensors))
        return {}   # no vehicle: the drive is refused right after

    monkeypatch.setattr(module, "moving_vehicles", recorded)
    with pytest.raises(DataFormatError, match="no moving vehicle"):
        make(DriveSettings(str(shared_data / "pandaset-002"), draws=0), sensors=(1,))
    assert asked == [(1,)]


def test_a_pair_reference_is_none_for_an_empty_aggregate():
    """A vehicle whose only points in its box are road under the body has no band-sides reference (skipped, not a
    crash), while its contract aggregate still gives one."""
    box = Box3D((0.0, 0.0, 0.75), (4.5, 1.8, 1.5), 0.0, "car", 3)
    road = np.array([[0.0, 0.0, -0.16], [0.05, 0.02, -0.165]], np.float32)   # the lowest 0.1 m, mid-footprint
    body = np.array([[0.1, 0.0, 0.1], [0.2, 0.1, 0.05]], np.float32)
    track = VehicleTrack("u", 3, "car", frames=[0, 1], boxes=[box, box], in_box=[road, road], reference=[body, body])
    assert pair_reference(track, True, 0.1, 16) is None
    reference = pair_reference(track, False, 0.1, 16)
    assert reference is not None and reference.shape == (16, 3) and set(map(tuple, reference)) == set(map(tuple, body))
