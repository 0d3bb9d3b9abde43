"""GGDNet: generation branch (multi-resolution encoder + tree decoder) and graph-guided deformation."""
from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from .box_refiner import BoxFrame, BoxRefiner, from_frame, refined_shape, to_frame
from .config import GGDConfig
from .folding import FoldCache, fold_bn
from .ops import ball_group, farthest_point_sample, flat_index, gather_points, knn_graph, neighbour_mean


def box_shape(sizes: Tensor | np.ndarray | Sequence[Sequence[float]]) -> Tensor:
    """(B, 2) float32 box aspect (width / length, height / length) of box sizes (B, 3) = (length, width, height):
    the box shape a box-conditioned GGDNet is given (the normalised frame divides by the length only)."""
    sizes = torch.as_tensor(np.asarray(sizes, dtype=np.float32).reshape(-1, 3))
    return sizes[:, 1:] / sizes[:, :1]


class GGDOutput(NamedTuple):
    """Every tensor the loss and the pipeline need (B = batch)."""

    coarse: Tensor            # P_s (B, N_s, 3), tree decoder output
    control: Tensor           # P_c (B, N_c, 3), FPS subset of the input
    control_deformed: Tensor  # P_c' (B, N_c, 3), first N_c points of P_o
    completion: Tensor        # P_o (B, N_o, 3) = P_g + offsets
    generated: Tensor         # P_g (B, N_o, 3) = concat(P_c, P_s)
    neighbours: Tensor        # kNN graph of P_g (B, N_o, k), used by the Laplacian loss
    control_index: Tensor     # (B, N_c) indices of P_c in the input
    box_frame: Tensor | None = None   # (B, 7) the refined box in the given box's frame (`BoxFrame` vector); None
                                      # without a box refiner


class LinearBN(nn.Module):
    """Point-wise Linear + BatchNorm + ReLU on (..., C); in eval mode BN is folded into the Linear.

    Under `torch.inference_mode` (the pipeline, the evaluation) the folded weights are cached (`FoldCache`)
    until a training-mode forward or an in-place change of a parameter or buffer: the same values as folding
    every call; after in-place changes through `.data`, fold anew with `clear_fold()`. Outside inference mode
    every call folds (autograd reaches the parameters).
    """

    def __init__(self, cin: int, cout: int, relu: bool = True) -> None:
        super().__init__()
        self.linear = nn.Linear(cin, cout, bias=False)
        self.bn = nn.BatchNorm1d(cout)
        self.relu = relu
        self._fold = FoldCache()   # (bias, weight^T)

    def clear_fold(self) -> None:
        """Drop the cached folded weights."""
        self._fold.clear()

    def _folded(self) -> tuple[Tensor, Tensor]:
        def fold() -> tuple[Tensor, Tensor]:
            return fold_bn(self.linear.weight, None, self.bn)
        if not torch.is_inference_mode_enabled():
            return fold()
        return self._fold.get((self.linear.weight, self.bn.weight, self.bn.bias, self.bn.running_mean,
                               self.bn.running_var), fold)

    def forward(self, x: Tensor) -> Tensor:
        shape = x.shape
        x2 = x.reshape(-1, shape[-1])
        if self.training:   # moves the running statistics (in place, without a version bump): refold in eval
            self._fold.clear()
            y = self.bn(self.linear(x2))
        else:
            bias, weight_t = self._folded()
            y = torch.addmm(bias, x2, weight_t)
        if self.relu:
            y = torch.relu_(y)
        return y.view(shape[:-1] + (-1,))


def _mlp_bn(cin: int, widths: tuple[int, ...]) -> nn.Sequential:
    layers = []
    for w in widths:
        layers.append(LinearBN(cin, w))
        cin = w
    return nn.Sequential(*layers)


