"""Generator version 2: sampling options, detector-box noise, mesh split, new kinds, patterns and sensor effects."""
from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from gd_completion.geometry import Box3D, denormalize, normalize
from gd_completion.synth.beams import PATTERN_NAMES, BeamPattern
from gd_completion.synth.dataset import V1_SAMPLING, V2_SAMPLING, SampleOptions, build_dataset, make_sample, sample_rng
from gd_completion.synth.meshio import HELDOUT_MESHES, sample_surface
from gd_completion.synth.vehicles import (
    BASE_KINDS,
    KIND_SIZE_RANGES,
    VEHICLE_KINDS,
    generate_vehicle,
    size_range,
    vehicle_label,
)


def digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


# Checksums of generator version 1 (commit b5d4935), taken before SampleOptions existed.
V1_PROCEDURAL = "0e4b1f7e46609316"  # build_dataset(4, seed=21, n_input=128, n_gt=256, patterns=PATS)
V1_MESHES = "32c59dec71f2c2ef"      # build_dataset(3, seed=2, meshes_dir=..., mesh_fraction=1, 128, 256)
PATS = ("pandar64", "hdl64e", "pandar40p")


def test_default_options_reproduce_version_1_bit_for_bit():
    data = build_dataset(4, seed=21, n_input=128, n_gt=256, patterns=PATS)
    assert digest(data["partial"], data["complete"], data["size"]) == V1_PROCEDURAL
    np.testing.assert_array_equal(data["size"], data["true_size"])
    assert np.all(data["box_noise"] == np.array([0, 0, 0, 1, 1, 1, 0], np.float32))
    assert data["metadata"]["sample_options"] == dict(V1_SAMPLING.to_dict(), patterns=list(PATS))
    again = build_dataset(4, seed=21, n_input=128, n_gt=256, options=SampleOptions(patterns=PATS))
    np.testing.assert_array_equal(again["partial"], data["partial"])


def test_version_1_mesh_samples_reachable(shared_data):
    data = build_dataset(3, seed=2, meshes_dir=shared_data / "vehicle-meshes", mesh_fraction=1.0, n_input=128,
                         n_gt=256, exclude_meshes=())
    assert digest(data["partial"], data["complete"]) == V1_MESHES


def test_options_round_trip_and_validation():
    for opts in (V1_SAMPLING, V2_SAMPLING):
        d = json.loads(json.dumps(opts.to_dict()))
        assert SampleOptions.from_dict(d) == opts
    assert V1_SAMPLING.kinds == BASE_KINDS and V1_SAMPLING.box_noise_prob == 0
    assert V2_SAMPLING.box_noise_prob > 0.5 and set(BASE_KINDS) < set(V2_SAMPLING.kinds)
    with pytest.raises(ValueError, match="kinds"):
        SampleOptions(kinds=("tank",))
    with pytest.raises(ValueError, match="beam pattern"):
        SampleOptions(patterns=("nope",))
    with pytest.raises(ValueError, match="box_noise_prob"):
        SampleOptions(box_noise_prob=1.5)
    with pytest.raises(ValueError, match="unknown fields"):
        SampleOptions.from_dict({"colour": "red"})


def _boxes(meta: dict) -> tuple[Box3D, Box3D]:
    """(true box, noisy box) of a sample from its meta."""
    true = np.asarray(meta["true_size"], np.float64)
    centre, yaw = np.asarray(meta["true_center"], np.float64), meta["yaw"]
    dist, az = meta["distance"], meta["azimuth"]
    if not np.any(meta["tilt"]):
        np.testing.assert_allclose(centre, [dist * np.cos(az), dist * np.sin(az), true[2] / 2], atol=1e-5)
    n = np.asarray(meta["box_noise"], np.float64)
    return (Box3D(tuple(centre), tuple(true), yaw), Box3D(tuple(centre + n[:3]), tuple(meta["size"]), yaw + n[6]))


