"""Evaluation: metrics against hand-computed values, baselines, PandaSet aggregates, a tiny evaluate run."""
from __future__ import annotations

import numpy as np
import pytest
import torch

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
    generated, completion = baselines.network_outputs(model, clouds, max_batch=2)
    assert generated.shape == completion.shape == (3, 256, 3)
    np.testing.assert_allclose(baselines.generation_only(model, clouds), generated, atol=1e-5)
    np.testing.assert_allclose(baselines.ggd_net(model, clouds[1]), completion[1], atol=1e-5)
    # The first N_c points of P_g are FPS control points copied from the (resampled) input.
    assert float(metrics.fidelity(generated[2, :TINY.num_control], clouds[2])) < 1e-10
    assert not np.allclose(generated, completion)
