"""Evaluation: metrics against hand-computed values, baselines, PandaSet aggregates, a tiny evaluate run."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from gd_completion.errors import EvaluationError
from gd_completion.evaluation import baselines, metrics
from gd_completion.model import GGDConfig, GGDNet, chamfer_l2, chamfer_l2_directional, save_checkpoint

TINY = GGDConfig(num_input=128, num_output=256, num_control=32, tree_arity=(8, 4, 7), encoder_h0=(16, 32),
                 encoder_h1=(32,), code_hidden=(64,), code_dim=32, tree_hidden=(32,), local_widths=(16,),
                 gcn_width=16, gcn_blocks=1)


def _pts(*rows):
    return np.array(rows, dtype=np.float32)


# --- metrics -----------------------------------------------------------------------------------------

def test_chamfer_directions_hand_computed():
    out = _pts([0, 0, 0], [1, 0, 0])
    gt = _pts([0, 0, 0], [0, 2, 0])
    # out->gt: 0 and min(1, 1+4) = 1 -> 0.5 ; gt->out: 0 and min(4, 1+4) = 4 -> 2.0
    dg, gd = metrics.chamfer_directional(out, gt)
    assert float(dg) == pytest.approx(0.5)
    assert float(gd) == pytest.approx(2.0)
    assert float(metrics.chamfer(out, gt)) == pytest.approx(2.5)
    assert float(metrics.chamfer(gt, out)) == pytest.approx(2.5)


def test_fidelity_and_coverage_hand_computed():
    partial = _pts([0, 0, 3], [1, 0, 1])
    output = _pts([0, 0, 0], [0, 0, 1])
    # (0,0,3) -> (0,0,1): 4 ; (1,0,1) -> (0,0,1): 1 ; mean 2.5
    assert float(metrics.fidelity(partial, output)) == pytest.approx(2.5)
    reference = _pts([0, 0, 0], [3, 4, 0])
    # (0,0,0) -> 0 ; (3,4,0) -> (0,0,0): 25, (0,0,1): 26 -> 25 ; mean 12.5
    assert float(metrics.coverage_error(reference, output)) == pytest.approx(12.5)
    # A point of the output that matches no reference point does not change coverage, only fidelity-like CD(D,G).
    extra = np.concatenate([output, _pts([10, 10, 10])])
    assert float(metrics.coverage_error(reference, extra)) == pytest.approx(12.5)
    assert float(metrics.chamfer_directional(extra, reference)[0]) > 10


def test_completeness_by_region_hand_computed():
    gt = _pts([0, 0, 0], [1, 0, 0], [0, 3, 0])
    partial = _pts([0, 0, 0.01], [1, 0.02, 0])          # near the first two GT points only
    output = _pts([0, 0, 0], [1, 0.1, 0], [0, 1, 0])
    # observed: (0,0,0) -> 0, (1,0,0) -> 0.01 ; unobserved: (0,3,0) -> (0,1,0): 4
    seen, unseen, fraction = metrics.completeness_by_region(gt, output, partial, radius=0.05)
    assert seen == pytest.approx(0.005)
    assert unseen == pytest.approx(4.0)
    assert fraction == pytest.approx(2 / 3)
    seen, unseen, fraction = metrics.completeness_by_region(gt, output, partial, radius=10.0)
    assert fraction == 1.0 and np.isnan(unseen) and seen == pytest.approx((0 + 0.01 + 4) / 3)


def test_metrics_batched_chunked_and_consistent_with_training_loss():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 200, 3)).astype(np.float32)
    b = rng.normal(size=(3, 150, 3)).astype(np.float32)
    full = metrics.nearest_sq_distance(a, b)
    tiny_chunks = metrics.nearest_sq_distance(a, b, chunk_entries=1)
    brute = ((a[:, :, None, :] - b[:, None, :, :]) ** 2).sum(-1).min(-1)
    assert full.shape == (3, 200)
    np.testing.assert_allclose(full.numpy(), brute, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(tiny_chunks.numpy(), brute, rtol=1e-5, atol=1e-6)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    np.testing.assert_allclose(metrics.chamfer(a, b).numpy(), chamfer_l2(ta, tb).numpy(), rtol=1e-4)
    dg, gd = metrics.chamfer_directional(a, b)
    ref_dg, ref_gd = chamfer_l2_directional(ta, tb)
    np.testing.assert_allclose(dg.numpy(), ref_dg.numpy(), rtol=1e-4)
    np.testing.assert_allclose(gd.numpy(), ref_gd.numpy(), rtol=1e-4)


# --- baselines ---------------------------------------------------------------------------------------

def test_mirror_baseline_known_partial():
    partial = _pts([0.1, 0.2, 0.3], [-0.4, -0.05, 0.0])
    out = baselines.mirror_symmetry(partial)
    np.testing.assert_array_equal(out, _pts([0.1, 0.2, 0.3], [-0.4, -0.05, 0.0],
                                            [0.1, -0.2, 0.3], [-0.4, 0.05, 0.0]))
    np.testing.assert_array_equal(baselines.raw_input(partial), partial)


def test_mirror_recovers_the_hidden_side_of_a_symmetric_shape():
    rng = np.random.default_rng(0)
    # Surface of a box 1 x 0.4 x 0.3 (normalised frame), seen from its left side only (y > 0).
    pts = rng.uniform(-0.5, 0.5, size=(4000, 3)) * np.array([1.0, 0.4, 0.3])
    axis = rng.integers(0, 3, 4000)
    pts[np.arange(4000), axis] = np.sign(rng.normal(size=4000)) * np.array([0.5, 0.2, 0.15])[axis]
    full = pts.astype(np.float32)
    left = full[full[:, 1] > 0.01]
    raw_cov = float(metrics.coverage_error(full, left))
    mirror_cov = float(metrics.coverage_error(full, baselines.mirror_symmetry(left)))
    assert raw_cov > 0.01  # the right side (y = -0.2) is about 0.2 from the nearest seen point
    assert mirror_cov < raw_cov / 20
    assert float(metrics.fidelity(left, baselines.mirror_symmetry(left))) == 0.0


def test_network_baselines_match_generate_and_forward():
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    rng = np.random.default_rng(1)
    clouds = [rng.normal(size=(n, 3)).astype(np.float32) * 0.2 for n in (60, 128, 300)]
    generated, completion = baselines.network_outputs(model, clouds, max_batch=8)
    assert generated.shape == completion.shape == (3, 256, 3)
    np.testing.assert_allclose(baselines.generation_only(model, clouds), generated, atol=1e-5)
    np.testing.assert_allclose(baselines.generation_only(model, clouds[2]), generated[2], atol=1e-5)
    # Same batch composition as network_outputs: the window kNN of the deformation is not exactly
    # batch-independent for spread-out (untrained) outputs.
    np.testing.assert_allclose(baselines.ggd_net(model, clouds), completion, atol=1e-5)
    assert baselines.ggd_net(model, clouds[1]).shape == (256, 3)
    # The first N_c points of P_g are FPS control points copied from the (resampled) input.
    assert float(metrics.fidelity(generated[2, :TINY.num_control], clouds[2])) < 1e-10
    assert not np.allclose(generated, completion)


# --- synthetic ---------------------------------------------------------------------------------------

def _box_surface(rng: np.random.Generator, n: int, size=(1.0, 0.4, 0.3)) -> np.ndarray:
    half = np.array(size) / 2.0
    pts = rng.uniform(-1.0, 1.0, size=(n, 3)) * half
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = np.sign(rng.normal(size=n)) * half[axis]
    return pts.astype(np.float32)


def _half_box_pairs(n_pairs: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    partial, complete = [], []
    for _ in range(n_pairs):
        full = _box_surface(rng, 6000)
        left = full[full[:, 1] > 0.0]
        partial.append(left[rng.choice(len(left), 1024, replace=False)])
        complete.append(full[rng.choice(len(full), 2048, replace=False)])
    return np.stack(partial), np.stack(complete)


def test_evaluate_synthetic_values():
    from gd_completion.evaluation.synthetic import evaluate_synthetic

    partial, complete = _half_box_pairs()
    torch.manual_seed(0)
    sizes = np.tile([4.0, 1.6, 1.2], (3, 1))  # the half-box shape (1, 0.4, 0.3) is normalised by a 4 m length
    result = evaluate_synthetic(GGDNet(TINY).eval(), partial, complete, sizes, seed=5, source="test")
    assert set(result.metrics) == set(baselines.BASELINE_NAMES)
    assert result.points == {"input": 1024, "mirror": 2048, "box_fill": 256, "template": 256, "ggd_merge": 256,
                             "mirror_template": 256, "generation": 256, "ggd_raw": 256, "ggd": 256}
    # the box alone covers the hidden half far better than the raw input; mirror + template sits on the surface
    assert result.metrics["box_fill"]["cd_gd"] < result.metrics["input"]["cd_gd"] / 3
    assert result.metrics["mirror_template"]["cd_dg"] < result.metrics["box_fill"]["cd_dg"]
    for name, m in result.metrics.items():
        assert m["cd"] == pytest.approx(m["cd_dg"] + m["cd_gd"], rel=1e-5), name
    brute_dg = np.mean([((p[:, None] - g[None]) ** 2).sum(-1).min(1).mean() for p, g in zip(partial, complete)])
    assert result.metrics["input"]["cd_dg"] == pytest.approx(brute_dg * 1e4, rel=1e-4)
    assert result.metrics["input"]["fidelity"] == 0.0
    assert result.metrics["mirror"]["fidelity"] == 0.0
    # Mirroring the seen half of a symmetric shape restores completeness (GT -> output) by a wide margin.
    assert result.metrics["mirror"]["cd_gd"] < result.metrics["input"]["cd_gd"] / 10
    assert result.metrics["ggd"]["fidelity"] > 0.0
    assert result.metrics["ggd"]["cd_gd"] != result.metrics["ggd_raw"]["cd_gd"]   # evenly spaced: other points
    # The raw input misses only the unobserved half: its observed-region completeness is near 0.
    assert 0.2 < result.observed_fraction < 0.8
    assert result.metrics["input"]["cd_gd_observed"] < result.metrics["input"]["cd_gd_unobserved"] / 20


def test_reference_sample_is_voxel_uniform():
    from gd_completion.evaluation.pandaset_eval import reference_sample

    rng = np.random.default_rng(2)
    spread = _box_surface(rng, 3000)
    cluster = np.repeat(_pts([0.5, 0.0, 0.0]), 10000, axis=0)  # 10000 returns on one spot (a near surface)
    agg = np.concatenate([cluster, spread])
    sample = reference_sample(agg, 1024)
    assert sample.shape == (1024, 3)
    assert float(metrics.nearest_sq_distance(sample, agg).max()) == 0.0  # every sample is an aggregate point
    assert int((sample == cluster[0]).all(1).sum()) <= 2  # random picks would take ~3/4 from the cluster
    small = reference_sample(spread[:100], 256)
    assert small.shape == (256, 3)


def test_the_band_near_a_side_is_within_the_zone_of_the_left_or_right_side():
    from gd_completion.evaluation.pandaset_eval import near_a_side
    from gd_completion.geometry import Box3D

    box = Box3D(center=(0.0, 0.0, 0.0), size=(4.0, 2.0, 1.5), yaw=0.3)
    # metres across: 1.0 (at the side), 0.65 (0.35 inside), 0.55 (0.45 inside), 0 (the middle), -0.7 (the other side)
    across = np.array([1.0, 0.65, 0.55, 0.0, -0.7]) / 4.0
    points = np.stack([np.zeros(5), across, np.full(5, -0.18)], axis=1).astype(np.float32)
    assert near_a_side(points, box).tolist() == [True, True, False, False, True]
    assert near_a_side(points, box, zone=0.5).tolist() == [True, True, True, False, True]


def test_size_bins():
    from gd_completion.evaluation.pandaset_eval import size_bin

    assert [size_bin(n) for n in (49, 50, 199, 200, 999, 1000, 50000)] == [
        "", "50-200", "50-200", "200-1000", "200-1000", ">1000", ">1000"]


# --- PandaSet ----------------------------------------------------------------------------------------

def test_pandaset_aggregate_of_a_parked_vehicle(shared_data):
    from gd_completion.datasets.pandaset import PandaSetSequence
    from gd_completion.evaluation.nearest import nearest_sq
    from gd_completion.evaluation.pandaset_eval import collect_tracks, in_ground_band, stationary_vehicles
    from gd_completion.preprocess import Preprocessing, with_aside

    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    sequence = PandaSetSequence(root)
    vehicles = stationary_vehicles(sequence)
    assert "Car" in vehicles.values() and all(not v.startswith("Pedestrian") for v in vehicles.values())
    prep = Preprocessing(min_points=1)
    cars = {u: c for u, c in vehicles.items() if c == "Car"}
    few = collect_tracks(sequence, cars, prep, frames=range(0, 6))
    uuid = max(few, key=lambda u: len(few[u].aggregate()))
    track_few = few[uuid]
    track_many = collect_tracks(sequence, {uuid: "Car"}, prep, frames=range(0, 24))[uuid]
    assert len(track_few.frames) >= 3
    assert set(track_few.frames) < set(track_many.frames)
    assert len(track_many.aggregate()) > len(track_few.aggregate()) > 1000

    agg = track_many.aggregate()
    length = min(b.size[0] for b in track_many.boxes)
    width = max(b.size[1] for b in track_many.boxes)
    height = max(b.size[2] for b in track_many.boxes)
    longest = max(b.size[0] for b in track_many.boxes)
    assert np.all(np.abs(agg[:, 0]) <= (longest / 2 + 0.1) / length + 1e-5)
    assert np.all(np.abs(agg[:, 1]) <= (width / 2 + 0.1) / length + 1e-5)
    assert np.all(np.abs(agg[:, 2]) <= (height / 2 + 0.1) / length + 1e-5)
    # Length along normalised x (data README: dimensions.y is the length, heading = yaw + pi/2): the
    # aggregate spans most of the box length along x and no more than the width along y.
    assert np.ptp(agg[:, 0]) > 0.8
    assert np.ptp(agg[:, 1]) < (width + 0.2) / length
    # Frames agree: each frame's points lie on the surface seen in the other frames (within a few cm).
    first = track_many.points[0]
    others = np.concatenate(track_many.points[1:])
    rms_m = float(metrics.fidelity(first, others)) ** 0.5 * length
    assert rms_m < 0.04

    # The band-kept reference (`in_box`) is the exact box: the contract's crop reaches 0.1 m past it (points there,
    # road beside the vehicle among them), `in_box` does not; it holds the crop's in-box points and the band's.
    past_the_box = 0
    for box, inside, cropped in zip(track_many.boxes, track_many.in_box, track_many.reference):
        half = np.array(box.size) / 2 / box.size[0] + 1e-5
        assert len(inside) and np.all(np.abs(inside) <= half)
        within = np.all(np.abs(cropped) <= half, axis=1)
        past_the_box += int((~within).sum())
        assert nearest_sq(cropped[within], inside).max(initial=0.0) == 0.0   # the crop's in-box points are in it
    assert past_the_box > 0
    # ... and nothing else: each of its points is above the ground cut (in the crop) or in the footprint's band
    for inside, cropped, aside in zip(track_many.in_box, track_many.reference, track_many.asides):
        assert nearest_sq(inside, with_aside(cropped, aside)).max() == 0.0
    assert any(in_ground_band(inside, box, prep.ground_clearance).any()
               for track in few.values() for box, inside in zip(track.boxes, track.in_box))


def test_a_wider_input_margin_widens_the_inputs_not_the_references(shared_data):
    """`collect_tracks(input_margin=)`: the references are those of the contract's margin, each entry's inputs
    hold its reference's points and more (some entries gain points), the noisy boxes are cropped as widely, and a
    margin narrower than the contract's is refused."""
    from gd_completion.datasets.pandaset import PandaSetSequence
    from gd_completion.evaluation.box_noise import BoxNoise
    from gd_completion.evaluation.pandaset_eval import collect_tracks, stationary_vehicles
    from gd_completion.preprocess import Preprocessing

    sequence = PandaSetSequence(shared_data / "pandaset-002")
    vehicles = stationary_vehicles(sequence)
    prep, frames = Preprocessing(min_points=1), range(0, 3)
    narrow = collect_tracks(sequence, vehicles, prep, frames=frames, noise=BoxNoise())
    wide = collect_tracks(sequence, vehicles, prep, frames=frames, noise=BoxNoise(), input_margin=0.4)
    gained = noisy_gained = 0
    for uuid, track in narrow.items():
        other = wide[uuid]
        assert other.frames == track.frames and len(other.reference) == len(track.points)
        for k, points in enumerate(track.points):
            np.testing.assert_array_equal(other.reference[k], points)   # the contract's crop
            np.testing.assert_array_equal(track.reference[k], points)   # equal margins: the inputs themselves
            wider = {tuple(p) for p in other.points[k]}
            assert all(tuple(p) in wider for p in points)
            gained += len(other.points[k]) > len(points)
            assert (track.noisy[k] is None) == (other.noisy[k] is None)   # the same noisy boxes are cropped
            if track.noisy[k] is not None and other.noisy[k] is not None:
                assert other.noisy[k].box == track.noisy[k].box   # the same noisy box, cropped more widely
                noisy_gained += len(other.noisy[k].normalized) > len(track.noisy[k].normalized)
                assert len(other.noisy[k].normalized) >= len(track.noisy[k].normalized)
    assert gained > 0 and noisy_gained > 0
    with pytest.raises(ValueError, match="the contract's"):
        collect_tracks(sequence, vehicles, prep, frames=frames, input_margin=0.05)
    with pytest.raises(ValueError, match=r"must be in \[0, 5\] metres"):
        collect_tracks(sequence, vehicles, prep, frames=frames, input_margin=6.0)