def test_box_noise_normalises_partial_and_complete_by_the_same_noisy_box():
    opts = SampleOptions(box_noise_prob=1.0)
    partial, complete, meta = make_sample(sample_rng(3, 0), "suv", pattern="pandar64", n_input=256, n_gt=2048,
                                          options=opts)
    noise = meta["box_noise"]
    assert not np.allclose(noise, [0, 0, 0, 1, 1, 1, 0])
    np.testing.assert_allclose(meta["size"], meta["true_size"] * noise[3:6], rtol=1e-5)
    true_box, noisy_box = _boxes(meta)
    # complete, brought back with the noisy box and normalised by the true one, fills the true box exactly
    c_true = normalize(denormalize(complete, noisy_box), true_box)
    ext = np.asarray(meta["true_size"]) / meta["true_size"][0]
    assert np.all(c_true.max(0) <= ext / 2 + 1e-3) and np.all(c_true.min(0) >= -ext / 2 - 1e-3)
    np.testing.assert_allclose((c_true.max(0) - c_true.min(0))[[0, 2]], ext[[0, 2]], atol=0.02)
    # ... while in the noisy frame it is off by the noise
    shift = np.abs((complete.max(0) + complete.min(0)) / 2)
    assert shift.max() > 0.005 or abs(noise[6]) > 0.02
    # the partial lies on that surface in the same frame
    d = np.sqrt(((partial[:, None] - complete[None]) ** 2).sum(-1)).min(1) * meta["size"][0]
    assert np.median(d) < 0.06
    again = make_sample(sample_rng(3, 0), "suv", pattern="pandar64", n_input=256, n_gt=2048, options=opts)
    np.testing.assert_array_equal(again[0], partial)
    np.testing.assert_array_equal(again[2]["box_noise"], noise)


def test_box_noise_statistics():
    opts = SampleOptions(box_noise_prob=0.5)
    data = build_dataset(24, seed=4, n_input=64, n_gt=64, options=opts)
    noise = data["box_noise"]
    noisy = ~np.all(noise == np.array([0, 0, 0, 1, 1, 1, 0], np.float32), axis=1)
    assert 4 <= noisy.sum() <= 20
    np.testing.assert_allclose(data["size"], data["true_size"] * noise[:, 3:6], rtol=1e-5)
    assert np.abs(noise[noisy, :2]).max() < 0.8 and np.abs(noise[noisy, 2]).max() < 0.3
    assert np.abs(np.degrees(noise[noisy, 6])).max() < 20


def test_mesh_split(shared_data):
    from gd_completion.synth.dataset import _meshes

    folder = shared_data / "vehicle-meshes"
    n_all = len(_meshes(str(folder)))
    train = build_dataset(4, seed=2, meshes_dir=folder, mesh_fraction=1.0, n_input=64, n_gt=64)
    assert train["metadata"]["exclude_meshes"] == list(HELDOUT_MESHES)
    assert len(_meshes(str(folder), tuple(HELDOUT_MESHES))) == n_all - len(HELDOUT_MESHES)
    held = build_dataset(4, seed=2, meshes_dir=folder, mesh_fraction=1.0, n_input=64, n_gt=64,
                         only_meshes=HELDOUT_MESHES)
    assert held["metadata"]["only_meshes"] == list(HELDOUT_MESHES) and held["metadata"]["exclude_meshes"] == []
    assert all(int(k.split(":")[1]) < len(HELDOUT_MESHES) for k in held["kind"])
    # the held-out set's shapes are none of the training set's: compare the drawn meshes' vertex counts
    from gd_completion.synth.meshio import load_mesh_folder

    train_v = {len(m.vertices) for m in load_mesh_folder(folder, exclude=HELDOUT_MESHES)}
    held_v = {len(m.vertices) for m in load_mesh_folder(folder, only=HELDOUT_MESHES)}
    assert train_v.isdisjoint(held_v) or len(train_v | held_v) < n_all  # distinct files (sanity)
    from gd_completion.errors import DataFormatError

    with pytest.raises(DataFormatError, match="no meshes left"):
        build_dataset(1, seed=0, meshes_dir=folder, only_meshes=("no_such_mesh",))


