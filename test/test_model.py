"""GGD-Net model tests: ops, shapes, gradients, losses on hand-computed values, checkpoints."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gd_completion.errors import CheckpointError
from gd_completion.model import (
    GGDConfig,
    GGDNet,
    chamfer_l2,
    chamfer_l2_directional,
    farthest_point_sample,
    load_model,
    read_checkpoint_metadata,
    save_checkpoint,
)
from gd_completion.model.losses import ggd_loss, laplacian_coordinates, laplacian_loss, smooth_l1
from gd_completion.model.network import LinearBN
from gd_completion.model.ops import ball_group, knn_graph, smallest_k, window_knn

TINY = GGDConfig(num_input=64, num_output=96, num_control=32, encoder_h0=(16, 32), encoder_h1=(32,),
                 code_hidden=(32,), code_dim=32, tree_arity=(4, 4, 4), tree_node_dim=8, tree_hidden=(32, 16),
                 radius=0.2, ball_m=4, local_widths=(8, 8), knn_k=4, gcn_width=16, gcn_blocks=1)


def _cloud(b: int, n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, n, 3, generator=g) - 0.5


def test_default_config_sizes_and_roundtrip():
    cfg = GGDConfig()
    assert (cfg.num_input, cfg.num_output, cfg.num_control, cfg.num_coarse) == (1024, 2048, 256, 1792)
    assert GGDConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="tree_arity"):
        GGDConfig(tree_arity=(8, 8))
    with pytest.raises(ValueError, match="unknown"):
        GGDConfig.from_dict({**cfg.to_dict(), "bogus": 1})


def test_forward_shapes_and_completion_layout():
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    x = _cloud(3, 64)
    out = model(x)
    assert out.coarse.shape == (3, 64, 3)
    assert out.control.shape == (3, 32, 3) and out.control_deformed.shape == (3, 32, 3)
    assert out.completion.shape == (3, 96, 3) and out.generated.shape == (3, 96, 3)
    assert torch.equal(out.completion[:, :32], out.control_deformed)
    assert torch.equal(out.generated, torch.cat([out.control, out.coarse], 1))
    assert torch.equal(model.generate(x), out.generated)
    assert torch.isfinite(out.completion).all()
    # eval mode is deterministic
    assert torch.equal(model(x).completion, out.completion)


def test_batched_equals_single_bitwise_in_eval():
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    x = _cloud(3, 64, seed=11)
    both = model(x).completion
    for i in range(3):
        assert torch.equal(model(x[i:i + 1]).completion, both[i:i + 1])


def test_control_points_are_fps_subset_of_input():
    model = GGDNet(TINY).eval()
    x = _cloud(2, 64, seed=3)
    out = model(x)
    idx = farthest_point_sample(x, 32)
    assert torch.equal(out.control_index, idx)
    assert torch.equal(out.control, torch.gather(x, 1, idx.unsqueeze(-1).expand(-1, -1, 3)))
    assert all(len(set(row.tolist())) == 32 for row in idx)


def test_gradient_reaches_every_parameter_group():
    torch.manual_seed(0)
    model = GGDNet(TINY).train()
    x, gt = _cloud(4, 64, 1), _cloud(4, 96, 2)
    losses = ggd_loss(model(x), gt, lam=3.0)
    losses["total"].backward()
    for group in ("encoder", "decoder", "local", "deform"):
        params = [(n, p) for n, p in model.named_parameters() if n.startswith(group)]
        assert params, group
        for name, p in params:
            assert p.grad is not None and p.grad.abs().sum() > 0, f"no gradient for {name}"


def test_fps_picks_farthest_point():
    pts = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0.1, 0, 0], [5, 0, 0], [2.6, 0, 0]]])
    assert farthest_point_sample(pts, 3).tolist() == [[0, 3, 4]]
    assert farthest_point_sample(pts, 5)[0, :4].tolist() == [0, 3, 4, 1]
    # nested prefixes
    x = _cloud(2, 200, seed=5)
    assert torch.equal(farthest_point_sample(x, 50), farthest_point_sample(x, 120)[:, :50])


def test_fps_duplicates_and_oversampling():
    pts = torch.tensor([[[1.0, 1, 1]] * 4 + [[2.0, 2, 2]] * 3])
    idx = farthest_point_sample(pts, 10)
    assert idx.shape == (1, 10) and idx.min() >= 0 and idx.max() < 7
    assert set(pts[0, idx[0, :2]][:, 0].tolist()) == {1.0, 2.0}
    same = torch.zeros(2, 30, 3)
    idx = farthest_point_sample(same, 8)
    assert idx.shape == (2, 8) and idx.max() < 30
    big = torch.rand(1, 3000, 3)   # low-memory path (no dense matrix)
    big[0, 1500:] = big[0, :1500]  # every point twice
    idx = farthest_point_sample(big, 64)
    assert len(set((idx[0] % 1500).tolist())) == 64


def test_knn_graph_recomputed_and_correct():
    pts = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [3.5, 0, 0]]])
    assert sorted(knn_graph(pts, 1)[0, :, 0].tolist()) == [0, 1, 2, 3]
    assert knn_graph(pts, 1)[0, :, 0].tolist() == [1, 0, 3, 2]
    model = GGDNet(TINY).eval()
    x = _cloud(1, 64, 7)
    k1 = model(x).neighbours
    k2 = model(x * torch.tensor([1.0, 3.0, 0.2])).neighbours
    assert not torch.equal(k1, k2)
    assert torch.equal(k1, knn_graph(model(x).generated, TINY.knn_k, TINY.knn_margin))


def test_smallest_k_exact():
    d = torch.rand(5, 7, 300)
    d[0, 0, :10] = 0.5   # ties
    val, idx = smallest_k(d, 8)
    exp = d.topk(8, -1, largest=False).values
    assert torch.equal(val, exp) and torch.equal(d.gather(-1, idx), exp)


def test_smallest_k_of_sparse_rows_indexes_only_real_columns():
    """Rows with fewer than k finite entries (a window holding fewer than k candidates) over widths that are
    not a multiple of the group: the inf slots must still name real columns (a padding column crashed the
    window search's gather on CUDA)."""
    g = torch.Generator().manual_seed(0)
    for w in range(64, 300, 7):
        d = torch.full((16, 32, w), float("inf"))
        finite = torch.rand(16, 32, w, generator=g) < 0.02
        d[finite] = torch.rand(int(finite.sum()), generator=g)
        val, idx = smallest_k(d, 6)
        assert int(idx.min()) >= 0 and int(idx.max()) < w
        assert torch.equal(val, d.topk(6, -1, largest=False).values)
        real = torch.isfinite(val)
        assert torch.equal(d.gather(-1, idx)[real], val[real])

def test_window_knn_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(2, 700, 3, generator=g)
    q = q / q.norm(dim=-1, keepdim=True) * torch.tensor([0.5, 0.22, 0.2])
    r = q[:, :300] + 0.01
    d_full = torch.cdist(q, r).pow(2)
    exp_d, exp_i = d_full.topk(5, -1, largest=False)
    dist, idx = window_knn(q, r, 5, margin=10.0)          # window covers everything: exact
    assert torch.allclose(dist, exp_d, atol=1e-5) and torch.equal(idx, exp_i)
    dist, idx = window_knn(q, r, 5, margin=0.08)           # exact wherever the 5th neighbour is within 0.08
    ok = exp_d[..., -1] < 0.08 ** 2
    assert ok.float().mean() > 0.5
    assert torch.allclose(dist[ok], exp_d[ok], atol=1e-5)
    # self-excluded kNN graph
    full = knn_graph(q, 4)
    win = knn_graph(q, 4, margin=10.0)
    assert torch.equal(full.sort(-1).values, win.sort(-1).values)
    assert not (win == torch.arange(700).view(1, -1, 1)).any()
    # ball query via windows is exact inside the radius
    has_ball = torch.cdist(q, r).amin(-1) < 0.05 - 1e-4      # rows with a point inside the radius
    assert has_ball.float().mean() > 0.3
    assert torch.equal(ball_group(q, r, 0.05, 6, window=True)[has_ball], ball_group(q, r, 0.05, 6)[has_ball])


def test_ball_group_radius_padding():
    centers = torch.tensor([[[0.0, 0, 0]]])
    pts = torch.tensor([[[0.1, 0, 0], [0.05, 0, 0], [3, 0, 0], [0.2, 0, 0]]])
    assert ball_group(centers, pts, 0.15, 3).tolist() == [[[1, 0, 1]]]
    assert ball_group(centers, pts, 0.25, 3).tolist() == [[[1, 0, 3]]]


def test_chamfer_hand_computed():
    a = torch.tensor([[[0.0, 0, 0], [1, 0, 0]]])
    b = torch.tensor([[[0.0, 0, 1], [2, 0, 0], [1, 1, 0]]])
    # a->b: 0 -> min(1, 4, 2)=1 ; 1 -> min(2, 1, 1)=1  => mean 1
    # b->a: (0,0,1) -> 1 ; (2,0,0) -> 1 ; (1,1,0) -> 1 => mean 1
    ab, ba = chamfer_l2_directional(a, b)
    assert ab.item() == pytest.approx(1.0) and ba.item() == pytest.approx(1.0)
    c = torch.tensor([[[0.0, 0, 0], [0, 3, 0]]])
    d = torch.tensor([[[0.0, 1, 0]]])
    # c->d: 1, 4 -> 2.5 ; d->c: 1 -> 1  => 3.5
    assert chamfer_l2(c, d).item() == pytest.approx(3.5)
    assert chamfer_l2(torch.cat([a, a]), torch.cat([a, a])).tolist() == [0.0, 0.0]
    # matches the brute-force definition, gradient included, across chunk boundaries
    x = torch.rand(2, 300, 3, requires_grad=True)
    y = torch.rand(2, 200, 3)
    ref = torch.cdist(x, y).pow(2)
    expect = ref.amin(2).mean(1) + ref.amin(1).mean(1)
    got = chamfer_l2(x, y)
    assert torch.allclose(got, expect, atol=1e-6)
    g1, = torch.autograd.grad(got.sum(), x)
    g2, = torch.autograd.grad(expect.sum(), x)
    assert torch.allclose(g1, g2, atol=1e-5)
    from gd_completion.model.losses import nearest_indices
    ia, ib = nearest_indices(x, y, chunk_entries=1000)
    assert torch.equal(ia, ref.argmin(2)) and torch.equal(ib, ref.argmin(1))


def test_smooth_l1_hand_computed():
    # beta = 1/sigma^2 = 0.25 ; |0.1| -> 0.5*0.01/0.25 = 0.02 ; |1.0| -> 1 - 0.125 = 0.875
    pred = torch.tensor([[[0.1, 1.0, 0.0]]])
    assert smooth_l1(pred, torch.zeros_like(pred)).item() == pytest.approx(0.895)
    pred2 = torch.tensor([[[0.1, 0, 0], [0, 0, 0]]])
    assert smooth_l1(pred2, torch.zeros_like(pred2)).item() == pytest.approx(0.01)


def test_laplacian_loss_hand_computed():
    pts = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    knn = torch.tensor([[[1, 2], [0, 2], [0, 1]]])
    delta = laplacian_coordinates(pts, knn)
    assert delta[0, 0].tolist() == pytest.approx([-0.5, -0.5, 0])
    assert delta[0, 1].tolist() == pytest.approx([1.0, -0.5, 0])
    # translating everything keeps the shape
    assert laplacian_loss(pts + 0.3, pts, knn).item() == pytest.approx(0.0, abs=1e-12)
    moved = pts.clone()
    moved[0, 0, 2] = 1.0   # lift point 0 by 1 in z: delta_0 z += 1, delta_1 and delta_2 z -= 0.5
    assert laplacian_loss(moved, pts, knn).item() == pytest.approx((1 + 0.25 + 0.25) / 3)


def test_ggd_loss_terms():
    torch.manual_seed(0)
    model = GGDNet(TINY).eval()
    x, gt = _cloud(2, 64, 1), _cloud(2, 96, 2)
    out = model(x)
    l0, l3 = ggd_loss(out, gt, lam=0.0), ggd_loss(out, gt, lam=3.0)
    assert l0["cd_coarse"].item() == pytest.approx(1000 * chamfer_l2(out.coarse, gt).mean().item(), rel=1e-5)
    expect = l0["cd_coarse"] + 1000 * l0["control"] + 0.5 * l0["shape"]
    assert l0["total"].item() == pytest.approx(expect.item(), rel=1e-5)
    assert (l3["total"] - l0["total"]).item() == pytest.approx(3 * l0["cd_fine"].item(), rel=1e-4)


def test_checkpoint_roundtrip(tmp_path):
    torch.manual_seed(1)
    model = GGDNet(TINY).train()
    model(_cloud(4, 64))   # update BN running statistics
    model.eval()
    path = save_checkpoint(tmp_path / "m.pt", model, epoch=3, note="hi", metrics={"cd": 1.5})
    loaded = load_model(path)
    x = _cloud(2, 64, 9)
    assert loaded.config == TINY and not loaded.training
    assert torch.equal(loaded(x).completion, model(x).completion)
    meta = read_checkpoint_metadata(path)
    assert meta["epoch"] == 3 and meta["note"] == "hi" and meta["metrics"] == {"cd": 1.5}
    assert meta["config"] == TINY.to_dict() and "state_dict" not in meta


def test_checkpoint_errors(tmp_path):
    with pytest.raises(CheckpointError, match="missing.pt.*not found"):
        load_model(tmp_path / "missing.pt")
    model = GGDNet(TINY)
    good = save_checkpoint(tmp_path / "good.pt", model)
    raw = good.read_bytes()
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CheckpointError, match="trunc.pt"):
        load_model(trunc)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00not a checkpoint" * 10)
    with pytest.raises(CheckpointError, match="junk.pt"):
        load_model(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(CheckpointError, match="other.pt.*not a gd_completion"):
        load_model(other)
    data = torch.load(good, weights_only=True)
    data["config"]["gcn_width"] = 24
    bad = tmp_path / "mismatch.pt"
    torch.save(data, bad)
    with pytest.raises(CheckpointError, match="mismatch.pt.*do not match"):
        load_model(bad)
    data["config"]["tree_arity"] = [3, 3]
    torch.save(data, bad)
    with pytest.raises(CheckpointError, match="mismatch.pt.*invalid config"):
        load_model(bad)


def test_default_size_forward_backward():
    torch.manual_seed(0)
    model = GGDNet().train()
    x = _cloud(2, 1024)
    out = model(x)
    assert out.completion.shape == (2, 2048, 3) and out.coarse.shape == (2, 1792, 3)
    ggd_loss(out, _cloud(2, 2048, 4), lam=3.0)["total"].backward()
    assert all(p.grad is not None for p in model.parameters())
    assert math.isfinite(float(out.completion.detach().abs().max()))


def test_box_conditioning_starts_as_the_unconditioned_model(tmp_path):
    """Zero-initialised box input: a warm start from an unconditioned checkpoint keeps its outputs exactly;
    the box shape is required."""
    from dataclasses import replace

    from gd_completion.model.checkpoint import save_checkpoint
    from gd_completion.model.network import box_shape
    from gd_completion.train import warm_start

    torch.manual_seed(0)
    plain = GGDNet(TINY).eval()
    save_checkpoint(tmp_path / "plain.pt", plain)
    cond = GGDNet(replace(TINY, box_conditioning=True)).eval()
    assert warm_start(cond, tmp_path / "plain.pt") == ["encoder.box_in.weight"]
    x = torch.rand(3, TINY.num_input, 3) - 0.5
    shapes = box_shape([[4.5, 1.8, 1.5], [6.0, 2.4, 2.9], [12.0, 2.5, 3.1]])
    with torch.inference_mode():
        assert torch.equal(cond(x, shapes).completion, plain(x).completion)
        assert torch.equal(plain(x, shapes).completion, plain(x).completion)   # ignored without conditioning
        with pytest.raises(ValueError, match="box_shape"):
            cond(x)
        with pytest.raises(ValueError, match="box_shape"):
            cond(x, shapes[:2])
    np.testing.assert_allclose(shapes.numpy(), [[0.4, 1 / 3], [0.4, 2.9 / 6], [2.5 / 12, 3.1 / 12]], rtol=1e-6)


def test_shape_basis_starts_as_the_plain_decoder_and_adds_its_weighted_shapes(tmp_path):
    """`shape_basis` K: a warm start from a checkpoint without it keeps its outputs exactly (the coefficients start at
    zero); with coefficients set, P_s moves by exactly their combination of the K learned shapes; it trains; a
    negative K is refused."""
    from dataclasses import replace

    from gd_completion.train import warm_start

    torch.manual_seed(0)
    plain = GGDNet(TINY).eval()
    save_checkpoint(tmp_path / "plain.pt", plain)
    based = GGDNet(replace(TINY, shape_basis=3)).eval()
    assert sorted(warm_start(based, tmp_path / "plain.pt")) == [
        "decoder.basis", "decoder.basis_weights.bias", "decoder.basis_weights.weight"]
    assert based.decoder.basis.shape == (3, TINY.num_coarse, 3) and based.decoder.basis.abs().max() > 0
    x = torch.rand(2, TINY.num_input, 3) - 0.5
    with torch.no_grad():
        assert torch.equal(based(x).coarse, plain(x).coarse)
        based.decoder.basis_weights.bias.copy_(torch.tensor([2.0, 0.0, -1.0]))
        moved = based(x).coarse - plain(x).coarse
    expected = 2.0 * based.decoder.basis[0] - based.decoder.basis[2]
    torch.testing.assert_close(moved, expected.expand_as(moved), atol=1e-6, rtol=0)
    based.train()
    based(x).coarse.square().sum().backward()
    assert based.decoder.basis.grad.abs().max() > 0 and based.decoder.basis_weights.weight.grad.abs().max() > 0
    assert GGDConfig.from_dict(based.config.to_dict()).shape_basis == 3
    with pytest.raises(ValueError, match="shape_basis"):
        replace(TINY, shape_basis=-1)


def test_mirrored_local_features_reach_the_unseen_side():
    """With mirror_local_features the balls around a point opposite the seen side group mirrored input points."""
    from dataclasses import replace

    from gd_completion.model.network import LocalFeatures, mirrored_source

    cfg = replace(TINY, mirror_local_features=True)
    g = torch.Generator().manual_seed(0)
    n = cfg.num_input
    seen = torch.rand(1, n, 3, generator=g) * torch.tensor([1.0, 0.05, 0.3]) + torch.tensor([-0.5, 0.17, -0.15])
    order = torch.arange(n).unsqueeze(0)
    source, source_order = mirrored_source(seen, order)
    assert source.shape == (1, 2 * n, 3) and torch.equal(source[0, n:, 1], -seen[0, :, 1])
    assert source_order[0, :4].tolist() == [0, n, 1, n + 1]
    opposite = seen[:, :5] * torch.tensor([1.0, -1.0, 1.0])     # where the unseen side would be
    idx = LocalFeatures(cfg).group(opposite, source, source_order)
    assert (idx[..., 0, :] >= n).all()                            # the r-ball holds mirrored points only
    plain = LocalFeatures(TINY).eval()
    mirrored = LocalFeatures(cfg).eval()
    mirrored.load_state_dict(plain.state_dict())
    with torch.inference_mode():
        assert not torch.equal(mirrored(opposite, seen, order), plain(opposite, seen, order))


def test_eval_linear_bn_folds_the_current_parameters():
    layer = LinearBN(5, 7)
    torch.nn.init.normal_(layer.bn.running_mean)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(40, 5, generator=g)

    def unfolded() -> torch.Tensor:
        with torch.no_grad():
            return torch.relu(F.batch_norm(layer.linear(x), layer.bn.running_mean, layer.bn.running_var,
                                           layer.bn.weight, layer.bn.bias, False, 0.0, layer.bn.eps))

    def inferred() -> torch.Tensor:
        with torch.inference_mode():
            out = layer(x)
        return out.clone()

    layer.eval()
    first = inferred()
    torch.testing.assert_close(first, unfolded())
    folded = layer._fold.cached
    assert folded is not None and not any(t.requires_grad or t.is_inference() for t in folded)
    copy.deepcopy(layer)                                                      # a cached fold is a plain tensor
    with torch.no_grad():
        layer.load_state_dict({k: v + 0.5 for k, v in layer.state_dict().items()})   # in-place copies
    torch.testing.assert_close(inferred(), unfolded())
    assert not torch.allclose(inferred(), first)
    layer.linear.weight.data.mul_(2.0)             # .data has its own version counter: clear_fold() refolds
    layer.clear_fold()
    torch.testing.assert_close(inferred(), unfolded())
    layer.train()                                  # a training step moves the running statistics
    layer(x + 3.0)
    layer.eval()
    torch.testing.assert_close(inferred(), unfolded())
    # eval mode with autograd folds every call: gradients reach the parameters, twice
    for _ in range(2):
        layer.zero_grad()
        layer(x).sum().backward()
        assert layer.linear.weight.grad is not None and layer.linear.weight.grad.abs().sum() > 0


def test_a_replaced_parameter_is_refolded_where_the_new_tensor_reuses_the_old_memory():
    """A parameter replaced by a new tensor, or given new `.data` (version 0; the allocator often hands it the freed
    block), is folded anew: the cache holds the storage it folded, so no new tensor can take its address."""
    layer = LinearBN(5, 7).eval()
    x = torch.randn(40, 5, generator=torch.Generator().manual_seed(1))
    for value in range(20):
        with torch.inference_mode():
            layer(x)
        if value % 2:
            layer.linear.weight.data = torch.full((7, 5), float(value))
        else:
            del layer.linear.weight
            layer.linear.weight = torch.nn.Parameter(torch.full((7, 5), float(value)))
        with torch.no_grad():
            expected = torch.relu(layer.bn(layer.linear(x)))
        with torch.inference_mode():
            torch.testing.assert_close(layer(x).clone(), expected)
