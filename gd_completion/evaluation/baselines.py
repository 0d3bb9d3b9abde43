"""Completion baselines on normalised partial clouds: raw input, mirror symmetry, generation-only, GGD-Net."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from gd_completion.merge import merge_with_pool, mirrored
from gd_completion.model.network import GGDNet, box_shape
from gd_completion.sampling import resample_indices
from gd_completion.spacing import SHIPPED_SPACING, SpacingSettings, even_spacing

# Report order; "generation" is GGD-Net's generation-only branch P_g = concat(P_c, P_s); "box_fill",
# "template" and "mirror_template" are the box-only priors of `priors` (no learning); "ggd_raw" is the network's
# P_o as it comes out, "ggd" P_o evenly spaced (`spacing`; the pipeline's output without the merge), "ggd_merge"
# what the pipeline publishes: the evenly spaced P_o after the measured merge (`merge`).
BASELINE_NAMES: tuple[str, ...] = ("input", "mirror", "box_fill", "template", "mirror_template", "generation",
                                   "ggd_raw", "ggd", "ggd_merge")
BASELINE_TITLES: dict[str, str] = {"input": "raw input", "mirror": "mirror symmetry",
                                   "box_fill": "box fill (uniform in the box, no input)",
                                   "template": "template (sedan fitted to the box, no input)",
                                   "mirror_template": "mirror + template, FPS to 2048",
                                   "generation": "generation only", "ggd_raw": "GGD-Net, raw P_o (before even spacing)",
                                   "ggd": "GGD-Net (network output, evenly spaced)",
                                   "ggd_merge": "GGD-Net + measured merge (published)"}


def raw_input(partial: np.ndarray) -> np.ndarray:
    """The partial cloud itself (float32 copy)."""
    return np.array(partial, dtype=np.float32)


def mirror_symmetry(partial: np.ndarray) -> np.ndarray:
    """Input plus its mirror image about the longitudinal vertical plane (y -> -y in the box frame).

    Works on (N, 3) or (B, N, 3); the output has twice the points, input first.
    """
    partial = np.asarray(partial, dtype=np.float32)
    return np.concatenate([partial, mirrored(partial)], axis=-2)


def _as_batch(model: GGDNet, partial: np.ndarray | Sequence[np.ndarray]) -> tuple[torch.Tensor, bool]:
    if isinstance(partial, np.ndarray) and partial.ndim == 3 and partial.shape[1] == model.config.num_input:
        return torch.from_numpy(partial.astype(np.float32)), False
    single = isinstance(partial, np.ndarray) and partial.ndim == 2
    clouds: list[np.ndarray] = [partial] if single else list(partial)  # type: ignore[list-item]
    return torch.from_numpy(_resampled(clouds, model.config.num_input)[0]), single


def _resampled(clouds: Sequence[np.ndarray], n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """(B, n, 3) float32: each cloud brought to `n` points the way the pipeline does (FPS down, cycle up), and
    per cloud the rows it took (`preprocess.resample_indices`)."""
    clouds = [np.asarray(c, dtype=np.float32).reshape(-1, 3) for c in clouds]
    empty = [i for i, c in enumerate(clouds) if len(c) == 0]
    if empty:
        raise ValueError(f"cannot complete empty clouds (indices {empty})")
    rows = [resample_indices(len(c), c, n) for c in clouds]
    batch = np.stack([c[r] for c, r in zip(clouds, rows)]) if clouds else np.zeros((0, n, 3), np.float32)
    return batch, rows


def _shapes(sizes: np.ndarray | Sequence[Sequence[float]] | None, count: int) -> torch.Tensor | None:
    """Box shapes (B, 2) of `count` clouds' box sizes (length, width, height); None without sizes."""
    if sizes is None:
        return None
    shapes = box_shape(sizes)
    if shapes.shape[0] != count:
        raise ValueError(f"{count} clouds but {shapes.shape[0]} box sizes")
    return shapes


@torch.inference_mode()
def generation_only(model: GGDNet, partial: np.ndarray | Sequence[np.ndarray],
                    sizes: np.ndarray | Sequence[Sequence[float]] | None = None) -> np.ndarray:
    """GGD-Net generation-only branch `GGDNet.generate`: (N_o, 3) for one cloud, (B, N_o, 3) for several.
    `sizes`: the boxes' (length, width, height), needed by a box-conditioned model."""
    batch, single = _as_batch(model, partial)
    out = model.eval().generate(batch, _shapes(sizes, len(batch))).float().numpy()
    return out[0] if single else out


@torch.inference_mode()
def ggd_net(model: GGDNet, partial: np.ndarray | Sequence[np.ndarray],
            sizes: np.ndarray | Sequence[Sequence[float]] | None = None) -> np.ndarray:
    """Full GGD-Net `forward(...).completion`: (N_o, 3) for one cloud, (B, N_o, 3) for several."""
    batch, single = _as_batch(model, partial)
    out = model.eval()(batch, _shapes(sizes, len(batch))).completion.float().numpy()
    return out[0] if single else out