def test_v2_preset_builds_and_is_recorded():
    data = build_dataset(6, seed=7, n_input=128, n_gt=256, options=V2_SAMPLING)
    assert data["partial"].shape == (6, 128, 3) and np.isfinite(data["complete"]).all()
    assert data["metadata"]["sample_options"] == V2_SAMPLING.to_dict()
    assert set(data["pattern"]) <= set(V2_SAMPLING.patterns)
    json.dumps(data["metadata"])


def test_wider_size_ranges():
    rng = np.random.default_rng(0)
    sizes = np.array([generate_vehicle(rng, "sedan", size_spread=0.15).extent for _ in range(40)])
    lo, hi = size_range("sedan", 0.15).T
    assert np.all(sizes >= lo - 1e-6) and np.all(sizes <= hi + 1e-6)
    (l0, l1), (w0, w1), (h0, h1) = KIND_SIZE_RANGES["sedan"]
    outside = (sizes[:, 1] < w0) | (sizes[:, 1] > w1) | (sizes[:, 2] < h0) | (sizes[:, 2] > h1)
    assert outside.sum() >= 10  # widths/heights a version-1 sedan never has
    with pytest.raises(ValueError):
        size_range("sedan", 1.5)


def test_hdl32e_pattern():
    assert "hdl32e" in PATTERN_NAMES
    p = BeamPattern.named("HDL-32E")
    e = np.array(p.elevations_deg)
    assert p.n_beams == 32 and e.max() == pytest.approx(10.67) and e.min() == pytest.approx(-30.67)
    np.testing.assert_allclose(-np.diff(e), 1.333, atol=0.01)
    assert p.horizontal_resolution_deg == 0.16


COMPOSITES = ("construction", "semi_trailer", "pickup_load", "trailer")


@pytest.mark.parametrize("kind", COMPOSITES)
@pytest.mark.parametrize("spread", [0.0, 0.15])
def test_composite_kinds_centred_in_range_and_closed(kind, spread):
    assert kind in VEHICLE_KINDS
    for seed in range(8):
        mesh = generate_vehicle(np.random.default_rng(seed), kind, size_spread=spread)
        lo, hi = mesh.bounds
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
        r = size_range(kind, spread)
        assert np.all(mesh.extent >= r[:, 0] - 1e-6) and np.all(mesh.extent <= r[:, 1] + 1e-6), (seed, mesh.extent)
        assert np.isfinite(mesh.vertices).all() and len(mesh.faces) >= 60
        assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
        # built of closed parts: every edge is shared by exactly two faces
        e = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, counts = np.unique(e, axis=0, return_counts=True)
        assert np.all(counts % 2 == 0)
    expected = {"construction": "truck", "semi_trailer": "truck", "pickup_load": "car", "trailer": "truck"}
    assert vehicle_label(kind) == expected[kind]


def test_construction_vehicle_is_low_and_heavy():
    """Most of its surface lies in the lower 65 % of the box, with a cab reaching the top at one end."""
    rng = np.random.default_rng(5)
    for seed in range(12):
        mesh = generate_vehicle(np.random.default_rng(seed), "construction")
        p = sample_surface(mesh, 4000, rng)
        z = (p[:, 2] - mesh.bounds[0, 2]) / mesh.extent[2]
        x = (p[:, 0] - mesh.bounds[0, 0]) / mesh.extent[0]
        assert (z < 0.65).mean() > 0.6, seed
        low = z < 0.5
        assert np.ptp(x[low]) > 0.8  # the low chassis / tracks / tool span most of the length
        top = z > 0.9
        assert top.any() and np.ptp(x[top]) < 0.6  # the cab (and maybe an arm), not a full-length roof


