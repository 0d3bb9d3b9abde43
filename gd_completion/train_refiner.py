"""Training of a GGDNet's box refiner (`model.box_refiner`) on pairs with box noise; the rest stays frozen.

The data are the synthetic training pairs (`synth.dataset`): each knows the error of the box it was cropped
and normalised with, so the true box in that box's frame (`box_refiner.frame_targets`) is the target; a labelled
real drive can be added (`drive_frames.drive_frames`: its moving vehicles cropped with noisy boxes). Every
epoch writes a whole GGDNet checkpoint (`box_refinement`: the completion network's weights and the refiner's):
`last.pt` (resumable) and `best.pt` (lowest validation loss).
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch.nn.functional import smooth_l1_loss

from .errors import CheckpointError, DataFormatError
from .model.box_refiner import FRAME_NAMES, BoxRefiner, frame_targets
from .model.checkpoint import model_from_checkpoint, read_checkpoint, save_checkpoint
from .model.config import GGDConfig
from .model.network import GGDNet, box_shape
from .preprocess import Preprocessing
from .train import PROGRESS_STEPS, TrainResult, _as_tensor, _backward, _no_finite_step_error, _skip_step

if TYPE_CHECKING:
    from .drive_frames import DriveFrames

log = logging.getLogger(__name__)


@dataclass
class RefinerSettings:
    """Optimisation settings of the refiner (Adam; the learning rate warms up over the first 5 % of the steps,
    then falls to 1 % of `lr` by a cosine)."""

    epochs: int = 6
    batch_size: int = 64
    lr: float = 1e-3
    seed: int = 0
    device: str = "cpu"
    # epochs whose batch norms use and update batch statistics; later epochs train with the running statistics
    # frozen (None: every epoch). The shipped run froze them after epoch 1 (docs/MODEL.md, "Box refinement").
    norm_train_epochs: int | None = None
    # size of the refiner added to a base without one (GGDConfig.refiner_widths, refiner_hidden)
    widths: tuple[int, ...] = GGDConfig.refiner_widths
    hidden: tuple[int, ...] = GGDConfig.refiner_hidden
    max_skipped_steps: int = 20   # steps per epoch whose loss or gradient is not finite (skipped) before giving up

    def __post_init__(self) -> None:
        self.widths, self.hidden = tuple(int(w) for w in self.widths), tuple(int(w) for w in self.hidden)

    def lr_at(self, step: int, total: int) -> float:
        """Learning rate of the 0-based optimisation `step` of `total`."""
        warm = max(1, total // 20)
        if step < warm:
            return self.lr * (step + 1) / warm
        t = min(1.0, (step - warm) / max(1, total - warm))
        return self.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))


@dataclass(frozen=True)
class FrameData:
    """Network inputs (S, N, 3) normalised by the boxes used, their box shapes (S, 2), true frames (S, 7)."""

    partial: torch.Tensor
    shape: torch.Tensor
    target: torch.Tensor

    @classmethod
    def from_datasets(cls, datasets: Sequence[dict[str, Any]]) -> FrameData:
        """From `synth.dataset` data sets (each needs `box_noise`, `yaw`, `size`, `true_size`)."""
        parts = []
        for data in datasets:
            missing = [k for k in ("partial", "box_noise", "yaw", "size", "true_size") if k not in data]
            if missing:
                raise DataFormatError(f"box refiner data: a data set without {missing} (made before box noise)")
            parts.append((np.asarray(data["partial"], np.float32), box_shape(data["size"]).numpy(),
                          frame_targets(data["box_noise"], data["yaw"], data["size"], data["true_size"])))
        if not parts:
            raise DataFormatError("box refiner data: no data sets")
        partial, shape, target = (np.concatenate(p) for p in zip(*parts))
        if not (np.isfinite(shape).all() and np.isfinite(target).all()):
            raise DataFormatError("box refiner data: non-finite or non-positive box sizes or box errors")
        return cls(_as_tensor(partial, "box refiner data partial"), torch.from_numpy(shape), torch.from_numpy(target))

    @classmethod
    def from_drive(cls, frames: DriveFrames) -> FrameData:
        """From a labelled drive's refiner samples (`drive_frames.drive_frames`)."""
        return cls(_as_tensor(frames.partial, "drive refiner data partial"), box_shape(frames.size),
                   torch.from_numpy(np.asarray(frames.target, np.float32)))

    @classmethod
    def concat(cls, parts: Sequence[FrameData]) -> FrameData:
        """All samples of `parts`, in order."""
        return cls(*(torch.cat([getattr(p, name) for p in parts]) for name in ("partial", "shape", "target")))

    def __len__(self) -> int:
        return self.partial.shape[0]