def test_observations_and_pose_scans_follow_the_reference_crop():
    """An entry is an observation by its reference's count (the contract's crop), not by its wider input's; the
    visibility scans are the reference's points."""
    from gd_completion.evaluation.pandaset_eval import MIN_INPUT_POINTS, VehicleTrack
    from gd_completion.geometry import Box3D

    box = Box3D((10.0, 0.0, 1.0), (4.0, 2.0, 1.5), 0.0, "car", 1)
    rng = np.random.default_rng(0)
    few, many, extra = (rng.normal(size=(n, 3)) for n in (MIN_INPUT_POINTS - 10, MIN_INPUT_POINTS + 10, 20))
    track = VehicleTrack("u", 1, "Car", frames=[0, 1], points=[np.vstack([few, extra]), np.vstack([many, extra])],
                         boxes=[box, box], sensors=[0, 0], origins=[np.zeros(3), np.zeros(3)], reference=[few, many])
    assert track.input_frames() == [1]   # the first entry's input has 60 points, its reference 40
    assert len(track.aggregate()) == len(few) + len(many)
    scans = track.pose_scans()
    assert len(scans) == 1 and scans[0][1] is track.reference[1]


def test_size_buckets_count_the_contracts_crop(shared_data, monkeypatch):
    """An observation whose wider input crosses a bucket's edge (190 points in the contract's crop, 210 in the input)
    stays in the contract's bucket."""
    from gd_completion.evaluation import pandaset_eval as pe
    from gd_completion.geometry import Box3D

    rng = np.random.default_rng(3)
    box = Box3D((10.0, 0.0, 1.0), (4.0, 2.0, 1.5), 0.0, "car", 7)
    scale = np.array([0.5, 0.25, 0.18], np.float32)
    reference = [(rng.uniform(-1, 1, (190, 3)) * scale).astype(np.float32) for _ in range(2)]
    inputs = [np.vstack([r, (rng.uniform(-1, 1, (20, 3)) * scale).astype(np.float32)]) for r in reference]
    track = pe.VehicleTrack("u", 7, "Car", frames=[0, 1], points=inputs, boxes=[box, box], sensors=[0, 0],
                            origins=[np.zeros(3), np.zeros(3)], noisy=[None, None],
                            asides=[np.zeros((0, 3), np.float32)] * 2, in_box=reference, reference=reference)
    monkeypatch.setattr(pe, "stationary_vehicles", lambda *args, **kwargs: {"u": "Car"})
    monkeypatch.setattr(pe, "collect_tracks", lambda *args, **kwargs: {"u": track})
    torch.manual_seed(0)
    result = pe.evaluate_pandaset(GGDNet(TINY).eval(), shared_data / "pandaset-002", noise=None,
                                  random_points=300, reference_points=200)
    assert [(i.n_points, i.size_bin) for i in result.items] == [(190, "50-200"), (190, "50-200")]


