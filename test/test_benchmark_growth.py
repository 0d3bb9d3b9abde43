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


def test_grown_network_has_more_parameters_the_same_output_and_every_part_trains(tmp_path):
    """Each growth computes what the small network did (to float rounding), and two plain gradient steps move every
    tensor of the grown network: no new part is stuck (a ReLU closed at zero would never pass a gradient)."""
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
        start = {name: p.detach().clone() for name, p in big.named_parameters()}
        big.train()
        optimizer = torch.optim.SGD(big.parameters(), lr=0.1)
        for _ in range(2):
            optimizer.zero_grad()
            big(partial).completion.square().sum().backward()
            optimizer.step()
        stuck = [name for name, p in big.named_parameters() if torch.equal(p, start[name])]
        assert not stuck, f"{changes}: never moved: {stuck}"
