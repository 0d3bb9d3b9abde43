"""Box-only priors, the observed/precision metric, box noise, the grid nearest neighbour, and a small real
PandaSet evaluation with every method."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from gd_completion.evaluation import box_noise, metrics, nearest, observed, priors
from gd_completion.evaluation.baselines import BASELINE_NAMES, BASELINE_TITLES, mirror_symmetry
from gd_completion.geometry import Box3D

SIZES = np.array([[4.5, 1.8, 1.5], [12.0, 2.5, 3.2]])


def test_box_fill_is_uniform_inside_each_box():
    fill = priors.box_fill(SIZES)
    assert fill.shape == (2, 2048, 3) and fill.dtype == np.float32
    half = SIZES / 2 / SIZES[:, :1]
    for cloud, h in zip(fill, half):
        assert np.all(np.abs(cloud) <= h + 1e-6)
        np.testing.assert_allclose(np.ptp(cloud, axis=0), 2 * h, rtol=0.01)      # fills the box to its faces
        np.testing.assert_allclose(cloud.mean(0), 0.0, atol=0.02)
        assert np.histogram(cloud[:, 0], bins=4, range=(-h[0], h[0]))[0].min() > 450  # ~512 per quarter
    np.testing.assert_array_equal(priors.box_fill(SIZES), fill)                  # seeded


def test_template_fits_the_box_and_thinning_keeps_the_count():
    template = priors.template_points(SIZES)
    assert template.shape == (2, 2048, 3)
    for cloud, size in zip(template, SIZES):
        # a surface sample of the sedan fitted to the box spans (almost) the whole box, centred on it
        np.testing.assert_allclose(np.ptp(cloud, axis=0), size / size[0], rtol=0.03)
        assert np.all(np.abs(cloud) <= size / size[0] / 2 + 1e-5)
    np.testing.assert_array_equal(priors.template_points(SIZES[:1])[0], template[0])  # fixed seeds
    partial = template[0][template[0][:, 1] > 0.05][:300]
    mirrored = mirror_symmetry(partial)
    union = priors.thinned_union([mirrored, template[0]])
    assert union.shape == (2048, 3)
    everything = np.concatenate([mirrored, template[0]])
    assert float(metrics.nearest_sq_distance(union, everything).max()) == 0.0   # a subset of the union
    assert len(np.unique(union, axis=0)) == 2048                                  # FPS: no repeats
    outs = priors.prior_outputs(partial, SIZES[0])
    assert set(outs) == {"box_fill", "template", "mirror_template"}
    assert all(v.shape == (2048, 3) for v in outs.values())
    np.testing.assert_array_equal(outs["mirror_template"], union)   # the prior is that union
    np.testing.assert_array_equal(priors.mirror_template(partial, SIZES[0]), union)


def test_grid_nearest_matches_brute_force():
    rng = np.random.default_rng(3)
    for n_target in (1, 7, 300, 5000):
        target = (rng.normal(size=(n_target, 3)) * [0.5, 0.2, 0.01]).astype(np.float32)  # flat, like one side
        query = (rng.uniform(-1.5, 1.5, (2000, 3))).astype(np.float32)
        np.testing.assert_allclose(nearest.nearest_sq(query, target),
                                   metrics.nearest_sq_distance(query, target).numpy(), rtol=1e-5, atol=1e-7)
    assert np.all(np.isinf(nearest.nearest_sq(query, np.zeros((0, 3)))))


def _plane() -> np.ndarray:
    """A wall x = 5 (normalised units) between y, z = -1 and 1, seen from the origin."""
    g = np.arange(-1.0, 1.0, 0.01)
    y, z = np.meshgrid(g, g)
    return np.stack([np.full(y.size, 5.0), y.ravel(), z.ravel()], 1).astype(np.float32)


def test_observed_and_precision_on_a_wall_seen_from_one_pose():
    wall = _plane()
    images = observed.range_images([(np.zeros(3), wall)])
    on_wall, in_front, behind, aside = [5.0, 0.1, 0.1], [4.5, 0.1, 0.1], [5.5, 0.1, 0.1], [5.0, 3.0, 0.0]
    points = np.array([on_wall, in_front, behind, aside], np.float32)
    np.testing.assert_array_equal(observed.judged(points, images), [True, True, False, False])
    # within tau of the surface still counts as on it; beyond tau behind it is hidden
    np.testing.assert_array_equal(observed.judged(np.array([[5.015, 0, 0], [5.05, 0, 0]], np.float32), images),
                                  [True, False])
    two = observed.two_sided(points, wall, images)
    assert two.precision == pytest.approx(0.5)      # judged: on_wall (precise) and in_front (0.5 away)
    assert two.judged_share == pytest.approx(0.5)
    assert two.recall < 0.01                        # 4 points cover almost none of the wall
    assert two.f_score == pytest.approx(2 * 0.5 * two.recall / (0.5 + two.recall))
    full = observed.two_sided(wall, wall, images)
    assert (full.precision, full.judged_share, full.recall, full.f_score) == (1.0, 1.0, 1.0, 1.0)
    # no pose: nothing judged, precision undefined
    empty = observed.range_images([])
    assert not observed.judged(points, empty).any()
    assert np.isnan(observed.two_sided(points, wall, empty).precision)
    np.testing.assert_array_equal(observed.pose_subset(40, 16), np.unique(np.round(np.linspace(0, 39, 16))))
    assert "judged" in observed.OBSERVED_DEFINITION


def test_box_noise_is_reproducible_and_has_the_stated_spread():
    box = Box3D((10.0, -3.0, 0.8), (4.5, 1.8, 1.5), 0.3, "car", 7)
    noise = box_noise.BoxNoise()
    a = box_noise.noisy_box(box, noise, (7, 12, 0))
    assert a == box_noise.noisy_box(box, noise, (7, 12, 0))                       # same key, same box
    assert a != box_noise.noisy_box(box, noise, (7, 12, 1))
    assert a != box_noise.noisy_box(box, box_noise.BoxNoise(seed=1), (7, 12, 0))
    assert a.instance_id == 7 and a.label == "car"
    many = [box_noise.noisy_box(box, noise, (7, k, 0)) for k in range(3000)]
    centres = np.array([b.center for b in many]) - box.center
    sizes = np.array([b.size for b in many]) / box.size - 1
    yaws = np.degrees(np.array([b.yaw for b in many]) - box.yaw)
    np.testing.assert_allclose(centres.std(0), [0.15, 0.15, 0.05], rtol=0.08)
    np.testing.assert_allclose(sizes.std(0), 0.05, rtol=0.08)
    assert yaws.std() == pytest.approx(4.0, rel=0.08)
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (100, 3)).astype(np.float32)
    np.testing.assert_allclose(box_noise.reframe(points, box, box), points, atol=1e-6)
    back = box_noise.reframe(box_noise.reframe(points, a, box), box, a)
    np.testing.assert_allclose(back, points, atol=1e-5)


def test_pandaset_evaluation_small(shared_data):
    from gd_completion.evaluation.pandaset_eval import evaluate_pandaset
    from gd_completion.evaluation.report import pandaset_section
    from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint

    root = shared_data / "pandaset-002"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    torch.manual_seed(0)
    model, prep = load_checkpoint(DEFAULT_WEIGHTS)
    result = evaluate_pandaset(model, root, preprocessing=prep, max_vehicles=3, max_frames_per_vehicle=3,
                               random_points=5000)
    items = result.items
    assert result.n_vehicles >= 2 and len(items) >= 6
    assert {i.sensor for i in items} <= {0, 1}
    for item in items:
        assert set(item.coverage) == set(BASELINE_NAMES) == set(item.noisy_coverage) == set(item.f_score)
        assert item.n_points >= 50 and item.fidelity["input"] == 0.0
        for name in ("box_fill", "template", "mirror_template", "generation", "ggd"):
            assert item.output_points[name] == 2048
        assert item.output_points["input"] >= item.n_points    # the input above the ground and its band's points
        assert item.output_points["mirror"] == 2 * item.output_points["input"]
        assert item.precision["input"] > 0.9 and item.judged["input"] > 0.5   # raw points lie on the reference
    assert any(item.output_points["input"] > item.n_points for item in items)   # tyres below the ground cut
    mean = {n: np.mean([i.coverage[n] for i in items]) for n in BASELINE_NAMES}
    assert mean["box_fill"] < mean["input"]
    assert mean["mirror"] < mean["input"]
    noisy = {n: np.mean([i.noisy_coverage[n] for i in items]) for n in BASELINE_NAMES}
    assert noisy["box_fill"] > mean["box_fill"]                                  # a wrong box costs coverage
    text = pandaset_section(result, 256, 1024)
    for name in BASELINE_NAMES:
        assert text.count(f"| {BASELINE_TITLES[name]} ") >= 6                    # every table has every method
    for heading in ("random reference", "voxel-uniform reference", "Fidelity x1e3", "Two-sided", "Box noise",
                    "by sensor"):
        assert heading in text
    assert result.worst and result.worst[0][0].endswith(f"cov {max(i.coverage['ggd_merge'] for i in items):.2f}")