# --- the evaluate command ----------------------------------------------------------------------------

def test_evaluate_command_tiny_run(tmp_path, shared_data, monkeypatch, capsys):
    import argparse

    from gd_completion import cli
    from gd_completion.evaluation import synthetic
    from gd_completion.tools import evaluate

    assert cli.SUBCOMMANDS["evaluate"] == "gd_completion.tools.evaluate"
    torch.manual_seed(0)
    model_path = save_checkpoint(tmp_path / "tiny.pt", GGDNet(TINY))
    nc64 = GGDConfig(**{**TINY.to_dict(), "num_control": 64, "tree_arity": [8, 4, 6]})
    ablation = save_checkpoint(tmp_path / "nc64.pt", GGDNet(nc64))
    partial, complete = _half_box_pairs(3)
    seen = {}

    def fake_heldout(n, *, seed, path=None):
        from gd_completion.evaluation.synthetic import HeldOut

        seen.update(n=n, seed=seed)
        return HeldOut(partial[:n], complete[:n], "test pairs", complete[:n] + 0.01, np.tile([4.0, 1.6, 1.2], (n, 1)))

    monkeypatch.setattr(synthetic, "load_heldout", fake_heldout)  # evaluate imports it when it runs
    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    out = tmp_path / "report"
    args = parser.parse_args(["evaluate", "--model", str(model_path), "--output", str(out),
                              "--synthetic-samples", "2", "--ablation-checkpoints", str(ablation), str(model_path),
                              "--pandaset", str(shared_data / "pandaset-002"), "--max-vehicles", "2",
                              "--max-frames-per-vehicle", "2", "--threads", "1", "--fusion-max-vehicles", "1",
                              "--heldout-mesh-samples", "2", "--random-reference-points", "2000",
                              "--fusion-max-frames", "3", "--fusion-consistency-frames", "3", "--reuse-frames", "4",
                              "--no-classification"])   # test_classification runs that part
    assert args.func(args) == 0
    assert seen == {"n": 2, "seed": synthetic.EVAL_SEED}
    text = (out / "report.md").read_text()
    printed = capsys.readouterr().out
    assert "Metric floor: a second uniform 2048-point sample" in text
    assert "### Completeness by region" in text
    for heading in ("## Synthetic held-out set", "## Control-point ablation", "## PandaSet 002",
                    "## PandaSet 002: track fusion", "Temporal consistency",
                    "Coverage error x1e3", "Fidelity x1e3", "GGD-Net", "mirror symmetry", "generation only"):
        assert heading in text and heading in printed
    ablation_rows = [line for line in text.splitlines() if line.startswith("| 32 ") or line.startswith("| 64 ")]
    assert [r.split()[1] for r in ablation_rows] == ["32", "64"]
    # the N_c = 32 checkpoint is the evaluated model: its ablation row repeats the synthetic table's figures
    cells = lambda line: [c.strip() for c in line.strip("|").split("|")]  # noqa: E731
    synthetic = {cells(line)[0]: cells(line) for line in text.split("### Completeness by region")[0].splitlines()
                 if line.startswith(("| GGD-Net", "| generation only"))}
    row32 = cells(ablation_rows[0])
    # the ablation compares the networks' raw P_o (the paper's claim), not the evenly spaced output
    assert row32[3] == synthetic["GGD-Net, raw P_o (before even spacing)"][1]
    assert row32[4] == synthetic["generation only"][1]
    assert "## Held-out meshes" in text and "held-out meshes of vehicle-meshes" in text
    pandaset = text.split("## PandaSet 002: single")[1].split("## PandaSet 002: track fusion")[0]
    pandaset_rows = [line for line in pandaset.splitlines() if line.startswith("| raw input")]
    # random and voxel coverage, fidelity, ground band kept (coverage, the band alone, by zone, fidelity),
    # two-sided, by sensor, box noise
    assert len(pandaset_rows) == 10
    band = pandaset.split("### Ground band kept: coverage")[1].split("### Ground band kept: fidelity")[0]
    band_fidelity = pandaset.split("### Ground band kept: fidelity")[1].split("###")[0]
    raw_band = [cells(line) for line in band_fidelity.splitlines() if line.startswith("| raw input")][0]
    assert raw_band[1] == "0.000"   # the raw input holds every in-box point: above the cut and the band's
    band_rows = [cells(line) for line in band.splitlines() if line.startswith("| raw input")]
    assert float(band_rows[1][1]) > float(band_rows[0][1])   # the band alone is covered worse than the whole
    assert len(band_rows) == 3 and len(band_rows[2]) == 3   # the band near the sides and under the body
    assert "m of the box's left or right side" in band and "% of the band's points on average" in band
    assert any(c != "-" for c in band_rows[2][1:])   # a table printed NaN as "-": some band was scored
    # the targets' ratios over the prior, from the unrounded means, under both coverage tables
    coverage = pandaset.split("### Coverage error x1e3 (reference")[1].split("###")[0]
    for section in (coverage, band):
        line = next(x for x in section.splitlines() if x.startswith("Over mirror + template, from the unrounded"))
        published = line.split("published ")[1].split(";")[0].split(" / ")
        table = {cells(x)[0]: cells(x) for x in section.split("\n\nThat reference")[0].splitlines()
                 if x.startswith(("| GGD-Net + measured", "| mirror + template"))}
        ratio = (float(table["GGD-Net + measured merge (published)"][-4])
                 / float(table["mirror + template, FPS to 2048"][-4]))
        assert len(published) == 4 and abs(float(published[0]) - ratio) < 0.01   # 'all', as the rounded cells give
    oracle = [cells(line) for line in pandaset.splitlines() if line.startswith("| (oracle)")]
    assert len(oracle) == 1 and float(oracle[0][1]) < float(oracle[0][2])   # the noisy box misplaces it
    fidelity_rows = [line for line in pandaset.split("### Fidelity")[1].splitlines() if line.startswith("| ")]
    assert cells(fidelity_rows[1])[0] == "raw input" and cells(fidelity_rows[1])[1] == "0.000"  # faithful to itself
    assert float(cells(pandaset_rows[0])[2]) > 0.0
    assert cells(pandaset_rows[0])[1].startswith("own: mean")
    assert (out / "pandaset_vehicles.png").stat().st_size > 10_000
    assert (out / "pandaset_worst.png").stat().st_size > 10_000
    assert (out / "heldout_meshes.png").stat().st_size > 10_000
    assert (out / "synthetic_vehicles.png").stat().st_size > 10_000
    reuse = {cells(line)[0]: cells(line) for line in text.split("## PandaSet 002: completion reuse")[1].splitlines()
             if line.startswith(("| fresh", "| reuse", "| mirror"))}
    assert sorted(reuse) == ["fresh", "mirror + template (no network)", "reuse, association", "reuse, cuboid ids"]
    prior = reuse["mirror + template (no network)"]
    assert int(prior[1]) == 0 and float(prior[4]) > 0   # no network run; a coverage error of its own
    assert int(reuse["reuse, association"][1]) < int(reuse["fresh"][1]) and int(reuse["fresh"][2]) == 0
    assert "true frame-to-frame links kept" in text