def test_pickup_load_carries_a_load_in_the_bed():
    rng = np.random.default_rng(1)
    higher = 0
    for seed in range(12):
        mesh = generate_vehicle(np.random.default_rng(seed), "pickup_load")
        p = sample_surface(mesh, 6000, rng)
        u = (p - mesh.bounds[0]) / mesh.extent
        bed = u[:, 0] < 0.38  # the bed: rear 40 % of the length
        assert (u[bed, 2] > 0.62).sum() > 30, seed  # something stands above the bed's sides
        higher += bool((u[bed, 2] > 0.97).any())  # the load is the highest part
    assert 1 <= higher <= 11


# --- patterns ------------------------------------------------------------------------------------------------


def _inside_box_scan(name: str, heading: float = 0.0):
    from gd_completion.synth.lidar import scan_meshes
    from gd_completion.synth.meshio import box_mesh

    room = box_mesh((80.0, 80.0, 60.0), (0.0, 0.0, 10.0))  # the sensor inside: every ray hits a wall
    scan = scan_meshes([room], (0.0, 0.0, 1.8), BeamPattern.named(name), np.random.default_rng(0), dropout=0.0,
                       range_noise_std=0.0, sensor_heading_deg=heading)
    d = scan.points - np.array([0.0, 0.0, 1.8], np.float32)
    el = np.degrees(np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1)))
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    return scan, el, az


@pytest.mark.parametrize("name,lo,hi,n", [("hdl32e", -30.67, 10.67, 32), ("vlp32c", -25.0, 15.0, 32),
                                          ("pandargt", -10.4, 9.6, 167)])
def test_new_patterns_elevations(name, lo, hi, n):
    assert name in PATTERN_NAMES
    p = BeamPattern.named(name)
    assert p.n_beams == n and min(p.elevations_deg) == pytest.approx(lo) and max(p.elevations_deg) == pytest.approx(hi)
    scan, el, _ = _inside_box_scan(name, heading=25.0)
    assert el.min() >= lo - 0.05 and el.max() <= hi + 0.05
    assert el.min() < lo + 0.2 and el.max() > hi - 0.2
    assert len(np.unique(scan.ring)) == n


def test_pandargt_fires_only_inside_its_field_of_view():
    p = BeamPattern.named("pandargt")
    assert p.fov_deg == 60.0 and p.horizontal_resolution_deg == 0.1
    np.testing.assert_allclose(-np.diff(p.elevations_deg), 0.12, atol=0.002)
    for heading in (25.0, 170.0, -100.0):
        scan, _, az = _inside_box_scan("pandargt", heading)
        rel = (az - heading + 180.0) % 360.0 - 180.0
        assert np.abs(rel).max() <= 30.0 + 0.1 and np.abs(rel).max() > 29.5
        assert len(scan.points) == pytest.approx(167 * 600, rel=0.01)
    from gd_completion.synth.lidar import intersect_arcs

    assert intersect_arcs((-10.0, 10.0), (0.0, 60.0)) == (0.0, 10.0)
    assert intersect_arcs((170.0, 190.0), (-185.0, -125.0)) == (175.0, 190.0)
    assert intersect_arcs((0.0, 10.0), (20.0, 80.0)) is None
    assert intersect_arcs((-180.0, 180.0), (20.0, 80.0)) == (20.0, 80.0)


def test_pandargt_sample_is_cut_by_its_field_of_view():
    opts = SampleOptions(patterns=("pandargt",))
    cut = 0
    for i in range(12):
        partial, complete, meta = make_sample(sample_rng(9, i), "sedan", n_input=256, n_gt=256, options=opts)
        assert meta["pattern"] == "pandargt"
        true_box, _ = _boxes(meta)
        world = denormalize(partial, true_box)
        rel = (np.degrees(np.arctan2(world[:, 1], world[:, 0])) - meta["sensor_heading"] + 180) % 360 - 180
        assert np.abs(rel).max() <= 30.1
        cut += np.abs(rel).max() > 29.0
    assert cut >= 1  # some vehicles stand at the edge of the field of view


# --- sensor effects ------------------------------------------------------------------------------------------


