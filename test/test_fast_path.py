"""The compiled CPU kernels against the torch path, and batch independence of every result."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from gd_completion import kernels
from gd_completion.cell_grid import bucket_points
from gd_completion.evaluation.baselines import published_outputs
from gd_completion.model import chamfer_l2, farthest_point_sample
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.network import box_shape
from gd_completion.model.ops import _nearest_k, ball_group, knn_graph, torch_kernels, window_knn
from gd_completion.pipeline import VehicleCompleter
from gd_completion.synth.dataset import build_dataset


@pytest.fixture(scope="module")
def model():
    return load_model(DEFAULT_WEIGHTS)


@pytest.fixture(scope="module")
def scans(model) -> dict:
    """64 simulated lidar scans of procedural vehicles, cropped and normalised as the node does (at the
    shipped model's input size, so a batched forward sees what the pipeline feeds it)."""
    return build_dataset(64, seed=8080, n_input=model.config.num_input, n_gt=2048)


def _same_up_to_exact_ties(query: torch.Tensor, ref: torch.Tensor, fast: tuple[torch.Tensor, torch.Tensor],
                           reference: tuple[torch.Tensor, torch.Tensor]) -> None:
    """Distances bitwise equal, and each path's indices really are at those distances: where the indices
    differ, the two candidates are at exactly the same distance (an exact tie)."""
    (d_fast, i_fast), (d_ref, i_ref) = fast, reference
    assert torch.equal(d_fast, d_ref)
    finite = torch.isfinite(d_ref)
    for idx in (i_fast, i_ref):
        picked = torch.gather(ref, 1, idx.reshape(idx.shape[0], -1, 1).expand(-1, -1, 3)).view(idx.shape + (3,))
        diff = query.unsqueeze(2) - picked
        d = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]
        assert torch.equal(d[finite], d_ref[finite])
    assert (i_fast == i_ref).float().mean() > 0.5     # ties are the exception, not the rule


def test_kernels_match_torch_searches(scans):
    x = torch.from_numpy(scans["partial"][:32])
    g = torch.Generator().manual_seed(1)
    queries = torch.cat([x, x + 0.01 * torch.randn(x.shape, generator=g)], 1)   # 2048 points, like P_g
    fps = farthest_point_sample(x, 512)
    with torch_kernels():
        assert torch.equal(fps, farthest_point_sample(x, 512))
    cases = [
        (queries, queries, {"k": 8, "margin": 0.08, "exclude_self": True}),   # the kNN graph over P_g
        (queries, x, {"k": 8, "margin": 0.05}),                            # the ball query at scale 1
        (queries, x[:, :256], {"k": 8, "margin": 0.1}),
        (queries[:, :60], x[:, :40], {"k": 8, "margin": 0.05}),           # tiny: searched whole
    ]
    for query, ref, options in cases:
        fast = window_knn(query, ref, block=32, **options)
        with torch_kernels():
            _same_up_to_exact_ties(query, ref, fast, window_knn(query, ref, block=32, **options))
    for query, ref, exclude_self in ((queries[:4], queries[:4], True), (queries[:4], x[:4, :64], False)):
        fast = _nearest_k(query, ref, 8, None, 0, exclude_self)                # brute force: graph, ball at 4r
        with torch_kernels():
            _same_up_to_exact_ties(query, ref, fast, _nearest_k(query, ref, 8, None, 0, exclude_self))


def test_bucket_points_groups_points_by_their_cell():
    """The cell step shared by the three grid searches: row-major cells, the last cell of an axis takes what
    lies beyond it, an infinite width puts every point in cell 0 of its axis, input order kept within a cell."""
    pts = np.array([[0.0, 5.0, 0.0], [0.95, -3.0, 0.9], [1.0, 0.0, 0.0], [2.5, 0.0, 1.5], [0.2, 1.0, 0.1],
                    [9.0, 0.0, 0.0], [0.5, 0.0, 7.0]], np.float32)
    start, order = bucket_points(pts, np.zeros(3), np.array([1.0, np.inf, 1.0]), np.array([3, 1, 2], np.int64))
    cells = [order[start[c]:start[c + 1]].tolist() for c in range(6)]
    assert cells == [[0, 1, 4], [6], [2], [], [5], [3]]   # cell = (x * 1 + y) * 2 + z