def test_load_heldout_uses_the_synth_dataset(tmp_path):
    from gd_completion.evaluation.synthetic import EVAL_SEED, load_heldout
    from gd_completion.synth import dataset

    partial, complete, source, surface, sizes, meshes, mesh_names = load_heldout(2)
    assert mesh_names is None and len(meshes) == 2 and all(v.shape[1] == 3 and f.shape[1] == 3 for v, f in meshes)
    assert partial.shape == (2, 1024, 3) and complete.shape == (2, 2048, 3) and surface.shape == (2, 2048, 3)
    assert str(EVAL_SEED) in source
    # the second surface sample is another sample of the same shape, not a copy, and leaves the pair unchanged
    plain = dataset.build_dataset(2, EVAL_SEED)
    np.testing.assert_array_equal(plain["complete"], complete)
    np.testing.assert_array_equal(plain["partial"], partial)
    np.testing.assert_array_equal(plain["size"], sizes)
    assert not np.allclose(surface, complete)
    from gd_completion.evaluation import metrics
    floor = metrics.chamfer(surface, complete).numpy()
    assert np.all(floor > 0) and np.all(floor < 1e-3)        # a few 1e-4: the sampling-density floor
    training = dataset.build_dataset(2, 0)
    assert not np.allclose(training["complete"], complete)  # evaluation shapes are not the seed-0 shapes
    path = dataset.save_dataset(tmp_path / "heldout.npz", dataset.build_dataset(3, EVAL_SEED + 1))
    p2, c2, source2, surface2, sizes2, meshes2, names2 = load_heldout(2, path=path)
    assert p2.shape == (2, 1024, 3) and c2.shape == (2, 2048, 3) and "heldout.npz" in source2 and surface2 is None
    assert meshes2 is None and names2 is None   # a file holds no meshes and names no shape
    assert sizes2.shape == (2, 3) and np.all(sizes2[:, 0] > sizes2[:, 1])  # (length, width, height) of the set
    data = dataset.load_dataset(path)
    del data["size"]
    dataset.save_dataset(tmp_path / "nosize.npz", data)
    from gd_completion.errors import EvaluationError
    with pytest.raises(EvaluationError, match="no per-sample box sizes"):
        load_heldout(2, path=tmp_path / "nosize.npz")


