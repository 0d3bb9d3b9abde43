"""Box refinement: where a vehicle's true box lies in the normalised frame of its (detector) box.

A detector's box is off by decimetres and degrees; normalised by it, the vehicle sits off centre, turned and
scaled. `BoxRefiner`, a small PointNet, estimates from the points the true box in that frame (`BoxFrame`);
GGDNet then completes in the refined frame (`to_frame`) and maps its points back (`from_frame`), so the
output stays in the frame of the box it was given and the preprocessing contract does not change.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from gd_completion.geometry import Box3D

from .folding import FoldCache, fold_bn

# Typical magnitude of each regressed value (centre x, y, z in box lengths; yaw in rad; log size factors):
# the network predicts them in these units, so every output starts near 0 (the identity) and weighs alike.
FRAME_UNITS = (0.04, 0.04, 0.015, 0.08, 0.06, 0.06, 0.06)
# Bounds of each value (beyond the training data's box errors): an input unlike any training scan cannot move
# the frame further than this (0.3 lengths, 29 deg, size factors 0.67-1.49).
FRAME_LIMITS = (0.3, 0.3, 0.15, 0.5, 0.4, 0.4, 0.4)
# Names of the regressed values, in order (training logs and validation records).
FRAME_NAMES = ("x", "y", "z", "yaw", "log_length", "log_width", "log_height")


class BoxFrame(NamedTuple):
    """The true box in the normalised frame of the given box (B = batch)."""

    offset: Tensor  # (B, 3) its centre
    yaw: Tensor     # (B,) its heading minus the given box's (rad)
    scale: Tensor   # (B, 3) its size over the given box's size (length, width, height)

    @classmethod
    def from_vector(cls, vector: Tensor) -> BoxFrame:
        """From (B, 7) = (offset, yaw, log scale)."""
        return cls(vector[:, :3], vector[:, 3], vector[:, 4:].exp())

    def to_vector(self) -> Tensor:
        """(B, 7) = (offset, yaw, log scale)."""
        return torch.cat([self.offset, self.yaw[:, None], self.scale.log()], 1)


def _rotate_z(points: Tensor, yaw: Tensor) -> Tensor:
    c, s = yaw.cos()[:, None], yaw.sin()[:, None]
    x, y = points[..., 0], points[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, points[..., 2]], -1)


def to_frame(points: Tensor, frame: BoxFrame) -> Tensor:
    """Points (B, N, 3) of the given box's normalised frame in the refined box's normalised frame."""
    return _rotate_z(points - frame.offset[:, None], -frame.yaw) / frame.scale[:, None, :1]


def from_frame(points: Tensor, frame: BoxFrame) -> Tensor:
    """Inverse of `to_frame`."""
    return _rotate_z(points * frame.scale[:, None, :1], frame.yaw) + frame.offset[:, None]


def refined_shape(shape: Tensor, frame: BoxFrame) -> Tensor:
    """Box shape (B, 2) = (width, height) / length of the refined box, from the given box's."""
    return shape * frame.scale[:, 1:] / frame.scale[:, :1]


def box_from_frame(box: Box3D, vector: np.ndarray) -> Box3D:
    """The refined box in the cloud's frame, from the given `box` and the refiner's `BoxFrame` vector (7,) in that
    box's normalised frame (centre in box lengths, yaw offset, log size factors); label and instance id kept."""
    v = np.asarray(vector, np.float64)
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    dx, dy, dz = v[:3] * box.size[0]
    centre = (box.center[0] + c * dx - s * dy, box.center[1] + s * dx + c * dy, box.center[2] + dz)
    size = tuple(float(a * math.exp(b)) for a, b in zip(box.size, v[4:]))
    return Box3D(tuple(float(x) for x in centre), size, float(box.yaw + v[3]), box.label, box.instance_id)


