"""The preprocessing contract: one network input for one cloud and box, whoever calls; stored in checkpoints."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gd_completion.errors import CheckpointError
from gd_completion.geometry import Box3D, normalize
from gd_completion.model import GGDNet
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint, load_model, save_checkpoint
from gd_completion.model.network import box_shape
from gd_completion.pipeline import FrameStats, VehicleCompleter
from gd_completion.preprocess import Preprocessing, crop_vehicles, footprint_band, network_input
from gd_completion.sampling import resample_indices


class Recording(torch.nn.Module):
    """A GGDNet that keeps every input it is given."""

    def __init__(self, model: GGDNet) -> None:
        super().__init__()
        self.model = model
        self.config = model.config
        self.inputs: list[torch.Tensor] = []
        self.shapes: list[torch.Tensor | None] = []

    def forward(self, x: torch.Tensor, box_shape: torch.Tensor | None = None):
        self.inputs.append(x.detach().clone())
        self.shapes.append(None if box_shape is None else box_shape.detach().clone())
        return self.model(x, box_shape)


@pytest.fixture(scope="module")
def parked_car(shared_data) -> tuple[np.ndarray, Box3D]:
    """PandaSet-002 frame 0 (Pandar64 points, world frame) and the stationary car with the most points."""
    from gd_completion.datasets.pandaset import PandaSetSequence, world_box_to_sensor
    from gd_completion.evaluation.pandaset_eval import stationary_vehicles

    sequence = PandaSetSequence(shared_data / "pandaset-002")
    cars = {uuid for uuid, label in stationary_vehicles(sequence).items() if label == "Car"}
    arrays = sequence.load_lidar(0)
    points = arrays["xyz"][arrays["sensor"] == 0].astype(np.float32)
    boxes = [world_box_to_sensor(r, np.eye(3), np.zeros(3), sequence.track_ids[str(r["uuid"])])
             for r in sequence.cuboids(0) if str(r.get("uuid")) in cars]
    vehicles, _ = crop_vehicles(points, boxes, Preprocessing())
    best = max(vehicles, key=lambda v: len(v.measured))
    assert 200 < len(best.measured) < 5000        # more than the network's 1024 after cropping: FPS runs
    return points, best.box


def test_every_caller_feeds_the_network_the_same_input(parked_car):
    """The node and `complete` (VehicleCompleter), training-data generation and the evaluation give the
    network bitwise the same input for the same cloud and box."""
    from gd_completion.evaluation.baselines import network_outputs
    from gd_completion.synth.dataset import network_partial

    points, box = parked_car
    model = Recording(load_model(DEFAULT_WEIGHTS))
    n = model.config.num_input
    completion = VehicleCompleter(model).complete_frame(points, [box])         # node and `complete`
    assert completion.stats.completed == 1
    pipeline_input = model.inputs[-1][0].numpy()
    pipeline_shape = model.shapes[-1]
    torch.testing.assert_close(pipeline_shape, box_shape([box.size]), rtol=0, atol=0)
    training_input, kept = network_partial(points, box, Preprocessing(), n)    # training-data generation
    np.testing.assert_array_equal(training_input, pipeline_input)
    network_outputs(model, [crop_vehicles(points, [box], Preprocessing())[0][0].normalized], [box.size])  # evaluation
    np.testing.assert_array_equal(model.inputs[-1][0].numpy(), pipeline_input)
    torch.testing.assert_close(model.shapes[-1], pipeline_shape, rtol=0, atol=0)
    assert pipeline_input.shape == (n, 3) and kept > n


def test_pandaset_evaluation_crops_through_the_contract(shared_data, parked_car):
    from gd_completion.datasets.pandaset import PandaSetSequence
    from gd_completion.evaluation.pandaset_eval import collect_tracks, stationary_vehicles

    points, box = parked_car
    sequence = PandaSetSequence(shared_data / "pandaset-002")
    uuid = next(u for u, iid in sequence.track_ids.items() if iid == box.instance_id)
    track = collect_tracks(sequence, {uuid: stationary_vehicles(sequence)[uuid]}, Preprocessing(), frames=[0])[uuid]
    vehicles, _ = crop_vehicles(points, [box], Preprocessing())
    np.testing.assert_array_equal(track.points[0], vehicles[0].normalized)


def test_contract_steps_on_hand_made_points():
    box = Box3D((10.0, 0.0, 0.75), (4.0, 2.0, 1.5), 0.0, "car", 3)
    inside = np.array([[10.0, 0.0, 1.0], [11.9, 0.9, 1.4], [8.1, -0.9, 0.2]], np.float32)
    ground = np.array([[10.0, 0.5, 0.05]], np.float32)          # within 0.1 m of the box floor
    margin = np.array([[12.05, 0.0, 1.0]], np.float32)          # 5 cm past the front face
    points = np.concatenate([inside, ground, margin])
    vehicles, too_few = crop_vehicles(points, [box], Preprocessing(crop_margin=0.1, min_points=4))
    assert len(vehicles) == 1 and too_few == []
    np.testing.assert_array_equal(vehicles[0].measured, np.concatenate([inside, margin]))
    np.testing.assert_allclose(vehicles[0].normalized[0], [0.0, 0.0, 0.25 / 4.0])
    vehicles, too_few = crop_vehicles(points, [box], Preprocessing(crop_margin=0.0, min_points=4))
    assert vehicles == [] and too_few == [box]                  # the margin point is gone: 3 < 4
    vehicles, _ = crop_vehicles(points, [box], Preprocessing(ground_clearance=0.0, min_points=1))
    assert len(vehicles[0].measured) == 5                       # no ground cut: the low point stays
    np.testing.assert_array_equal(resample_indices(3, inside, 7), [0, 1, 2, 0, 1, 2, 0])
    big = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    assert len(set(resample_indices(50, big, 20).tolist())) == 20
    assert network_input(big, 20).shape == (20, 3)
    with pytest.raises(ValueError, match="empty"):
        network_input(np.zeros((0, 3), np.float32), 20)


def test_preprocessing_values_are_checked():
    assert Preprocessing.from_dict(None) == Preprocessing() == Preprocessing(0.1, 0.1, 20)
    assert Preprocessing.from_dict(Preprocessing(0.2, 0.0, 5).to_dict()) == Preprocessing(0.2, 0.0, 5)
    with pytest.raises(ValueError, match="unknown preprocessing keys"):
        Preprocessing.from_dict({"crop_margin": 0.1, "voxel": 0.05})
    for bad in ({"crop_margin": -0.5}, {"crop_margin": float("nan")}, {"ground_clearance": 3.0}, {"min_points": 0}):
        with pytest.raises(ValueError):
            Preprocessing(**bad)


def test_checkpoint_preprocessing_round_trips_and_is_applied(tmp_path):
    model = load_model(DEFAULT_WEIGHTS)
    custom = Preprocessing(crop_margin=0.5, ground_clearance=0.0, min_points=5)
    path = save_checkpoint(tmp_path / "custom.pt", model, custom)
    loaded_model, loaded = load_checkpoint(path)
    assert loaded == custom and loaded_model.config == model.config
    completer = VehicleCompleter.from_checkpoint(path, num_threads=1)
    assert completer.preprocessing == custom
    box = Box3D((0.0, 0.0, 0.75), (4.0, 2.0, 1.5), 0.0, "car", 1)
    rng = np.random.default_rng(2)
    near = (rng.uniform(-0.5, 0.5, (8, 3)) * [4.0, 2.0, 1.5] + [0.0, 0.0, 0.75]).astype(np.float32)
    outside = np.array([[2.3, 0.0, 0.8], [-2.3, 0.2, 0.9]], np.float32)    # 0.3 m past the faces
    points = np.concatenate([near, outside])
    applied = completer.prepare(points, [box], FrameStats())
    assert len(applied) == 1 and len(applied[0].measured) == 10        # margin 0.5 and min_points 5 applied
    default = VehicleCompleter(model).prepare(points, [box], FrameStats())
    assert default == []                                                 # 8 points < 20 with the defaults
    overridden = VehicleCompleter.from_checkpoint(path, num_threads=1, crop_margin=0.1)
    assert overridden.preprocessing == Preprocessing(0.1, 0.0, 5)


def test_checkpoint_without_preprocessing_gets_todays_values(tmp_path):
    data = torch.load(DEFAULT_WEIGHTS, weights_only=True)
    data.pop("preprocessing", None)
    torch.save(data, tmp_path / "old.pt")
    assert load_checkpoint(tmp_path / "old.pt")[1] == Preprocessing(crop_margin=0.1, ground_clearance=0.1,
                                                                    min_points=20)
    data["preprocessing"] = {"crop_margin": "wide"}
    torch.save(data, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="invalid preprocessing"):
        load_checkpoint(tmp_path / "bad.pt")


def test_training_data_records_its_preprocessing():
    from gd_completion.synth.dataset import build_dataset

    prep = Preprocessing(crop_margin=0.2, ground_clearance=0.05, min_points=30)
    data = build_dataset(2, seed=3, n_input=64, n_gt=64, preprocessing=prep)
    assert data["metadata"]["preprocessing"] == prep.to_dict()
    assert (data["n_points"] >= 30).all()


def test_the_ground_band_in_the_footprint_is_kept_aside_not_fed():
    """The ground cut's points inside the box's own footprint (tyres, wheel arches) are kept as the vehicle's band;
    those in the crop margin or below the box floor (road) are not, and none of them is in the network's points."""
    box = Box3D((10.0, 0.0, 0.75), (4.0, 2.0, 1.5), 0.0, "car", 3)
    body = np.array([[10.0, 1.0, 1.0], [11.9, 0.9, 1.4], [8.1, -0.9, 0.2], [9.0, 1.0, 0.6]], np.float32)
    tyres = np.array([[11.3, 0.95, 0.05], [8.7, -0.95, 0.02]], np.float32)   # in the band, inside the footprint
    road = np.array([[12.05, 0.0, 0.05], [10.0, 1.06, 0.03], [10.0, 0.0, -0.05]], np.float32)  # margin, below floor
    vehicles, _ = crop_vehicles(np.concatenate([body, tyres, road]), [box], Preprocessing(min_points=4))
    (vehicle,) = vehicles
    np.testing.assert_array_equal(vehicle.measured, body)
    np.testing.assert_allclose(vehicle.band, normalize(tyres, box), atol=1e-6)
    assert footprint_band(normalize(tyres, box), box, 0.1).all()
    assert not footprint_band(normalize(road, box), box, 0.1).any()
    assert not footprint_band(normalize(body, box), box, 0.1).any()