def test_evaluate_synthetic_on_the_true_mesh(shared_data):
    from gd_completion.evaluation.report import synthetic_section
    from gd_completion.evaluation.synthetic import SYNTHETIC_METRICS, evaluate_synthetic, load_heldout_meshes

    held = load_heldout_meshes(3, shared_data / "vehicle-meshes", seed=5)
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    result = evaluate_synthetic(model, held.partial, held.complete, held.sizes, surface=held.surface,
                                meshes=held.meshes)
    for name, m in result.metrics.items():
        assert set(m) == set(SYNTHETIC_METRICS), name
        assert 0.0 <= m["far"] <= 1.0 - m["on_surface"] + 1e-12, name
    assert result.floor is not None
    assert result.floor["on_surface"] == 1.0 and result.floor["far"] == 0.0   # drawn on the mesh
    assert result.metrics["input"]["on_surface"] > 0.95   # scan returns: on the surface, up to sensor noise
    assert result.metrics["box_fill"]["on_surface"] < 0.7 and result.metrics["box_fill"]["far"] > 0.2
    text = synthetic_section(result)
    header = [line for line in text.splitlines() if line.startswith("| method")][0]
    assert header.rstrip(" |").endswith("| on surface | far")
    assert "on surface: share of output points within 0.02 (2 % of the length) of the true mesh" in text
    assert "on surface 1.000 (1 by construction" in text and "Not measured here" not in text
    # without the meshes the columns are empty and the report says why
    bare = evaluate_synthetic(model, held.partial, held.complete, held.sizes, surface=held.surface)
    assert np.isnan(bare.metrics["ggd"]["on_surface"]) and np.isnan(bare.floor["far"])
    assert bare.metrics["ggd"]["cd"] == result.metrics["ggd"]["cd"]
    assert "Not measured here ('-')" in synthetic_section(bare)


