"""`benchmarks/heldout_code_fit.py` splits the network at its code faithfully, and its fits move the points to the
truth without changing the network."""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from test_model import TINY

from gd_completion.model import GGDNet
from gd_completion.model.losses import chamfer_l2
from gd_completion.model.network import box_shape

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
from heldout_code_fit import Frozen, fitted, published  # noqa: E402

CONFIG = replace(TINY, box_conditioning=True, box_refinement=True, refiner_widths=(8, 16), refiner_hidden=(16,))
SIZES = np.array([[4.5, 1.8, 1.5], [5.0, 2.0, 1.9], [12.0, 2.5, 3.5]])


def _model() -> GGDNet:
    torch.manual_seed(0)
    model = GGDNet(CONFIG)
    with torch.no_grad():   # a refiner and a box input that do something, so that a missed frame or box shows
        for p in [*model.refiner.parameters(), model.encoder.box_in.weight]:
            p.add_(0.2 * torch.randn_like(p))
        for lin in (model.deform.out.self_lin, model.deform.out.nbr_lin):   # offsets large enough to show
            lin.weight.mul_(10.0)
    return model.eval()


def test_frozen_network_with_the_encoders_code_computes_the_pipelines_forward_pass():
    """The pipeline's eval forward runs one cloud at a time; the split runs the batch at once: the same points."""
    model = _model()
    partial = torch.rand(3, CONFIG.num_input, 3) - 0.5
    expected = model(partial, box_shape(SIZES))
    assert expected.box_frame is not None and expected.box_frame.abs().max() > 1e-3   # the refiner moved the box
    assert (expected.completion - expected.generated).abs().max() > 1e-2             # the G-ResNet moved P_g
    frozen = Frozen(model, partial, SIZES)
    completion, _ = frozen.completion(frozen.code)
    torch.testing.assert_close(completion, expected.completion, atol=1e-5, rtol=0)
    torch.testing.assert_close(frozen.coarse(frozen.code), expected.coarse, atol=1e-5, rtol=0)
    other = frozen.completion(frozen.code + 1.0)[0]   # the code reaches the output
    assert (other - completion).abs().max() > 1e-3


def test_the_g_resnet_takes_its_own_code_when_given_one():
    model = _model()
    frozen = Frozen(model, torch.rand(3, CONFIG.num_input, 3) - 0.5, SIZES)
    code = frozen.code + 0.5
    same = frozen.completion(code)[0]
    torch.testing.assert_close(frozen.completion(code, code)[0], same, atol=0, rtol=0)
    kept = frozen.completion(code, frozen.code)[0]
    assert (kept - same).abs().max() > 1e-3   # the G-ResNet's code changed its offsets
    p_g = torch.cat([frozen.control, model.decoder(code)], 1)   # the decoder's code is `code`, the G-ResNet's its own
    expected, _ = model.deformed(p_g, CONFIG.num_control, frozen.code, frozen.partial, frozen.order)
    torch.testing.assert_close(kept, frozen._back(expected), atol=0, rtol=0)


def test_fits_bring_the_points_nearer_the_truth_and_leave_the_network_as_it_was():
    model = _model()
    weights = {name: p.detach().clone() for name, p in model.state_dict().items()}
    partial = torch.rand(2, CONFIG.num_input, 3) - 0.5
    frozen = Frozen(model, partial, SIZES[:2])
    truth = torch.rand(2, 200, 3) - 0.5
    before = chamfer_l2(frozen.coarse(frozen.code), truth).detach()
    code = fitted(frozen, lambda coarse, offset: chamfer_l2(coarse, truth), 30)
    assert (chamfer_l2(frozen.coarse(code), truth).detach() < 0.9 * before).all()
    decayed = fitted(frozen, lambda coarse, offset: chamfer_l2(coarse, truth), 30, decay=True)
    assert (chamfer_l2(frozen.coarse(decayed), truth).detach() < 0.9 * before).all()
    assert not torch.equal(decayed, code)   # the schedule changed the steps
    through = fitted(frozen, lambda points, offset: chamfer_l2(points, truth), 10, through=True)
    nc = CONFIG.num_control
    start = frozen.completion(frozen.code)[0][:, nc:]
    assert (chamfer_l2(frozen.completion(through)[0][:, nc:], truth) < chamfer_l2(start, truth)).all()
    for name, tensor in model.state_dict().items():
        assert torch.equal(tensor, weights[name]), name


def test_published_keeps_the_measured_points_and_spaces_only_when_asked():
    model = _model()
    partial = torch.rand(2, CONFIG.num_input, 3) - 0.5
    frozen = Frozen(model, partial, SIZES[:2])
    clouds = [p.numpy() for p in partial]
    merged, raw, spaced = published(frozen, frozen.code, clouds, SIZES[:2], spacing="none")
    np.testing.assert_array_equal(raw, spaced)
    merged_spaced, raw_again, spaced_shipped = published(frozen, frozen.code, clouds, SIZES[:2])
    np.testing.assert_array_equal(raw, raw_again)
    assert np.abs(spaced_shipped - raw).max() > 1e-4
    assert merged.shape == raw.shape
    for cloud, out in zip(clouds, merged):   # the merge published measured points
        assert (np.linalg.norm(out[:, None] - cloud[None], axis=-1).min(1) == 0).any()