def test_grid_search_of_the_knn_graph_matches_the_window_search(scans):
    x = torch.from_numpy(scans["partial"][:8])
    g = torch.Generator().manual_seed(2)
    noisy = torch.cat([x, x + 0.01 * torch.randn(x.shape, generator=g)], 1)
    spread = noisy * torch.tensor([40.0, 1.0, 1.0])          # a stretched cloud: the grid coarsens its cells
    repeated = torch.cat([x, x[:, :256]], 1)                   # exact duplicates: ties everywhere
    sparse = noisy[:, ::8] * 3.0                               # many k-th neighbours beyond the margin
    for points in (noisy, spread, repeated, sparse):
        for k in (1, 6, 8):
            grid = window_knn(points, points, k, 0.08, block=32, exclude_self=True, grid=True)
            with torch_kernels():
                _same_up_to_exact_ties(points, points, grid,
                                       window_knn(points, points, k, 0.08, block=32, exclude_self=True))
    tiny = noisy[:, :40]                                         # searched whole: the grid without a window
    for k in (1, 6):
        grid = window_knn(tiny, tiny, k, 0.08, block=32, exclude_self=True, grid=True)
        with torch_kernels():
            _same_up_to_exact_ties(tiny, tiny, grid, window_knn(tiny, tiny, k, 0.08, block=32, exclude_self=True))
    # a non-finite point has no grid cell: the window search answers, indices stay in range
    broken = noisy[:1].clone()
    broken[0, 5] = float("nan")
    broken[0, 9] = float("inf")
    idx = window_knn(broken, broken, 6, 0.08, block=32, exclude_self=True, grid=True)[1]
    assert idx.shape == (1, broken.shape[1], 6) and 0 <= int(idx.min()) and int(idx.max()) < broken.shape[1]
    # queries a rounding error from a cell border (their cell and the border are computed apart)
    border = np.zeros((1, 4, 3), np.float32)                   # (tiny: window_knn would search it whole)
    border[0, :, 0] = [-1.0, -5e-17, -5.6e-17, -4e-17]
    on_grid = kernels.knn(border, border, 1, 4 / 3, 32, True, True, 1.0)
    np.testing.assert_array_equal(on_grid[0], kernels.knn(border, border, 1, 4 / 3, 32, True, True, 0.0)[0])
    far = noisy[:1].clone()
    far[0, 0] = 1e30                                           # one absurd point: coarse cells, no overflow
    grid = window_knn(far, far, 6, 0.08, block=32, exclude_self=True, grid=True)
    with torch_kernels():
        _same_up_to_exact_ties(far, far, grid, window_knn(far, far, 6, 0.08, block=32, exclude_self=True))