def test_mixed_pixels_fall_between_foreground_and_background():
    from gd_completion.synth.lidar import scan_meshes
    from gd_completion.synth.meshio import box_mesh

    front = box_mesh((1.0, 2.0, 4.0), (10.0, 0.0, 1.0))  # faces the sensor at 9.5 m
    wall = box_mesh((1.0, 30.0, 10.0), (20.5, 0.0, 2.0))  # at 20 m
    pattern = BeamPattern.named("hdl64e")

    def ranges(prob: float) -> np.ndarray:
        scan = scan_meshes([front, wall], (0.0, 0.0, 1.8), pattern, np.random.default_rng(1), dropout=0.0,
                           range_noise_std=0.0, azimuth_range=(-30.0, 30.0), mixed_pixel_prob=prob)
        return scan.points[:, 0]  # x: depth along the view

    clean, mixed = ranges(0.0), ranges(1.0)
    between = (mixed > 10.0) & (mixed < 19.5)
    assert not ((clean > 10.0) & (clean < 19.5)).any()
    assert between.sum() >= 20 and len(mixed) == len(clean)
    # only at the silhouette: the mixed points lie near the front box's side edges (y = +-1) or its top
    scan = scan_meshes([front, wall], (0.0, 0.0, 1.8), pattern, np.random.default_rng(1), dropout=0.0,
                       range_noise_std=0.0, azimuth_range=(-30.0, 30.0), mixed_pixel_prob=1.0)
    p = scan.points[between]
    ang = np.degrees(np.arctan2(np.abs(p[:, 1]), p[:, 0]))
    edge_ang = np.degrees(np.arctan2(1.0, 9.5))
    el = np.degrees(np.arctan2(p[:, 2] - 1.8, np.hypot(p[:, 0], p[:, 1])))
    top_el = np.degrees(np.arctan2(3.0 - 1.8, 9.5))
    near_edge = (np.abs(ang - edge_ang) < 0.6) | (np.abs(el - top_el) < 0.8)
    assert near_edge.all()


def test_tilted_ground_plane():
    from gd_completion.synth.lidar import scan_meshes

    n = np.array([0.03, -0.02, 1.0])
    n /= np.linalg.norm(n)
    sensor = np.array([0.0, 0.0, 1.8])
    scan = scan_meshes([], sensor, BeamPattern.named("pandar64"), np.random.default_rng(0), range_noise_std=0.0,
                       ground_plane=(n, float(n @ sensor) - 1.8), azimuth_range=(-20.0, 20.0))
    assert len(scan.points) > 1000 and np.all(scan.object_index == -1)
    np.testing.assert_allclose(scan.points @ n, float(n @ sensor) - 1.8, atol=1e-3)
    flat = scan_meshes([], sensor, BeamPattern.named("pandar64"), np.random.default_rng(0), range_noise_std=0.0,
                       ground_plane=((0.0, 0.0, 1.0), 0.0), azimuth_range=(-20.0, 20.0))
    old = scan_meshes([], sensor, BeamPattern.named("pandar64"), np.random.default_rng(0), range_noise_std=0.0,
                      ground_z=0.0, azimuth_range=(-20.0, 20.0))
    np.testing.assert_allclose(flat.points, old.points, atol=1e-4)