def with_refiner(model: GGDNet, widths: Sequence[int] = GGDConfig.refiner_widths,
                 hidden: Sequence[int] = GGDConfig.refiner_hidden) -> GGDNet:
    """`model` with a fresh (identity) box refiner of these sizes added, or itself when it has one of these sizes;
    CheckpointError when it has one of other sizes."""
    if model.refiner is not None:
        if (model.config.refiner_widths, model.config.refiner_hidden) != (tuple(widths), tuple(hidden)):
            raise CheckpointError(f"the base has a box refiner of widths {list(model.config.refiner_widths)}, "
                                  f"hidden {list(model.config.refiner_hidden)}, not {list(widths)}, {list(hidden)}")
        return model
    refined = GGDNet(replace(model.config, box_refinement=True, refiner_widths=tuple(widths),
                             refiner_hidden=tuple(hidden)))
    refined.load_state_dict({**refined.state_dict(), **model.state_dict()})   # strict: the same names but refiner.*
    return refined


def mirrored_batch(partial: torch.Tensor, target: torch.Tensor, flip: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples with `flip` mirrored about the box's vertical longitudinal plane (y -> -y): a mirrored vehicle
    is a vehicle, and its true box is mirrored too (centre y and yaw change sign)."""
    sign = 1.0 - 2.0 * flip.to(partial.dtype)
    partial = partial * torch.stack([torch.ones_like(sign), sign, torch.ones_like(sign)], 1)[:, None]
    target = target.clone()
    target[:, 1] *= sign
    target[:, 3] *= sign
    return partial, target


def _refiner(model: GGDNet) -> BoxRefiner:
    """The model's box refiner (CheckpointError when it has none)."""
    if model.refiner is None:
        raise CheckpointError("this model has no box refiner")
    return model.refiner


def frame_loss(model: GGDNet, partial: torch.Tensor, shape: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Smooth L1 between the refiner's frame and the true one, in `box_refiner.FRAME_UNITS`."""
    units = _refiner(model).units
    return smooth_l1_loss(_refiner(model).vector(partial, shape) / units, target / units)


@torch.inference_mode()
def validate(model: GGDNet, data: FrameData, device: torch.device | str, batch: int = 256) -> dict[str, float]:
    """Loss and the RMS error of each frame value in FRAME_UNITS, the refiner's and the given box's."""
    was_training = _refiner(model).training
    _refiner(model).eval()
    preds = [_refiner(model).vector(data.partial[s:s + batch].to(device), data.shape[s:s + batch].to(device)).cpu()
             for s in range(0, len(data), batch)]
    _refiner(model).train(was_training)
    pred, units = torch.cat(preds), _refiner(model).units.cpu()
    rms = ((pred - data.target) ** 2).mean(0).sqrt() / units
    given = (data.target ** 2).mean(0).sqrt() / units
    return {"loss": float(smooth_l1_loss(pred / units, data.target / units)),
            **{f"rms_{n}": float(v) for n, v in zip(FRAME_NAMES, rms)},
            **{f"given_rms_{n}": float(v) for n, v in zip(FRAME_NAMES, given)}}


def train_refiner(base: str | Path, train_data: FrameData, val_data: FrameData, out_dir: str | Path,
                  settings: RefinerSettings | None = None, *, resume: bool = False,
                  preprocessing: Preprocessing | None = None) -> TrainResult:
    """Train the box refiner of GGDNet checkpoint `base` (one is added when it has none) with everything else
    frozen; `resume` continues from `out_dir/last.pt`. Checkpoints keep `base`'s preprocessing contract."""
    settings = settings or RefinerSettings()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    last_path, best_path = out_dir / "last.pt", out_dir / "best.pt"
    device = torch.device(settings.device)
    torch.manual_seed(settings.seed)
    base_data = read_checkpoint(base)
    preprocessing = preprocessing or Preprocessing.from_dict(base_data.get("preprocessing"))
    if not base_data["config"].get("box_conditioning"):
        raise CheckpointError(f"checkpoint {base}: the box refiner needs a box-conditioned model")
    model = with_refiner(model_from_checkpoint(base_data, base), settings.widths, settings.hidden).to(device)
    steps_per_epoch = len(train_data) // settings.batch_size
    if steps_per_epoch < 1:
        raise DataFormatError(f"box refiner data: {len(train_data)} samples, fewer than one batch")
    model.requires_grad_(False)
    _refiner(model).requires_grad_(True)
    optimizer = torch.optim.Adam(_refiner(model).parameters(), lr=settings.lr)
    total_steps = settings.epochs * steps_per_epoch
    start_epoch, history, best = 0, [], math.inf
    if resume and last_path.is_file():
        data = read_checkpoint(last_path)
        try:
            same_model = GGDConfig.from_dict(data["config"]) == model.config
        except (KeyError, ValueError, TypeError):
            same_model = False
        if not {"optimizer", "epoch", "best_loss"} <= set(data) or not same_model:
            raise CheckpointError(f"checkpoint {last_path}: not a resumable refiner checkpoint of {base}")
        model.load_state_dict(data["state_dict"])
        optimizer.load_state_dict(data["optimizer"])
        start_epoch, history, best = int(data["epoch"]), list(data.get("history", [])), float(data["best_loss"])
        log.info("resuming from %s at epoch %d", last_path, start_epoch)
    model.eval()          # the completion network's batch norms stay as they are
    log.info("training the box refiner (%d parameters) on %d samples, validating on %d, device %s",
             sum(p.numel() for p in _refiner(model).parameters()), len(train_data), len(val_data), device)
    for epoch in range(start_epoch, settings.epochs):
        g = torch.Generator().manual_seed(settings.seed * 100003 + epoch)   # resumable shuffling and mirroring
        perm = torch.randperm(len(train_data), generator=g)
        flips = torch.rand(len(train_data), generator=g) < 0.5
        _refiner(model).train(settings.norm_train_epochs is None or epoch < settings.norm_train_epochs)
        total, skipped, t0 = 0.0, 0, time.monotonic()
        for step in range(steps_per_epoch):
            idx = perm[step * settings.batch_size:(step + 1) * settings.batch_size]
            partial, target = mirrored_batch(train_data.partial[idx], train_data.target[idx], flips[idx])
            loss = frame_loss(model, partial.to(device), train_data.shape[idx].to(device), target.to(device))
            optimizer.zero_grad(set_to_none=True)
            if not _backward(_refiner(model), loss, 0.0):
                skipped = _skip_step(epoch, step + 1, skipped, settings.max_skipped_steps)
                continue
            for group in optimizer.param_groups:
                group["lr"] = settings.lr_at(epoch * steps_per_epoch + step, total_steps)
            optimizer.step()
            total += loss.item()
            if (step + 1) % PROGRESS_STEPS == 0:
                log.info("epoch %d step %d/%d loss %.4f (%.1f s)", epoch + 1, step + 1, steps_per_epoch,
                         total / (step + 1 - skipped), time.monotonic() - t0)
        if skipped == steps_per_epoch:
            raise _no_finite_step_error(epoch)
        record = {"epoch": epoch + 1, "seconds": time.monotonic() - t0, "skipped_steps": skipped,
                  "train_loss": total / (steps_per_epoch - skipped),
                  **{f"val_{k}": v for k, v in validate(model, val_data, device).items()}}
        history.append(record)
        log.info("epoch %d/%d loss %.4f | val loss %.4f, RMS in units (given box): %s | %.1fs", epoch + 1,
                 settings.epochs, record["train_loss"], record["val_loss"],
                 ", ".join(f"{n} {record[f'val_rms_{n}']:.3f} ({record[f'val_given_rms_{n}']:.3f})"
                           for n in FRAME_NAMES),
                 record["seconds"])
        extra = {"epoch": epoch + 1, "history": history, "settings": asdict(settings), "best_loss": best,
                 "base": str(base)}
        if record["val_loss"] < best:
            best = extra["best_loss"] = record["val_loss"]
            save_checkpoint(best_path, model, preprocessing, **extra)
        save_checkpoint(last_path, model, preprocessing, optimizer=optimizer.state_dict(), **extra)
    return TrainResult(out_dir=out_dir, last_path=last_path, best_path=best_path if best_path.is_file() else None,
                       epochs_done=settings.epochs, stopped_early=False, history=history)
