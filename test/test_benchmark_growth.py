"""`benchmarks/heldout_memorise.py`'s capacity probes start from a grown network that computes what the original did."""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from test_model import TINY

from gd_completion.model import GGDNet, load_model
from gd_completion.model.checkpoint import save_checkpoint

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
from heldout_memorise import grown  # noqa: E402


def test_grown_network_has_more_parameters_and_the_same_output(tmp_path):
    torch.manual_seed(0)
    small = GGDNet(TINY)
    with torch.no_grad():   # offsets large enough that a wrong copy shows
        for lin in (small.deform.out.self_lin, small.deform.out.nbr_lin):
            lin.weight.mul_(10.0)
    path = save_checkpoint(tmp_path / "small.pt", small.eval())
    partial = torch.rand(3, TINY.num_input, 3) - 0.5
    before = load_model(path)(partial)
    for changes in ({"gcn_blocks": 3}, {"gcn_width": 24}, {"tree_hidden": (48, 24)}, {"shape_basis": 4},
                    {"gcn_blocks": 2, "gcn_width": 32, "tree_hidden": (64, 16)}):
        big = load_model(grown(str(path), str(tmp_path / "big.pt"), **changes))
        assert all(getattr(big.config, k) == v for k, v in changes.items())
        assert big.num_parameters() > small.num_parameters()
        after = big(partial)
        assert (after.completion - after.generated).abs().max() > 1e-3   # the deformation is not idle
        torch.testing.assert_close(after.completion, before.completion, atol=1e-5, rtol=0)
        torch.testing.assert_close(after.coarse, before.coarse, atol=1e-5, rtol=0)