class MultiResolutionEncoder(nn.Module):
    """f_i = concat(g(h0(P_i)), g(h1_i(h0(P_i)))) for P_i = FPS prefixes of N/1, N/2, N/8 points; MLP -> code."""

    def __init__(self, cfg: GGDConfig) -> None:
        super().__init__()
        self.fractions = cfg.encoder_fractions
        self.h0 = _mlp_bn(3, cfg.encoder_h0)
        self.h1 = nn.ModuleList(_mlp_bn(cfg.encoder_h0[-1], cfg.encoder_h1) for _ in cfg.encoder_fractions)
        cin = len(cfg.encoder_fractions) * (cfg.encoder_h0[-1] + cfg.encoder_h1[-1])
        layers: list[nn.Module] = []
        for w in cfg.code_hidden:
            layers += [nn.Linear(cin, w), nn.ReLU()]
            cin = w
        layers.append(nn.Linear(cin, cfg.code_dim))
        self.head = nn.Sequential(*layers)
        # box shape enters the first layer of the head (zero at init: a warm start keeps its function)
        self.box_in = nn.Linear(2, cfg.code_hidden[0] if cfg.code_hidden else cfg.code_dim, bias=False) \
            if cfg.box_conditioning else None
        if self.box_in is not None:
            nn.init.zeros_(self.box_in.weight)

    def forward(self, partial: Tensor, order: Tensor, shape: Tensor | None = None) -> Tensor:
        n = partial.shape[1]
        h0 = self.h0(partial)                      # point-wise, so h0(P_i) is a subset of h0(P)
        feats = []
        for frac, h1 in zip(self.fractions, self.h1):
            h = h0 if frac == 1 else gather_points(h0, order[:, : max(n // frac, 1)])
            feats += [h.amax(1), h1(h).amax(1)]
        x = self.head[0](torch.cat(feats, -1))
        if self.box_in is not None:
            x = x + self.box_in(shape)
        return self.head[1:](x)


class TreeDecoder(nn.Module):
    """TopNet tree: the code is split into arity[0] nodes, each node (with the code) into arity[l] children."""

    def __init__(self, cfg: GGDConfig) -> None:
        super().__init__()
        d, code = cfg.tree_node_dim, cfg.code_dim
        self.arity = cfg.tree_arity
        self.node_dim = d
        self.root = nn.Sequential(nn.Linear(code, cfg.tree_hidden[0]), nn.ReLU(),
                                  nn.Linear(cfg.tree_hidden[0], self.arity[0] * d), nn.Tanh())
        self.node_in = nn.ModuleList()
        self.code_in = nn.ModuleList()
        self.rest = nn.ModuleList()
        for level, a in enumerate(self.arity[1:], start=1):
            last = level == len(self.arity) - 1
            self.node_in.append(nn.Linear(d, cfg.tree_hidden[0], bias=False))
            self.code_in.append(nn.Linear(code, cfg.tree_hidden[0]))   # code term computed once per shape
            layers: list[nn.Module] = [nn.ReLU()]
            cin = cfg.tree_hidden[0]
            for w in cfg.tree_hidden[1:]:
                layers += [nn.Linear(cin, w), nn.ReLU()]
                cin = w
            layers.append(nn.Linear(cin, a * (3 if last else d)))
            if not last:
                layers.append(nn.Tanh())
            self.rest.append(nn.Sequential(*layers))
        # the shape basis: coefficients start at zero (a warm start keeps its function), shapes small and random
        self.basis_weights = nn.Linear(code, cfg.shape_basis) if cfg.shape_basis else None
        self.basis = nn.Parameter(torch.randn(cfg.shape_basis, cfg.num_coarse, 3) * 0.01) if cfg.shape_basis else None
        if self.basis_weights is not None:
            nn.init.zeros_(self.basis_weights.weight)
            nn.init.zeros_(self.basis_weights.bias)

    def forward(self, code: Tensor) -> Tensor:
        b = code.shape[0]
        nodes = self.root(code).view(b, self.arity[0], self.node_dim)
        for node_in, code_in, rest in zip(self.node_in, self.code_in, self.rest):
            h = node_in(nodes) + code_in(code).unsqueeze(1)
            nodes = rest(h).view(b, -1, self.node_dim if rest[-1].__class__ is nn.Tanh else 3)  # type: ignore[index]
        if self.basis_weights is not None and self.basis is not None:
            nodes = nodes + torch.einsum("bk,knd->bnd", self.basis_weights(code), self.basis)
        return nodes


def mirrored_source(partial: Tensor, order: Tensor) -> tuple[Tensor, Tensor]:
    """(input followed by its mirror image y -> -y (B, 2N, 3), FPS order interleaving each point with its mirror).

    Every prefix of 2k of the new order is the first k FPS points and their mirror images, so the ball groups'
    FPS subsets keep their meaning (the same density of points per ball at every scale)."""
    n = partial.shape[1]
    mirror = partial * partial.new_tensor([1.0, -1.0, 1.0])
    return torch.cat([partial, mirror], 1), torch.stack([order, order + n], -1).reshape(order.shape[0], -1)


class LocalFeatures(nn.Module):
    """F(p_i; P): input points grouped in balls of radii s*r around p_i, shared MLP, max-pool, concat scales.

    The ball of radius s*r takes its M points from the FPS prefix of N/s^2 input points (same density
    of M points per ball area at every scale; one kNN of M per scale instead of M*max(s) on all N).
    """

    inv_radius: Tensor   # buffer: 1 / (radius x scale) per ball

    def __init__(self, cfg: GGDConfig) -> None:
        super().__init__()
        self.radius, self.m, self.scales = cfg.radius, cfg.ball_m, cfg.ball_scales
        self.window = cfg.window_search
        self.mirror = cfg.mirror_local_features
        self.mlp = _mlp_bn(3, cfg.local_widths)
        self.out_dim = len(cfg.ball_scales) * cfg.local_widths[-1]
        self.register_buffer("inv_radius", 1.0 / (cfg.radius * torch.tensor(cfg.ball_scales, dtype=torch.float32)),
                             persistent=False)

    EVAL_CHUNK = 1024   # queries (all batch elements) per chunk of the MLP in eval mode

    def forward(self, centers: Tensor, partial: Tensor, order: Tensor) -> Tensor:
        b, q, _ = centers.shape
        if self.mirror:
            partial, order = mirrored_source(partial, order)
        idx = self.group(centers, partial, order)   # every query at once: the same searches in training and eval
        if self.training or b * q <= self.EVAL_CHUNK:
            return self._features(centers, partial, idx)
        # eval: chunks of query points keep the (chunk, S, M, C) activations in cache (BN is folded, so exact)
        step = max(1, self.EVAL_CHUNK // b)
        return torch.cat([self._features(centers[:, s:s + step], partial, idx[:, s:s + step])
                          for s in range(0, q, step)], 1)

    def group(self, centers: Tensor, partial: Tensor, order: Tensor) -> Tensor:
        """Indices (B, Q, S, M) into `partial` of the M ball neighbours of every center at every scale."""
        b, q, _ = centers.shape
        n = partial.shape[1]
        groups = []
        for s in self.scales:
            size = max(n // (s * s), 1)
            if s == 1 or size >= n:
                groups.append(ball_group(centers, partial, s * self.radius, self.m, window=self.window))
            else:
                sub = order[:, :size]
                local = ball_group(centers, gather_points(partial, sub), s * self.radius, self.m)
                groups.append(torch.gather(sub, 1, local.reshape(b, -1)).view(b, q, self.m))
        return torch.stack(groups, 2)

    def _features(self, centers: Tensor, partial: Tensor, idx: Tensor) -> Tensor:
        b, q, _ = centers.shape
        grouped = gather_points(partial, idx)                                           # (B,Q,S,M,3)
        rel = (grouped - centers[:, :, None, None, :]) * self.inv_radius.view(1, 1, -1, 1, 1)
        feat = self.mlp(rel).amax(3)                                                    # (B,Q,S,C)
        return feat.reshape(b, q, self.out_dim)


class GraphConv(nn.Module):
    """Pixel2Mesh graph convolution: y = x W0 + (A x) W1 + b, A = kNN adjacency / k."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.self_lin = nn.Linear(cin, cout)
        self.nbr_lin = nn.Linear(cin, cout, bias=False)

    def forward(self, x: Tensor, nbr_flat: Tensor, k: int) -> Tensor:
        # A(x W1) == (A x) W1; apply the linear map first when it narrows the features.
        if self.nbr_lin.out_features <= self.nbr_lin.in_features:
            nb = neighbour_mean(self.nbr_lin(x), nbr_flat, k)
        else:
            nb = self.nbr_lin(neighbour_mean(x, nbr_flat, k))
        return self.self_lin(x) + nb


class GResNet(nn.Module):
    """G-ResNet: input graph conv, residual blocks of two graph convs, output graph conv to 3-D offsets."""

    def __init__(self, cfg: GGDConfig, local_dim: int) -> None:
        super().__init__()
        w, self.k = cfg.gcn_width, cfg.knn_k
        self.inp = GraphConv(local_dim + 3 + 2, w)
        # f_final is the same for every point and rows of A sum to 1: its W0 and W1 terms merge into one.
        self.code_lin = nn.Linear(cfg.code_dim, w, bias=False)
        self.blocks = nn.ModuleList(nn.ModuleList([GraphConv(w, w), GraphConv(w, w)]) for _ in range(cfg.gcn_blocks))
        self.out = GraphConv(w, 3)
        with torch.no_grad():
            for lin in (self.out.self_lin, self.out.nbr_lin):
                lin.weight.mul_(cfg.offset_init_gain)
            self.out.self_lin.bias.zero_()

    def forward(self, x: Tensor, code: Tensor, knn: Tensor) -> Tensor:
        nbr = flat_index(knn, knn.shape[1])
        h = torch.relu(self.inp(x, nbr, self.k) + self.code_lin(code).unsqueeze(1))
        for g1, g2 in self.blocks:  # type: ignore[misc]  # a ModuleList of (GraphConv, GraphConv) ModuleLists
            h = (h + torch.relu(g2(torch.relu(g1(h, nbr, self.k)), nbr, self.k))) * 0.5  # type: ignore[has-type]
        return self.out(h, nbr, self.k)


class GGDNet(nn.Module):
    """Graph-Guided Deformation network (Shi et al., RA-L 2021); see docs/MODEL.md."""

    def __init__(self, config: GGDConfig | None = None) -> None:
        super().__init__()
        self.config = config or GGDConfig()
        self.encoder = MultiResolutionEncoder(self.config)
        self.decoder = TreeDecoder(self.config)
        self.local = LocalFeatures(self.config)
        self.deform = GResNet(self.config, self.local.out_dim)
        self.refiner = (BoxRefiner(self.config.refiner_widths, self.config.refiner_hidden)
                        if self.config.box_refinement else None)

    def _check(self, partial: Tensor, shape: Tensor | None) -> None:
        if partial.dim() != 3 or partial.shape[-1] != 3:
            raise ValueError(f"GGDNet expects partial clouds (B, N, 3), got {tuple(partial.shape)}")
        if self.config.box_conditioning and (shape is None or tuple(shape.shape) != (partial.shape[0], 2)):
            raise ValueError("this GGDNet is box-conditioned: pass box_shape (B, 2) = (width, height) / length "
                             f"(network.box_shape), got {None if shape is None else tuple(shape.shape)}")
        if partial.shape[1] < self.config.num_control:
            raise ValueError(f"GGDNet needs >= num_control={self.config.num_control} input points, "
                             f"got {partial.shape[1]}")

    def _order(self, partial: Tensor) -> Tensor:
        """FPS order long enough for every subset (N/2, N/8, N_c, N/s^2 are all prefixes of it)."""
        n = partial.shape[1]
        longest = max([self.config.num_control] + [n // f for f in self.config.encoder_fractions if f > 1]
                      + [n // (s * s) for s in self.config.ball_scales if s > 1])
        return farthest_point_sample(partial, min(longest, n))

    def _shape(self, box_shape: Tensor | None, like: Tensor) -> Tensor | None:
        """Box shape on the input's device and dtype; None (ignored) for a model without box conditioning."""
        if not self.config.box_conditioning:
            return None
        return box_shape.to(like.device, like.dtype) if box_shape is not None else None

    def _generate(self, partial: Tensor, order: Tensor, shape: Tensor | None
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        nc = self.config.num_control
        code = self.encoder(partial, order, shape)
        coarse = self.decoder(code)
        control_index = order[:, :nc]
        control = gather_points(partial, control_index)
        return code, coarse, control, control_index, order

    def _in_chunks(self, partial: Tensor) -> bool:
        """Whether this batch runs in eval chunks of `eval_batch_chunk` clouds (eval mode, a larger batch)."""
        return not self.training and partial.shape[0] > self.eval_batch_chunk > 0

    def _chunks(self, partial: Tensor, order: Tensor, shape: Tensor | None) -> list[tuple]:
        """(partial, order, shape) per eval chunk of `eval_batch_chunk` clouds."""
        step = self.eval_batch_chunk
        shapes = shape.split(step) if shape is not None else [None] * len(partial.split(step))
        return list(zip(partial.split(step), order.split(step), shapes))

    def _refine(self, partial: Tensor, shape: Tensor | None) -> tuple[Tensor, Tensor | None, BoxFrame | None]:
        """(partial, shape) in the refined box's frame and that frame; unchanged and None without a refiner.
        In eval mode the refiner runs one chunk at a time, like the rest (batch-independent results)."""
        if self.refiner is None or shape is None:
            return partial, shape, None
        if self._in_chunks(partial):
            step = self.eval_batch_chunk
            vector = torch.cat([self.refiner.vector(p, s) for p, s in zip(partial.split(step), shape.split(step))])
        else:
            vector = self.refiner.vector(partial, shape)
        frame = BoxFrame.from_vector(vector)
        return to_frame(partial, frame), refined_shape(shape, frame), frame

    def generate(self, partial: Tensor, box_shape: Tensor | None = None) -> Tensor:
        """Generation-only branch (ablation baseline): P_g = concat(P_c, P_s), (B, N_o, 3)."""
        shape = self._shape(box_shape, partial)
        self._check(partial, shape)
        partial, shape, frame = self._refine(partial, shape)
        order = self._order(partial)
        if self._in_chunks(partial):   # same chunks as forward
            parts = [self._generate(*chunk) for chunk in self._chunks(partial, order, shape)]
            generated = torch.cat([torch.cat([p[2], p[1]], 1) for p in parts], 0)
        else:
            _, coarse, control, _, _ = self._generate(partial, order, shape)
            generated = torch.cat([control, coarse], 1)
        return generated if frame is None else from_frame(generated, frame)

    # Eval mode runs the batch one cloud at a time after one batched FPS: per-cloud tensors stay in
    # cache (on CPU as fast as or faster than chunks of 4 or 16), and every cloud's result is bitwise
    # identical to its batch-1 result (GEMM rounding otherwise depends on the batch size, and a
    # rounding difference can flip a near-tie in the kNN / ball searches). 0 disables chunking.
    eval_batch_chunk: int = 1

    def forward(self, partial: Tensor, box_shape: Tensor | None = None) -> GGDOutput:
        """Complete `partial` (B, N, 3); a box-conditioned model also needs `box_shape` (B, 2) (`box_shape()`
        of the boxes' sizes), which other models ignore."""
        shape = self._shape(box_shape, partial)
        self._check(partial, shape)
        partial, shape, frame = self._refine(partial, shape)
        order = self._order(partial)    # one FPS loop for the whole batch
        if self._in_chunks(partial):
            parts = [self._forward(*chunk) for chunk in self._chunks(partial, order, shape)]
            # every field but box_frame (set below, for the whole batch)
            out = GGDOutput(*(torch.cat(ts, 0) for ts in zip(*(part[:-1] for part in parts))))
        else:
            out = self._forward(partial, order, shape)
        if frame is None:
            return out
        nc = self.config.num_control   # P_c, P_s and P_c' are parts of P_g and P_o: two transforms, not five
        generated, completion = from_frame(out.generated, frame), from_frame(out.completion, frame)
        return out._replace(generated=generated, completion=completion, control=generated[:, :nc],
                            coarse=generated[:, nc:], control_deformed=completion[:, :nc], box_frame=frame.to_vector())

    def _forward(self, partial: Tensor, order: Tensor, shape: Tensor | None) -> GGDOutput:
        code, coarse, control, control_index, order = self._generate(partial, order, shape)
        nc = control.shape[1]
        p_g = torch.cat([control, coarse], 1)
        p_o, knn = self.deformed(p_g, nc, code, partial, order)
        return GGDOutput(coarse=coarse, control=control, control_deformed=p_o[:, :nc], completion=p_o,
                         generated=p_g, neighbours=knn, control_index=control_index)

    def deformed(self, p_g: Tensor, nc: int, code: Tensor, partial: Tensor, order: Tensor) -> tuple[Tensor, Tensor]:
        """(P_o, the kNN graph over P_g): the G-ResNet's offsets added to P_g, whose first `nc` points are the control
        points, with this `code`, the input `partial` (its FPS `order`) in the frame it was completed in."""
        knn = knn_graph(p_g, self.config.knn_k, self.config.knn_margin if self.config.window_search else None)
        label = torch.zeros(p_g.shape[0], p_g.shape[1], 2, dtype=p_g.dtype, device=p_g.device)
        label[:, :nc, 0] = 1.0
        label[:, nc:, 1] = 1.0
        x = torch.cat([self.local(p_g, partial, order), p_g, label], -1)
        return p_g + self.deform(x, code, knn), knn

    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)