def test_sensor_effects():
    from gd_completion.synth.dataset import _sensor_effects

    rng = np.random.default_rng(0)
    sensor = np.array([0.0, 0.0, 1.8])
    # a 4 x 1.5 m car side at 10 m: points on x = 10, z in [0, 1.5]; ground points at z = 0
    car = np.stack([np.full(4000, 10.0), rng.uniform(-2, 2, 4000), rng.uniform(0, 1.5, 4000)], 1)
    ground = np.stack([rng.uniform(5, 60, 4000), rng.uniform(-5, 5, 4000), np.zeros(4000)], 1)
    pts = np.concatenate([car, ground]).astype(np.float32)
    obj = np.concatenate([np.zeros(4000, np.int32), -np.ones(4000, np.int32)])
    centre = np.array([10.0, 0.0, 0.75])

    def run(**kw):
        return _sensor_effects(pts, obj, sensor, centre, 1.5, True, np.random.default_rng(3), SampleOptions(**kw))

    np.testing.assert_array_equal(run(), pts)
    rough = run(ground_roughness=0.05)
    assert 0.04 < rough[4000:, 2].std() < 0.06 and np.array_equal(rough[:4000], pts[:4000])
    glass = run(glass_dropout=1.0, glass_passthrough=1.0)  # every glass return comes from behind the glass
    assert len(glass) == len(pts)
    moved = np.linalg.norm(glass - pts, axis=1) > 1e-4
    h = pts[moved, 2] / 1.5
    assert moved.sum() > 50 and h.min() > 0.5 and h.max() < 0.93
    extra = np.linalg.norm(glass[moved] - sensor, axis=1) - np.linalg.norm(pts[moved] - sensor, axis=1)
    assert extra.min() >= 0.2 - 1e-3 and extra.max() <= 1.5 + 1e-3
    lost = run(glass_dropout=1.0, glass_passthrough=0.0)
    assert len(pts) - len(lost) > 50 and (lost[:, 2] > 1.4).sum() == (pts[:, 2] > 1.4).sum()  # roof kept
    far = run(range_dropout=0.5)
    kept_g = far[far[:, 2] == 0]
    near_share = (kept_g[:, 0] < 20).sum() / (pts[4000:, 0] < 20).sum()
    far_share = (kept_g[:, 0] > 45).sum() / (pts[4000:, 0] > 45).sum()
    assert near_share > 0.9 and far_share < 0.8
    patch = run(patch_dropout=3.0)
    assert len(patch) < len(pts) and len(patch[patch[:, 2] == 0]) == 4000  # only the vehicle loses patches


def test_v2_preset_sample_is_deterministic_and_uses_every_effect():
    assert V2_SAMPLING.mixed_pixel_prob > 0 and V2_SAMPLING.glass_dropout > 0 and V2_SAMPLING.tilt_deg > 0
    assert V2_SAMPLING.range_dropout > 0 and V2_SAMPLING.patch_dropout > 0 and V2_SAMPLING.ground_roughness > 0
    assert {"pandargt", "hdl32e", "pandar64", "hdl64e"} <= set(V2_SAMPLING.patterns)
    a = make_sample(sample_rng(1, 3), n_input=128, n_gt=128, options=V2_SAMPLING)
    b = make_sample(sample_rng(1, 3), n_input=128, n_gt=128, options=V2_SAMPLING)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_tilted_sensor_sees_the_vehicle_on_the_tilted_ground():
    for i in range(3):
        partial, complete, meta = make_sample(sample_rng(1, i), "sedan", pattern="hdl64e", n_input=256, n_gt=4096,
                                              options=SampleOptions(tilt_deg=3.0))
        roll, pitch = np.radians(meta["tilt"])
        assert np.abs(meta["tilt"]).max() > 0.3
        cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
        rot = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        n = rot[:, 2]
        sensor = np.array([0.0, 0.0, meta["sensor_height"]])
        true_box, box = _boxes(meta)
        world = denormalize(complete, box)
        above = world @ n - (n @ sensor - meta["sensor_height"])  # height over the tilted ground
        assert abs(above.min()) < 0.02  # the wheels stand on it
        assert (world[:, 2] - world[:, 2].min()).max() > 1.2
        d = np.sqrt(((partial[:, None] - complete[None]) ** 2).sum(-1)).min(1) * meta["size"][0]
        assert np.median(d) < 0.06


def test_v2_workers_match_serial(shared_data):
    kw = dict(n_input=64, n_gt=64, options=V2_SAMPLING, meshes_dir=shared_data / "vehicle-meshes", mesh_fraction=0.5)
    serial = build_dataset(3, seed=5, workers=1, **kw)
    parallel = build_dataset(3, seed=5, workers=2, **kw)
    np.testing.assert_array_equal(serial["partial"], parallel["partial"])
    np.testing.assert_array_equal(serial["complete"], parallel["complete"])
    np.testing.assert_array_equal(serial["box_noise"], parallel["box_noise"])


