"""Batch norm folded into the linear map before it, for inference, and the cache that holds the folded weights."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor, nn


def fold_bn(weight: Tensor, bias: Tensor | None, bn: nn.BatchNorm1d) -> tuple[Tensor, Tensor]:
    """(bias, weight^T) of the affine map x -> bn(x W^T + bias) in eval mode; `weight` (out, in)."""
    mean, var = bn.running_mean, bn.running_var
    if mean is None or var is None:
        raise ValueError("fold_bn needs a BatchNorm1d with running statistics (track_running_stats)")
    scale = bn.weight * torch.rsqrt(var + bn.eps)
    shift = bn.bias - mean * scale
    if bias is not None:
        shift = shift + bias * scale
    return shift, (weight * scale[:, None]).t()


class FoldCache:
    """A value computed from some tensors, kept until one of them changes: another tensor, an in-place change
    (its version counter), dtype or device. The entry holds the storage of the tensors it was computed from, so
    no new tensor can take one of their addresses while it is cached (a parameter replaced by a new tensor, or
    given new `.data`, of the same version would otherwise look unchanged). In-place changes through `.data` (its
    own version counter) are not seen: `clear()` then. One attribute holds the entry, so threads sharing a module
    read a consistent one."""

    def __init__(self) -> None:
        self._entry: tuple[tuple, tuple[Tensor | None, ...], Any] | None = None   # (key, sources, value)

    def clear(self) -> None:
        """Drop the cached value."""
        self._entry = None

    @property
    def cached(self) -> Any:
        """The cached value, None when there is none."""
        entry = self._entry
        return None if entry is None else entry[2]

    def get(self, sources: Sequence[Tensor | None], compute: Callable[[], Any]) -> Any:
        """The cached value if `sources` are unchanged since it was computed, else `compute()` (as plain tensors:
        without autograd, outside inference mode), cached."""
        key = tuple((t.data_ptr(), t._version, t.dtype, t.device) if t is not None else None for t in sources)
        entry = self._entry
        if entry is None or entry[0] != key:
            with torch.inference_mode(False), torch.no_grad():
                held = tuple(t.detach() if t is not None else None for t in sources)   # their storage, even if swapped
                entry = (key, held, compute())
            self._entry = entry
        return entry[2]