def network_outputs(model: GGDNet, partials: np.ndarray | Sequence[np.ndarray],
                    sizes: np.ndarray | Sequence[Sequence[float]] | None = None,
                    max_batch: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """(generation-only P_g, GGD-Net P_o), each (B, N_o, 3), from one batched forward per chunk.

    Clouds of any size are resampled to `num_input` as in the pipeline; `sizes` (B, 3) are their boxes'
    (length, width, height), needed by a box-conditioned model. In eval mode P_g of the forward pass
    equals `generate` (FPS is deterministic), so one pass serves both baselines.
    """
    generated, completion, _ = network_forward(model, partials, sizes, max_batch)
    return generated, completion


@torch.inference_mode()
def network_forward(model: GGDNet, partials: np.ndarray | Sequence[np.ndarray],
                    sizes: np.ndarray | Sequence[Sequence[float]] | None = None, max_batch: int = 32
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`network_outputs` and the network's kNN graph over P_g (B, N_o, k) int64, which `spacing.even_spacing` uses."""
    model = model.eval()
    if isinstance(partials, np.ndarray) and partials.ndim == 3 and partials.shape[1] == model.config.num_input:
        batch = partials.astype(np.float32, copy=False)
    else:
        batch = _resampled(list(partials), model.config.num_input)[0]
    shapes = _shapes(sizes, len(batch))
    generated, completion, graph = [], [], []
    for start in range(0, len(batch), max_batch):
        out = model(torch.from_numpy(np.ascontiguousarray(batch[start:start + max_batch])),
                    shapes[start:start + max_batch] if shapes is not None else None)
        generated.append(out.generated.float().numpy())
        completion.append(out.completion.float().numpy())
        graph.append(out.neighbours.numpy())
    if not generated:
        empty = np.zeros((0, model.config.num_output, 3), np.float32)
        return empty, empty.copy(), np.zeros((0, model.config.num_output, model.config.knn_k), np.int64)
    return np.concatenate(generated), np.concatenate(completion), np.concatenate(graph)


@dataclass(frozen=True)
class NetworkOutputs:
    """The network methods' outputs for a batch of partial clouds, each (B, N_o, 3) float32."""

    generated: np.ndarray   # generation-only branch P_g
    raw: np.ndarray         # GGD-Net P_o as the network gives it
    completion: np.ndarray  # P_o evenly spaced (`spacing.even_spacing`), as the pipeline's output without the merge
    published: np.ndarray   # the evenly spaced P_o after the measured merge, as the pipeline publishes it


def published_outputs(model: GGDNet, partials: Sequence[np.ndarray],
                      sizes: np.ndarray | Sequence[Sequence[float]] | None = None, max_batch: int = 32,
                      asides: Sequence[np.ndarray] | None = None,
                      spacing: SpacingSettings | None = SHIPPED_SPACING) -> NetworkOutputs:
    """`network_outputs` of partial clouds of any size, their completions evenly spaced (`spacing.even_spacing` with
    `spacing`; None: the raw P_o, as the pipeline's `even_spacing` off) and then merged with a pool of all their
    measured points (`merge.merge_with_pool`), as the pipeline does for single frames and tracks' fused partials
    alike; `asides`: the points each cloud's crop kept aside (`preprocess.CroppedVehicle.aside`), pooled too."""
    partials = [np.asarray(p, np.float32).reshape(-1, 3) for p in partials]
    if asides is not None and len(asides) != len(partials):
        raise ValueError(f"{len(partials)} partial clouds but {len(asides)} sets of points kept aside")
    batch = _resampled(partials, model.config.num_input)[0]
    generated, raw, graph = network_forward(model, batch, sizes, max_batch)
    return NetworkOutputs(generated, raw, *spaced_and_merged(raw, graph, partials, sizes, asides, spacing))


def spaced_and_merged(raw: np.ndarray, graph: np.ndarray, partials: Sequence[np.ndarray],
                      sizes: np.ndarray | Sequence[Sequence[float]] | None = None,
                      asides: Sequence[np.ndarray] | None = None,
                      spacing: SpacingSettings | None = SHIPPED_SPACING) -> tuple[np.ndarray, np.ndarray]:
    """(completion, published) of the network's raw P_o (B, N_o, 3) and its kNN graph, as `published_outputs` makes
    them: evenly spaced (None: the raw P_o), then merged with a pool of each cloud's measured points."""
    completion = even_spacing(raw, spacing, graph=graph) if spacing is not None else raw.copy()
    boxes = np.asarray(sizes, np.float64).reshape(-1, 3) if sizes is not None else None
    merged = [merge_with_pool(c, p, aside=None if asides is None else asides[i],
                              size=None if boxes is None else boxes[i]).points
              for i, (p, c) in enumerate(zip(partials, completion))]
    return completion, np.stack(merged) if merged else completion.copy()