def test_the_surround_within_the_pool_margin_is_kept_aside_not_fed():
    """With a pool margin wider than the crop's, the points above the ground between the two margins (a vehicle's end
    that a loose box cuts off) are kept aside as its surround: not among the network's points, not the ground's and
    not those beyond the pool margin; with no wider pool margin there is none, and an unusable margin is refused."""
    box = Box3D((10.0, 0.0, 0.75), (4.0, 2.0, 1.5), 0.0, "car", 3)
    body = np.array([[10.0, 1.0, 1.0], [11.9, 0.9, 1.4], [8.1, -0.9, 0.2], [12.08, 0.0, 0.6]], np.float32)
    cut_off = np.array([[12.3, 0.2, 0.7], [12.35, -0.3, 1.1], [10.0, -1.35, 0.9]], np.float32)   # 0.1-0.4 m past
    ground = np.array([[12.3, 0.0, 0.05]], np.float32)        # between the margins, in the ground band: road
    beyond = np.array([[12.6, 0.0, 0.8], [10.0, 1.5, 0.8]], np.float32)   # past the pool margin
    points = np.concatenate([body, cut_off, ground, beyond])
    (vehicle,), _ = crop_vehicles(points, [box], Preprocessing(min_points=4), pool_margin=0.4)
    np.testing.assert_array_equal(vehicle.measured, body)
    np.testing.assert_allclose(vehicle.surround, normalize(cut_off, box), atol=1e-6)
    np.testing.assert_allclose(vehicle.aside, normalize(cut_off, box), atol=1e-6)   # no band here
    for margin in (0.0, 0.1):   # not wider than the crop's: the crop alone
        (plain,), _ = crop_vehicles(points, [box], Preprocessing(min_points=4), pool_margin=margin)
        np.testing.assert_array_equal(plain.measured, body)
        assert plain.surround.shape == (0, 3)
    for bad in (-0.1, math.nan, 6.0):
        with pytest.raises(ValueError, match="pool_margin"):
            crop_vehicles(points, [box], Preprocessing(min_points=4), pool_margin=bad)