def frame_targets(box_noise: np.ndarray, yaw: np.ndarray, size: np.ndarray, true_size: np.ndarray) -> np.ndarray:
    """(S, 7) float32 true `BoxFrame` vectors of training pairs (`synth.dataset` fields: the box error
    `box_noise` (S, 7) = centre offset, size factors, yaw offset; the vehicle's heading `yaw`; the size of the
    box used `size` and the vehicle's `true_size`)."""
    box_noise = np.asarray(box_noise, np.float64)
    box_yaw = np.asarray(yaw, np.float64) + box_noise[:, 6]
    d = -box_noise[:, :3]                       # true centre - box centre, world axes
    c, s = np.cos(box_yaw), np.sin(box_yaw)
    length = np.asarray(size, np.float64)[:, 0]
    offset = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1) / length[:, None]
    log_scale = np.log(np.asarray(true_size, np.float64) / np.asarray(size, np.float64))
    return np.concatenate([offset, -box_noise[:, 6:7], log_scale], 1).astype(np.float32)


class BoxRefiner(nn.Module):
    """PointNet (shared MLP, max pool, MLP) from a vehicle's points and its box shape to its `BoxFrame`."""

    units: Tensor    # buffers (register_buffer): FRAME_UNITS, FRAME_LIMITS
    limits: Tensor

    def __init__(self, widths: tuple[int, ...], hidden: tuple[int, ...]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = 3
        for w in widths:
            layers += [nn.Conv1d(cin, w, 1), nn.BatchNorm1d(w), nn.ReLU()]
            cin = w
        self.points = nn.Sequential(*layers)
        head: list[nn.Module] = []
        cin += 2
        for w in hidden:
            head += [nn.Linear(cin, w), nn.ReLU()]
            cin = w
        self.out = nn.Linear(cin, 7)
        nn.init.zeros_(self.out.weight)   # identity at init
        nn.init.zeros_(self.out.bias)
        self.head = nn.Sequential(*head)
        self.register_buffer("units", torch.tensor(FRAME_UNITS))
        self.register_buffer("limits", torch.tensor(FRAME_LIMITS), persistent=False)
        self._pairs = tuple(zip(self.points[0::3], self.points[1::3]))  # type: ignore[call-overload]  # Sequential slices   # (Conv1d, BatchNorm1d) per point layer
        self._fold = FoldCache()   # ((bias, weight^T) per point layer)

    def clear_fold(self) -> None:
        """Drop the cached folded weights (after in-place changes through `.data`, as `LinearBN.clear_fold`)."""
        self._fold.clear()

    def _point_code(self, partial: Tensor) -> Tensor:
        """(B, C) max-pooled point features; under inference mode in eval with each BN folded into its Conv1d
        (cached, like `LinearBN`), one GEMM per layer."""
        if self.training or not torch.is_inference_mode_enabled():
            if self.training:
                self._fold.clear()   # training moves the running statistics in place
            return self.points(partial.transpose(1, 2)).amax(2)
        folded = self._fold.get([t for conv, bn in self._pairs for t in (conv.weight, conv.bias, bn.weight, bn.bias,
                                                                           bn.running_mean, bn.running_var)],
                                lambda: [fold_bn(conv.weight[:, :, 0], conv.bias, bn) for conv, bn in self._pairs])
        b, n, _ = partial.shape
        h = partial.reshape(b * n, 3)
        for bias, weight_t in folded:
            h = torch.relu_(torch.addmm(bias, h, weight_t))
        return h.view(b, n, -1).amax(1)

    def vector(self, partial: Tensor, shape: Tensor) -> Tensor:
        """(B, 7) `BoxFrame` vector of `partial` (B, N, 3) in the given box's frame with its `shape` (B, 2)."""
        code = self._point_code(partial)
        vector = self.out(self.head(torch.cat([code, shape], 1))) * self.units
        return torch.maximum(torch.minimum(vector, self.limits), -self.limits)

    def forward(self, partial: Tensor, shape: Tensor) -> BoxFrame:
        return BoxFrame.from_vector(self.vector(partial, shape))