def test_placement_floor_hand_computed():
    from gd_completion.evaluation.pandaset_eval import placement_floor
    from gd_completion.geometry import Box3D, normalize

    box = Box3D((10.0, 5.0, 0.0), (4.0, 2.0, 1.5), 0.3, "car", 1)
    shifted = Box3D((10.0 + 0.1 * np.cos(0.3), 5.0 + 0.1 * np.sin(0.3), 0.0), (4.0, 2.0, 1.5), 0.3, "car", 1)
    perfect = normalize(np.array([[10.0, 5.0, 0.0], [11.0, 5.5, 0.3]]), box)
    assert placement_floor(perfect, perfect, box, box) < 1e-9
    # placed by a box 0.1 m ahead along its heading: every point 0.1 m / 4 m off, x1e3
    assert placement_floor(perfect, perfect, shifted, box) == pytest.approx((0.1 / 4.0) ** 2 * 1e3, rel=1e-4)


def test_heldout_mesh_set_draws_only_the_heldout_meshes(shared_data, tmp_path):
    from gd_completion.errors import EvaluationError
    from gd_completion.evaluation.synthetic import load_heldout_meshes
    from gd_completion.synth.dataset import build_dataset
    from gd_completion.synth.meshio import HELDOUT_MESHES, load_mesh

    meshes = shared_data / "vehicle-meshes"
    held = load_heldout_meshes(3, meshes, seed=5)
    data = build_dataset(3, 5, meshes_dir=meshes, mesh_fraction=1.0, only_meshes=HELDOUT_MESHES)
    # every pair a mesh shape, drawn from the list of the held-out meshes alone ("mesh:<index in that list>")
    assert all(k.startswith("mesh:") and int(k[5:]) < len(HELDOUT_MESHES) for k in data["kind"]), data["kind"]
    np.testing.assert_array_equal(held.partial, data["partial"])
    np.testing.assert_array_equal(held.complete, data["complete"])
    np.testing.assert_array_equal(held.sizes, np.asarray(data["size"], np.float64))
    assert held.surface.shape == held.complete.shape and "held-out meshes of vehicle-meshes" in held.source
    assert held.meshes is not None and len(held.meshes) == 3
    # each pair names its mesh: the named file's faces are the pair's (the vertices are scaled and deformed)
    assert held.mesh_names is not None and len(held.mesh_names) == 3 and set(held.mesh_names) <= set(HELDOUT_MESHES)
    for name, (_, faces) in zip(held.mesh_names, held.meshes):
        np.testing.assert_array_equal(faces, load_mesh(meshes / f"{name}.ply").faces)
    with pytest.raises(EvaluationError, match="held-out meshes"):
        load_heldout_meshes(1, tmp_path)