def test_a_neighbours_points_are_never_kept_aside_as_this_vehicles():
    """Two cars 0.3 m apart: a point in one car's crop is never the other's surround, and a point in the gap, in
    neither crop, is kept aside once, by the car it lies nearer to."""
    front = Box3D((10.0, 0.0, 0.75), (4.0, 2.0, 1.5), 0.0, "car", 1)    # x 8 .. 12
    behind = Box3D((14.3, 0.0, 0.75), (4.0, 2.0, 1.5), 0.0, "car", 2)   # x 12.3 .. 16.3
    bodies = np.array([[9.0, 0.5, 1.0], [11.95, 0.0, 0.8], [12.35, 0.1, 0.8], [15.0, -0.5, 1.0]], np.float32)
    gap = np.array([[12.13, 0.0, 0.9], [12.17, 0.0, 0.9]], np.float32)   # 0.13 / 0.17 m from the front car
    vehicles, _ = crop_vehicles(np.concatenate([bodies, gap]), [front, behind], Preprocessing(min_points=1),
                                pool_margin=0.4)
    first, second = vehicles
    np.testing.assert_allclose(first.surround, normalize(gap[:1], front), atol=1e-6)    # nearer the front car
    np.testing.assert_allclose(second.surround, normalize(gap[1:], behind), atol=1e-6)  # nearer the car behind
    assert len(first.measured) == 2 and len(second.measured) == 2   # each body point once, in its own crop