def _beyond_box(partial: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Per point of a normalised partial, how far (m) it lies outside its box along x or y (0 inside)."""
    half = np.asarray(size, np.float64)[:2] / 2
    return (np.abs(partial[:, :2].astype(np.float64)) * size[0] - half).max(1).clip(min=0.0)


def test_crop_margin_max_draws_each_samples_margin_and_crops_with_it():
    opts = SampleOptions(box_noise_prob=1.0, box_center_sigma=0.3, crop_margin_max=0.5)
    margins, beyond = [], []
    for i in range(8):
        partial, _, meta = make_sample(sample_rng(5, i), "sedan", pattern="pandar64", n_input=512, n_gt=256,
                                       options=opts)
        margins.append(meta["crop_margin"])
        beyond.append(_beyond_box(partial, meta["size"]).max())
        assert beyond[-1] <= meta["crop_margin"] + 1e-4   # cropped with its own margin, not a wider one
    assert all(0.1 <= m <= 0.5 for m in margins) and np.ptp(margins) > 0.1
    assert max(beyond) > 0.1 + 1e-3                     # a wider crop let in what the contract's would drop
    # not above the contract's margin: the contract's crop, drawing nothing (off, 0, is the version-1 digests' case)
    plain = SampleOptions(box_noise_prob=1.0, box_center_sigma=0.3)
    a = make_sample(sample_rng(5, 0), "sedan", pattern="pandar64", n_input=128, n_gt=64,
                    options=dataclasses.replace(plain, crop_margin_max=0.1))
    b = make_sample(sample_rng(5, 0), "sedan", pattern="pandar64", n_input=128, n_gt=64, options=plain)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[2]["crop_margin"] == 0.1
    # off: absent from the dict the data sets' cache keys are made of, as before the option existed
    assert "crop_margin_max" not in plain.to_dict() and opts.to_dict()["crop_margin_max"] == 0.5
    for bad in (-0.1, 6.0, float("nan")):
        with pytest.raises(ValueError, match="crop_margin_max"):
            SampleOptions(crop_margin_max=bad)


def test_bend_taper_lean_moves_a_box_by_the_given_amounts_and_deform_draws_them():
    """On a 4 x 2 x 1 box: a bend of 0.02 raises both ends by 0.02 of the height; a taper of
    0.05 widens the front by 5 % and narrows the back as much; a lean of 0.04 moves the top 0.02 of the length forward
    and leaves the bottom. The data set's random deformation draws the same amounts as before (pinned values)."""
    from gd_completion.synth.meshio import box_mesh
    from gd_completion.synth.vehicles import _deform, bend_taper_lean

    box = box_mesh((4.0, 2.0, 1.0))
    v = box.vertices
    bent = bend_taper_lean(box, (0.02, 0.0, 0.0)).vertices
    np.testing.assert_allclose(bent[:, 2] - v[:, 2], 0.02)   # every corner of a box lies at an end
    tapered = bend_taper_lean(box, (0.0, 0.05, 0.0)).vertices
    np.testing.assert_allclose(tapered[:, 1], v[:, 1] * np.where(v[:, 0] > 0, 1.05, 0.95))
    leant = bend_taper_lean(box, (0.0, 0.0, 0.04)).vertices
    np.testing.assert_allclose(leant[:, 0] - v[:, 0], np.where(v[:, 2] > 0, 0.04 * 4.0 * 0.5, 0.0), atol=1e-12)
    np.testing.assert_array_equal(bend_taper_lean(box, (0.0, 0.0, 0.0)).vertices, v)
    # the data set's draw, pinned to the values of the code before bend_taper_lean was split out of it
    drawn = _deform(box, np.random.default_rng(3), 0.02).vertices
    np.testing.assert_allclose(drawn[[0, 1, 5]], [[-2.0, -1.0105275797, -0.5165740333],
                                                  [-1.9758980428, -1.0105275797, 0.4834259667],
                                                  [2.0241019572, -0.9894724203, 0.4834259667]], atol=1e-9)