def test_mesh_pairs_draw_only_the_named_meshes(shared_data):
    """`load_mesh_pairs` (the held-out set's loader, any list of meshes): every pair from the named meshes, each
    named; a name the folder lacks is an error that says what is missing."""
    from gd_completion.errors import EvaluationError
    from gd_completion.evaluation.synthetic import load_mesh_pairs

    meshes = shared_data / "vehicle-meshes"
    names = ("basic_basiccar", "public_bus")   # two of the training meshes
    pairs = load_mesh_pairs(4, meshes, names, seed=7, what="training")
    assert pairs.mesh_names is not None and len(pairs.mesh_names) == 4 and set(pairs.mesh_names) <= set(names)
    assert pairs.partial.shape[0] == 4 and "2 training meshes of vehicle-meshes" in pairs.source
    with pytest.raises(EvaluationError, match="1 of the 2 training meshes found"):
        load_mesh_pairs(1, meshes, ("basic_basiccar", "no_such_mesh"), what="training")


def test_evaluate_command_skips_missing_pandaset(tmp_path, capsys):
    import argparse

    from gd_completion.tools import evaluate

    model_path = save_checkpoint(tmp_path / "tiny.pt", GGDNet(TINY), note="test model")
    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    args = parser.parse_args(["evaluate", "--model", str(model_path), "--output", str(tmp_path / "out"),
                              "--synthetic-samples", "0", "--pandaset", str(tmp_path / "absent")])
    assert args.func(args) == 0
    text = (tmp_path / "out" / "report.md").read_text()
    assert f"Skipped: {tmp_path / 'absent'} not found" in text
    assert "note: test model" in text and "N_c = 32" in text
    assert "## Synthetic" not in text and not list((tmp_path / "out").glob("*.png"))


def test_f_score_hand_computed():
    out = np.array([[0.0, 0, 0], [1, 0, 0]], np.float32)
    gt = np.array([[0.0, 0, 0.005], [5, 0, 0]], np.float32)
    assert float(metrics.f_score(out, gt)) == pytest.approx(0.5)          # precision 1/2, recall 1/2
    assert float(metrics.f_score(out, out)) == 1.0
    assert float(metrics.f_score(out, out + 10)) == 0.0
    three = np.array([[0.0, 0, 0], [0.02, 0, 0], [0.04, 0, 0]], np.float32)
    # precision 1/2 (out[0] only), recall 1/3 (three[0] only): F = 2 * (1/2 * 1/3) / (1/2 + 1/3) = 0.4
    assert float(metrics.f_score(out, three)) == pytest.approx(0.4)
    batch = metrics.f_score(np.stack([out, out]), np.stack([gt, out]))
    np.testing.assert_allclose(batch.numpy(), [0.5, 1.0])


def _tiny_pandaset_run(tmp_path, shared_data):
    """(the evaluate command's parser, the arguments of a small PandaSet-only run of a tiny untrained model)."""
    import argparse

    from gd_completion.tools import evaluate

    torch.manual_seed(0)
    model_path = save_checkpoint(tmp_path / "tiny.pt", GGDNet(TINY))
    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    return parser, ["--model", str(model_path), "--synthetic-samples", "0", "--pandaset",
                    str(shared_data / "pandaset-002"), "--max-vehicles", "2", "--max-frames-per-vehicle", "2",
                    "--threads", "1", "--no-fusion", "--no-reuse", "--random-reference-points", "2000"]


def test_evaluate_command_box_noise_sigmas(tmp_path, shared_data):
    """`--box-noise` sets the box-noise run's sigmas: with all four at zero the noisy boxes are the true ones, so
    every method's noisy coverage is its clean one; a negative or NaN sigma is a one-line error before any output."""
    parser, common = _tiny_pandaset_run(tmp_path, shared_data)
    out = tmp_path / "report"
    args = parser.parse_args(["evaluate", "--output", str(out), "--box-noise", "0", "0", "0", "0", *common])
    assert args.func(args) == 0
    text = (out / "report.md").read_text()
    table = text.split("### Box noise")[1].split("###")[0]
    assert "sigma 0.0 m centre x/y, 0.0 m centre z, 0 % size (each dimension), 0.0 deg yaw" in table
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()
             if line.startswith("| ") and not line.startswith(("| method", "| (oracle)"))]
    assert len(cells) == 9
    for row in cells:
        assert row[1] == row[2] and row[3] in ("+0.0 %", "-0.0 %"), row   # equal up to rounding of the yaw
    for bad in (["0.15", "-0.05", "0", "4"], ["nan", "0", "0", "0"]):
        failed = tmp_path / f"failed_{bad[0]}"
        args = parser.parse_args(["evaluate", "--output", str(failed), "--box-noise", *bad, *common])
        with pytest.raises(EvaluationError, match="finite standard deviation >= 0"):
            args.func(args)
        assert not failed.exists()
    with pytest.raises(SystemExit):   # sigmas for a run that is skipped: refused, not ignored
        parser.parse_args(["evaluate", "--box-noise", "0.1", "0", "0", "0", "--no-box-noise"])


