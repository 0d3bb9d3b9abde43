"""`benchmarks/heldout_code_fit.py` splits the network at its code faithfully, and its fit moves P_s to the truth."""
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
from heldout_code_fit import Frozen, fitted  # noqa: E402

CONFIG = replace(TINY, box_conditioning=True, box_refinement=True, refiner_widths=(8, 16), refiner_hidden=(16,))


def _model() -> GGDNet:
    torch.manual_seed(0)
    model = GGDNet(CONFIG)
    with torch.no_grad():   # a refiner and a box input that do something, so that a missed frame or box shows
        for p in [*model.refiner.parameters(), model.encoder.box_in.weight]:
            p.add_(0.2 * torch.randn_like(p))
    model.eval_batch_chunk = 0   # the whole batch at once, as Frozen runs it
    return model.eval()


def test_frozen_network_with_the_encoders_code_computes_the_forward_pass():
    model = _model()
    partial = torch.rand(3, CONFIG.num_input, 3) - 0.5
    sizes = np.array([[4.5, 1.8, 1.5], [5.0, 2.0, 1.9], [12.0, 2.5, 3.5]])
    expected = model(partial, box_shape(sizes))
    assert expected.box_frame is not None and expected.box_frame.abs().max() > 1e-3   # the refiner moved the box
    frozen = Frozen(model, partial, sizes)
    completion, _ = frozen.completion(frozen.code)
    torch.testing.assert_close(completion, expected.completion, atol=1e-5, rtol=0)
    torch.testing.assert_close(frozen.coarse(frozen.code), expected.coarse, atol=1e-5, rtol=0)
    other = frozen.completion(frozen.code + 1.0)[0]   # the code reaches the output
    assert (other - completion).abs().max() > 1e-3


def test_fitting_the_code_to_the_truth_brings_p_s_nearer_it():
    model = _model()
    partial = torch.rand(2, CONFIG.num_input, 3) - 0.5
    sizes = np.array([[4.5, 1.8, 1.5], [5.0, 2.0, 1.9]])
    frozen = Frozen(model, partial, sizes)
    truth = torch.rand(2, 200, 3) - 0.5
    before = chamfer_l2(frozen.coarse(frozen.code), truth)
    code = fitted(frozen, lambda coarse, offset: chamfer_l2(coarse, truth), 30)
    after = chamfer_l2(frozen.coarse(code), truth).detach()
    assert (after < 0.9 * before.detach()).all()
    through = fitted(frozen, lambda points, offset: chamfer_l2(points, truth), 10, through=True)
    p_o = frozen.completion(through)[0][:, CONFIG.num_control:]
    start = frozen.completion(frozen.code)[0][:, CONFIG.num_control:]
    assert (chamfer_l2(p_o, truth) < chamfer_l2(start, truth)).all()
    assert all(not p.requires_grad for p in model.parameters())   # the network itself stays as it was