def _ball_distances(centers: torch.Tensor, points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Squared distance (B, Q, m) of each ball slot's point to its center, in the searches' arithmetic."""
    picked = torch.gather(points, 1, idx.reshape(idx.shape[0], -1, 1).expand(-1, -1, 3)).view(idx.shape + (3,))
    diff = centers.unsqueeze(2) - picked
    return diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]


def test_ball_query_kernel_matches_the_torch_ball_groups(scans):
    """The compiled ball query (a grid for the balls, the window scan for the nearest point of empty ones) picks
    points at exactly the distances the torch path's picks are at, slot by slot: the same indices up to exact
    ties, in every case the model meets and where the grid cannot serve."""
    x = torch.from_numpy(scans["partial"][:8])
    g = torch.Generator().manual_seed(3)
    centers = torch.cat([x, x + 0.05 * torch.randn(x.shape, generator=g), 0.6 * torch.rand(x.shape, generator=g)
                         - 0.3], 1)   # on the scan, near it, and far from it (empty balls: padding only)
    mirrored = torch.cat([x, x * torch.tensor([1.0, -1.0, 1.0])], 1)           # scale 1: exact duplicates, ties
    broken = x.clone()
    broken[0, 3] = float("nan")                                                # no grid: the scan answers
    far = x.clone()
    far[:, 0] = 1e30                                                           # an outlier packs the grid
    stretch = torch.tensor([40.0, 1.0, 1.0])                                   # the grid coarsens its cells
    cases = [(centers, mirrored, 0.05, True, 4), (centers, x[:, :128], 0.1, False, 4), (centers, x, 0.05, True, 8),
             (centers[:, :40], x[:, :30], 0.05, True, 4),                      # tiny: searched whole
             (centers, x[:, :3], 0.1, False, 4),                               # fewer points than m: padded
             (centers * stretch, x * stretch, 0.05, True, 8),
             (centers, far, 0.05, True, 4), (centers[:1], broken[:1], 0.05, True, 4)]
    for query, points, radius, window, m in cases:
        fast = ball_group(query, points, radius, m, window=window)
        with torch_kernels():
            reference = ball_group(query, points, radius, m, window=window)
        assert fast.shape == reference.shape == query.shape[:2] + (m,)
        d_fast, d_ref = _ball_distances(query, points, fast), _ball_distances(query, points, reference)
        finite = torch.isfinite(d_ref)
        assert torch.equal(finite, torch.isfinite(d_fast)) and torch.equal(d_fast[finite], d_ref[finite])
        assert (fast == reference).float().mean() > 0.5
        inside = d_ref[finite] <= radius * radius
        assert 0 < inside.float().mean() < 1 or len(points[0]) <= 3 or not torch.isfinite(points).all()
    with pytest.raises(ValueError, match="ball_query"):          # the kernel's own contract, for direct callers
        kernels.ball_query(x[:1].numpy(), x[:1, :3].numpy(), 4, 0.05, 32, True)
    with pytest.raises(ValueError, match="ball_query"):
        kernels.ball_query(x[:1].numpy(), x[:1].numpy(), 4, -0.05, 32, True)


def test_kernel_window_edge_cases():
    # fewer candidates in the window than k: distance inf and the ref point at the window's start, in both paths
    ref = torch.tensor([[[0.0, 0, 0], [0.01, 0, 0]] + [[5.0 + i, 0, 0] for i in range(200)]])
    query = torch.tensor([[[0.003, 0, 0]] * 70])
    fast = window_knn(query, ref, 4, 0.05, block=32)
    with torch_kernels():
        _same_up_to_exact_ties(query, ref, fast, window_knn(query, ref, 4, 0.05, block=32))
    assert torch.isinf(fast[0][0, 0, 2:]).all() and (fast[1][0, :, 2:] == 0).all()
    # duplicates and one-point clouds
    same = torch.zeros(1, 100, 3)
    assert farthest_point_sample(same, 8)[0].tolist() == [0] * 8
    assert knn_graph(torch.zeros(1, 1, 3), 4).shape == (1, 1, 0)


def _shapes(scans) -> torch.Tensor:
    return box_shape(scans["size"])


def test_fast_path_equals_torch_path_on_32_scans(scans, model):
    x = torch.from_numpy(scans["partial"][:32])
    gt = torch.from_numpy(scans["complete"][:32])
    shapes = _shapes(scans)[:32]
    with torch.inference_mode():
        fast = model(x, shapes).completion
        with torch_kernels():
            reference = model(x, shapes).completion
    assert (fast - reference).abs().max().item() <= 1e-3
    cd_fast = chamfer_l2(fast, gt).mean().item() * 1e4
    cd_ref = chamfer_l2(reference, gt).mean().item() * 1e4
    assert f"{cd_fast:.3g}" == f"{cd_ref:.3g}", (cd_fast, cd_ref)


def test_vehicle_alone_equals_vehicle_among_63_others(scans, model):
    partials = list(scans["partial"])        # 64 vehicles
    together = VehicleCompleter(model, threads=2)
    try:
        frame = together.complete_normalized(partials, scans["size"])
    finally:
        together.close()
    alone = VehicleCompleter(model, threads=1)
    for i in (0, 17, 40, 63):
        assert np.array_equal(alone.complete_normalized([partials[i]], scans["size"][i:i + 1])[0], frame[i])
    with torch.inference_mode():              # one batched forward and the same merge: the same bits as well
        batched = model(torch.from_numpy(scans["partial"]), _shapes(scans)).completion.numpy()
    evaluated = published_outputs(model, partials, scans["size"], max_batch=64)   # the evaluation's path
    assert np.array_equal(evaluated.raw, batched)
    assert np.array_equal(evaluated.published, frame)
    unmerged = VehicleCompleter(model, threads=1, measured_merge=False)
    assert np.array_equal(unmerged.complete_normalized(partials[:3], scans["size"][:3]), evaluated.completion[:3])
    unmerged.even_spacing = False
    assert np.array_equal(unmerged.complete_normalized(partials[:3], scans["size"][:3]), batched[:3])


def test_torch_path_is_batch_independent(scans, model):
    x = torch.from_numpy(scans["partial"][:6])   # more than 4 clouds: once a switch of FPS arithmetic
    shapes = _shapes(scans)[:6]
    with torch.inference_mode(), torch_kernels():
        both = model(x, shapes).completion
        for i in (0, 5):
            assert torch.equal(model(x[i:i + 1], shapes[i:i + 1]).completion, both[i:i + 1])


def test_cpu_tensors_take_the_kernels_and_the_switch_restores(monkeypatch, scans):
    from gd_completion.model import ops

    def fail(*args, **kwargs):
        raise AssertionError("torch path used")
    x = torch.from_numpy(scans["partial"][:2])
    monkeypatch.setattr(ops, "_fps_torch", fail)
    monkeypatch.setattr(ops, "_window_knn_torch", fail)
    farthest_point_sample(x, 64)
    knn_graph(x, 8, 0.08)
    with pytest.raises(AssertionError, match="torch path used"), torch_kernels():
        farthest_point_sample(x, 64)
    knn_graph(x, 8, 0.08)                         # the context restored the kernels


def test_torch_path_still_trains(tmp_path):
    from test_model import TINY
    from test_train import _data, _settings

    from gd_completion.train import train
    with torch_kernels():
        result = train(TINY, _data(8, 0), _data(4, 1), tmp_path, _settings(epochs=4, generation_epochs=4))
    history = result.history
    assert result.epochs_done == 4 and history[-1]["train_total"] < 0.8 * history[0]["train_total"]


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="no CUDA device on this machine: the CUDA path is checked where a GPU is lent")
def test_cuda_torch_path_matches_cpu_fast_path(scans, model):
    import copy
    x = torch.from_numpy(scans["partial"][:8])
    shapes = _shapes(scans)[:8]
    gpu = copy.deepcopy(model).to("cuda")
    # TF32 (cuDNN's default for convolutions) rounds products to a 10-bit mantissa: a different network
    tf32 = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with torch.inference_mode():
            cpu_out = model(x, shapes).completion
            gpu_out = gpu(x.cuda(), shapes.cuda()).completion.cpu()
            alone = gpu(x[3:4].cuda(), shapes[3:4].cuda()).completion.cpu()
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = tf32
    # CUDA's GEMMs round differently in the last bit, which can flip one discrete choice (an FPS pick, a kNN
    # tie) in a rare cloud: most clouds agree to 1e-4, and every cloud's shape to a Chamfer distance of 1e-5
    per_cloud = (gpu_out - cpu_out).abs().amax((1, 2))
    assert (per_cloud <= 1e-4).float().mean().item() >= 0.75
    assert chamfer_l2(gpu_out, cpu_out).max().item() <= 1e-5
    assert chamfer_l2(alone, gpu_out[3:4]).max().item() <= 1e-5   # batch 1 may pick other convolution kernels