def test_evaluate_command_crop_margin(tmp_path, shared_data):
    """`--crop-margin` widens the PandaSet inputs only: the same observations and references (the band-kept and
    the fidelity tables' reference rows equal), the report says so; a margin narrower than the model's contract or
    not finite is a one-line error before any output."""
    parser, common = _tiny_pandaset_run(tmp_path, shared_data)
    common += ["--no-box-noise", "--pool-margin", "0"]   # no points kept aside beyond the crop: the inputs differ
    texts = {}
    for name, extra in (("contract", []), ("wide", ["--crop-margin", "0.3"])):
        args = parser.parse_args(["evaluate", "--output", str(tmp_path / name), *extra, *common])
        assert args.func(args) == 0
        texts[name] = (tmp_path / name / "report.md").read_text()
    assert "cropped with a margin of 0.3 m" in texts["wide"] and "cropped with a margin" not in texts["contract"]
    counts = [t.split(" observations (frame, sensor)")[0].rsplit("\n", 1)[-1] for t in texts.values()]
    assert counts[0] == counts[1]

    def row(text: str, section: str, title: str) -> str:
        table = text.split(section)[1].split("###")[0]
        return next(line for line in table.splitlines() if line.startswith(f"| {title}"))

    # the references and the fidelity's points are the contract's: methods that ignore the input agree
    for section in ("### Coverage error x1e3 (reference", "### Ground band kept: coverage", "### Fidelity x1e3"):
        assert row(texts["contract"], section, "box fill") == row(texts["wide"], section, "box fill")
    # the inputs are wider: the raw input covers the reference at least as well, and differs
    assert row(texts["contract"], "### Coverage error x1e3 (reference", "raw input") != \
        row(texts["wide"], "### Coverage error x1e3 (reference", "raw input")
    args = parser.parse_args(["evaluate", "--output", str(tmp_path / "same"), "--crop-margin", "0.1", *common])
    assert args.func(args) == 0   # the contract's own margin: not called wider
    assert "cropped with a margin" not in (tmp_path / "same" / "report.md").read_text()
    refused_before_output(parser, common, tmp_path, (
        (["--crop-margin", "0.05"], "narrower than the model's contract"),
        (["--crop-margin", "nan"], "a margin in metres"),
        (["--crop-margin", "0.3", "--no-pandaset"], "the PandaSet part is skipped")))


def refused_before_output(parser, common: list[str], tmp_path, cases) -> None:
    """Each (extra arguments, message) of `cases` given to `evaluate` is a one-line EvaluationError matching the
    message, raised before the output folder is made."""
    for bad, message in cases:
        failed = tmp_path / f"failed_{bad[1]}"
        args = parser.parse_args(["evaluate", "--output", str(failed), *bad, *common])
        with pytest.raises(EvaluationError, match=message):
            args.func(args)
        assert not failed.exists()


def test_evaluate_command_pool_margin(tmp_path, shared_data):
    """`--pool-margin` keeps the measured points within it aside for the merge: the inputs (raw input, published) gain
    the points beside the crop, the references and the methods that ignore the input do not change, the report says
    so and counts what is published beside the crop; an unusable margin is a one-line error before any output."""
    parser, common = _tiny_pandaset_run(tmp_path, shared_data)
    common.append("--no-box-noise")
    texts = {}
    for margin in ("0", "0.4"):
        args = parser.parse_args(["evaluate", "--output", str(tmp_path / margin), "--pool-margin", margin, *common])
        assert args.func(args) == 0
        texts[margin] = (tmp_path / margin / "report.md").read_text()
    said = "The measured points above the ground within 0.4 m of the box"
    assert said in texts["0.4"] and "The measured points above the ground within" not in texts["0"]

    def row(text: str, section: str, title: str) -> list[str]:
        table = text.split(section)[1].split("###")[0]
        return [c.strip() for c in next(line for line in table.splitlines() if line.startswith(f"| {title}"))
                .strip("|").split("|")]

    coverage, two_sided = "### Coverage error x1e3 (reference", "### Two-sided"
    assert row(texts["0"], coverage, "box fill") == row(texts["0.4"], coverage, "box fill")
    assert row(texts["0"], coverage, "raw input") != row(texts["0.4"], coverage, "raw input")
    beside = {m: float(row(t, two_sided, "raw input")[-1].rstrip(" %")) for m, t in texts.items()}
    assert beside["0"] == 0.0 < beside["0.4"]   # the raw input's points beside the crop: the pool margin's only
    assert row(texts["0.4"], two_sided, "box fill")[-1] == "0.00 %"
    refused_before_output(parser, common, tmp_path, (
        (["--pool-margin", "-1"], "a margin in metres"), (["--pool-margin", "nan"], "a margin"),
        (["--pool-margin", "0.4", "--no-pandaset"], "the PandaSet part is skipped")))


@pytest.mark.integration  # reads the shared drive at length
def test_evaluate_command_crop_margin_reaches_fusion_and_reuse(tmp_path, shared_data, monkeypatch):
    """`--crop-margin` is passed to the track-fusion and reuse parts too (the reuse part's completers crop with it;
    both reports say so); the contract's own margin is not reported as wider anywhere. The completers keep the
    default pool margin."""
    from gd_completion import pipeline
    from gd_completion.preprocess import POOL_MARGIN

    margins, pools = [], []

    class Recording(pipeline.VehicleCompleter):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            margins.append(self.preprocessing.crop_margin)
            pools.append(self.pool_margin)

    monkeypatch.setattr(pipeline, "VehicleCompleter", Recording)
    parser, common = _tiny_pandaset_run(tmp_path, shared_data)
    common = [a for a in common if a not in ("--no-fusion", "--no-reuse")]
    common += ["--no-box-noise", "--fusion-max-vehicles", "1", "--fusion-max-frames", "2",
               "--fusion-consistency-frames", "2", "--reuse-frames", "2"]
    for margin, said in (("0.3", True), ("0.1", False)):
        out = tmp_path / f"m{margin}"
        args = parser.parse_args(["evaluate", "--output", str(out), "--crop-margin", margin, *common])
        assert args.func(args) == 0
        text = (out / "report.md").read_text()
        fusion = text.split("## PandaSet 002: track fusion")[1].split("## PandaSet 002: completion reuse")[0]
        reuse = text.split("## PandaSet 002: completion reuse")[1]
        for section in (fusion, reuse):
            assert (f"a margin of {margin} m" in section) == said
        assert margins == [float(margin)] * 3   # fresh, reuse by ids, reuse by association
        assert pools == [POOL_MARGIN] * 3        # the node's default pool margin
        margins.clear()
        pools.clear()
