"""Training of GGDNet on (partial, complete) pairs: lambda schedule, validation, resumable checkpoints."""
from __future__ import annotations

import hashlib
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .errors import CheckpointError, DataFormatError, TrainingError
from .model.checkpoint import model_from_checkpoint, read_checkpoint, save_checkpoint
from .model.config import GGDConfig
from .model.losses import (
    CD_SCALE,
    SURFACE_SCALE,
    chamfer_and_surface,
    chamfer_l2,
    coverage,
    drive_loss,
    ggd_loss,
    target_normals,
)
from .model.network import GGDNet, box_shape
from .preprocess import Preprocessing

log = logging.getLogger(__name__)
PROGRESS_STEPS = 100   # a progress line in the log every this many optimisation steps

# (partial (S, N, 3), complete (S, N_o, 3)[, box sizes (S, 3)]) numpy arrays or tensors
ArrayPair = Sequence[Any]


@dataclass
class TrainSettings:
    """Optimisation settings (paper: 70 epochs, 40 generation-only, lambda 3, Adam, batch 32)."""

    epochs: int = 70
    generation_epochs: int = 40     # lambda = 0 for these epochs, then `lam`
    lam: float = 3.0
    alpha: float = 1000.0
    beta: float = 0.5
    gamma: float = 0.0              # weight of the surface term (0: the paper's loss); see losses.ggd_loss
    surface_planes: bool = False    # the surface term to the targets' tangent planes (training only: validation
    #                                 reports the distance to the nearest target point); see losses.plane_distance
    rho: float = 0.0                # weight of the repulsion term (0: the paper's loss); see losses.ggd_loss
    tangential: bool = False        # the repulsion term within each point's plane; see losses.repulsion
    drive_weight: float = 1.0       # weight of the real drive's batches (`train(drive=)`; losses.drive_loss)
    drive_precision: float = 0.0    # the drive's precision term in its loss, so x drive_weight (0: coverage only);
    #                                 see losses.drive_loss. best.pt's objective does not count it
    batch_size: int = 32
    lr: float = 1e-3                # paper: 0.01; see docs/MODEL.md
    lr_final: float | None = None   # cosine decay per epoch from lr to lr_final (None: constant lr)
    max_grad_norm: float = 10.0     # gradient clipping (0 disables)
    max_skipped_steps: int = 20     # steps per epoch whose loss or gradient is not finite (skipped) before giving up
    freeze: tuple[str, ...] = ()    # parameter-name prefixes kept as they are (no gradient, batch norms in eval mode)
    seed: int = 0
    device: str = "cpu"
    time_budget_s: float | None = None

    def __post_init__(self) -> None:
        bad = [name for name in ("gamma", "rho", "drive_weight", "drive_precision")
               if not getattr(self, name) >= 0]   # NaN too
        if bad:
            raise TrainingError(f"the weight of {' and '.join(bad)} must be >= 0 (0 leaves its term out); got "
                                + ", ".join(f"{name} {getattr(self, name)}" for name in bad))
        if self.surface_planes and not self.gamma > 0:
            raise TrainingError("surface_planes (--surface-planes) shapes the surface term: give that term a weight, "
                                "gamma > 0 (--gamma)")

    def lam_at(self, epoch: int) -> float:
        """Lambda of the 0-based `epoch`."""
        return 0.0 if epoch < self.generation_epochs else self.lam

    def lr_at(self, epoch: int) -> float:
        """Learning rate of the 0-based `epoch`: constant, or cosine from `lr` (first epoch) to `lr_final` (last)."""
        if self.lr_final is None or self.epochs <= 1:
            return self.lr
        t = min(epoch, self.epochs - 1) / (self.epochs - 1)
        return self.lr_final + 0.5 * (self.lr - self.lr_final) * (1.0 + math.cos(math.pi * t))


@dataclass
class TrainResult:
    """What `train` produced."""

    out_dir: Path
    last_path: Path
    best_path: Path | None
    epochs_done: int
    stopped_early: bool
    history: list[dict[str, float]] = field(default_factory=list)


def _as_tensor(a: Any, name: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(a, dtype=np.float32)) if not isinstance(a, torch.Tensor) else a.float()
    if t.dim() != 3 or t.shape[-1] != 3:
        raise DataFormatError(f"{name}: expected (S, N, 3) points, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise DataFormatError(f"{name}: contains NaN or infinite coordinates")
    return t.contiguous()


def _pairs(data: ArrayPair, name: str, cfg: GGDConfig, targets: int | None = None
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(partial, complete, box shapes (S, 2) or None) checked against `cfg`; the targets need `targets` points or
    more (default N_o)."""
    targets = cfg.num_output if targets is None else targets
    if len(data) not in (2, 3):
        raise DataFormatError(f"{name}: expected (partial, complete) or (partial, complete, box sizes)")
    partial, complete = _as_tensor(data[0], f"{name} partial"), _as_tensor(data[1], f"{name} complete")
    shapes = None
    if len(data) == 3 and data[2] is not None:
        sizes = np.asarray(data[2], dtype=np.float32)
        if sizes.shape != (partial.shape[0], 3) or not np.isfinite(sizes).all() or (sizes <= 0).any():
            raise DataFormatError(f"{name}: box sizes must be ({partial.shape[0]}, 3), finite and positive; got "
                                  f"shape {sizes.shape}" + (", with non-finite or non-positive values"
                                                            if sizes.shape == (partial.shape[0], 3) else ""))
        shapes = box_shape(sizes)
    elif cfg.box_conditioning:
        raise DataFormatError(f"{name}: a box-conditioned model needs the box sizes (partial, complete, sizes)")
    if partial.shape[0] != complete.shape[0] or partial.shape[0] == 0:
        raise DataFormatError(f"{name}: {partial.shape[0]} partial vs {complete.shape[0]} complete samples")
    if partial.shape[1] != cfg.num_input or complete.shape[1] < targets:
        raise DataFormatError(f"{name}: expected partial (S, {cfg.num_input}, 3) and complete (S, >= "
                              f"{targets}, 3), got {tuple(partial.shape)} and {tuple(complete.shape)}")
    return partial, complete, shapes


def _rows(shapes: torch.Tensor | None, idx: Any, device: torch.device | str) -> torch.Tensor | None:
    return shapes[idx].to(device) if shapes is not None else None


@torch.inference_mode()
def evaluate(model: GGDNet, partial: torch.Tensor, complete: torch.Tensor, batch_size: int,
             device: str | torch.device, shapes: torch.Tensor | None = None) -> dict[str, float]:
    """Mean Chamfer (x1000) of P_o (`cd_completion`), of the generation branch P_g (`cd_generated`) and P_s, and
    the mean distance (x100) of P_o's points to the nearest ground-truth point (`surface`)."""
    was_training = model.training
    model.eval()
    sums = {"cd_completion": 0.0, "cd_generated": 0.0, "cd_coarse": 0.0, "surface": 0.0}
    for s in range(0, partial.shape[0], batch_size):
        x, gt = partial[s:s + batch_size].to(device), complete[s:s + batch_size].to(device)
        out = model(x, _rows(shapes, slice(s, s + batch_size), device))
        cd, to_surface = chamfer_and_surface(out.completion, gt)
        sums["cd_completion"] += cd.sum().item()
        sums["cd_generated"] += chamfer_l2(out.generated, gt).sum().item()
        sums["cd_coarse"] += chamfer_l2(out.coarse, gt).sum().item()
        sums["surface"] += to_surface.sum().item()
    model.train(was_training)
    return {k: (SURFACE_SCALE if k == "surface" else CD_SCALE) * v / partial.shape[0] for k, v in sums.items()}


@torch.inference_mode()
def evaluate_drive(model: GGDNet, partial: torch.Tensor, reference: torch.Tensor, batch_size: int,
                   device: str | torch.device, shapes: torch.Tensor | None = None) -> float:
    """Mean coverage (x1000) of the drive pairs' references by P_o (`losses.coverage`)."""
    was_training = model.training
    model.eval()
    total = 0.0
    for s in range(0, partial.shape[0], batch_size):
        out = model(partial[s:s + batch_size].to(device), _rows(shapes, slice(s, s + batch_size), device))
        total += coverage(reference[s:s + batch_size].to(device), out.completion).sum().item()
    model.train(was_training)
    return CD_SCALE * total / partial.shape[0]


def _backward(model: torch.nn.Module, total: torch.Tensor, max_grad_norm: float) -> bool:
    """Backpropagate `total` and clip the gradient norm to `max_grad_norm` (0: no clipping); False (nothing to
    step) when the loss or the gradient is not finite: one bad batch must not turn every weight into NaN."""
    if not torch.isfinite(total):
        return False
    total.backward()
    norm = torch.nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm if max_grad_norm > 0 else math.inf)
    return bool(torch.isfinite(norm))


def frozen_modules(model: torch.nn.Module, prefixes: Sequence[str]) -> list[torch.nn.Module]:
    """Stop the gradients of every parameter whose name starts with one of `prefixes`; the submodules they name
    (to keep in eval mode, `train_mode`). TrainingError for a prefix that names no parameter."""
    unused = [p for p in prefixes if not any(n.startswith(p) for n, _ in model.named_parameters())]
    if unused:
        raise TrainingError(f"freeze: no parameter name starts with {unused}")
    for name, parameter in model.named_parameters():
        if any(name.startswith(p) for p in prefixes):
            parameter.requires_grad_(False)
    return [m for n, m in model.named_modules() if n and any(f"{n}.".startswith(p) for p in prefixes)]


def train_mode(model: torch.nn.Module, frozen: Sequence[torch.nn.Module]) -> None:
    """`model` in training mode but its `frozen` submodules (their batch norms keep their running statistics)."""
    model.train()
    for module in frozen:
        module.eval()


def _skip_step(epoch: int, step: int, skipped: int, limit: int) -> int:
    """Log a skipped step (0-based `epoch`, 1-based `step`) and return the epoch's new count of skipped steps;
    TrainingError beyond `limit`."""
    skipped += 1
    log.warning("epoch %d step %d: non-finite loss or gradient, step skipped (%d this epoch)", epoch + 1, step,
                skipped)
    if skipped > limit:
        raise TrainingError(f"epoch {epoch + 1}: more than {limit} steps with a non-finite loss or gradient; lower "
                            "the learning rate or check the data")
    return skipped


def _no_finite_step_error(epoch: int) -> TrainingError:
    return TrainingError(f"epoch {epoch + 1}: every step had a non-finite loss or gradient")


def warm_start(model: GGDNet, path: str | Path, skip: Sequence[str] = ()) -> list[str]:
    """Copy into `model` every tensor of checkpoint `path` with the same name and shape, except names
    starting with a prefix in `skip`; returns the names left at their fresh initialisation."""
    source = read_checkpoint(path)["state_dict"]
    target = model.state_dict()
    fresh = [name for name, t in target.items()
             if name not in source or source[name].shape != t.shape or any(name.startswith(p) for p in skip)]
    model.load_state_dict({**target, **{k: source[k] for k in target if k not in fresh}})
    return fresh


def train(config: GGDConfig, train_data: ArrayPair, val_data: ArrayPair, out_dir: str | Path,
          settings: TrainSettings | None = None, *, resume: bool = False, init_from: str | Path | None = None,
          init_skip: Sequence[str] = (), preprocessing: Preprocessing | None = None,
          drive: tuple[ArrayPair, ArrayPair] | None = None, **overrides: Any) -> TrainResult:
    """Train GGDNet; writes `out_dir/last.pt` (resumable) every epoch and `out_dir/best.pt` (best validation
    objective: P_o's CD, plus `drive_weight` times the drive pairs' coverage with a drive).

    `overrides` set TrainSettings fields (epochs=, batch_size=, lr=, generation_epochs=, lam=, device=,
    seed=, time_budget_s=...) on a copy of `settings`, checked as `TrainSettings` checks its own. With
    `resume=True` and an existing last.pt, training continues from it (its model config and optimizer state; the
    epoch count and schedule come from `settings`).
    Otherwise `init_from` warm-starts the new model from a checkpoint (`warm_start`; e.g. the shipped
    weights for a control-point ablation whose tree decoder differs), skipping the `init_skip` prefixes.
    `preprocessing`: the contract the data was made with (`synth.dataset` metadata), stored in every checkpoint.
    `drive`: (training, validation) pairs of a real drive, (partial, reference, box sizes) each
    (`drive_frames.drive_pairs`): every step adds a batch of them, weighted `drive_weight` (`losses.drive_loss`).
    """
    settings = settings or TrainSettings()
    unknown = sorted(k for k in overrides if not hasattr(settings, k))
    if unknown:
        raise TypeError(f"train: unknown setting {unknown[0]!r}")
    settings = replace(settings, **overrides)   # a new object, checked like any other (`__post_init__`)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    last_path, best_path = out_dir / "last.pt", out_dir / "best.pt"
    device = torch.device(settings.device)
    start = time.monotonic()

    torch.manual_seed(settings.seed)
    model = GGDNet(config)
    optimizer_state, resumed_freeze, resumed_objective = None, None, None
    start_epoch, history, best = 0, [], math.inf
    if resume and last_path.is_file():
        data = read_checkpoint(last_path)
        if "optimizer" not in data or "epoch" not in data:
            raise CheckpointError(f"checkpoint {last_path}: not a resumable training checkpoint")
        model = model_from_checkpoint(data, last_path)
        config = model.config
        optimizer_state = data["optimizer"]
        resumed_freeze = tuple(data.get("settings", {}).get("freeze", ()))
        trained_on_drive = any("val_drive_coverage" in record for record in data.get("history", []))
        resumed_objective = str(data.get("objective", "cd + drive coverage" if trained_on_drive else "cd"))
        start_epoch = int(data["epoch"])
        history = list(data.get("history", []))
        best = float(data.get("best_cd", math.inf))
        log.info("resuming from %s at epoch %d", last_path, start_epoch)
    elif init_from is not None:
        fresh = warm_start(model, init_from, init_skip)
        log.info("warm start from %s: %d tensors copied, fresh: %s", init_from,
                 len(model.state_dict()) - len(fresh), ", ".join(fresh) or "none")
    tr_x, tr_y, tr_s = _pairs(train_data, "training data", config)
    va_x, va_y, va_s = _pairs(val_data, "validation data", config)
    drive_train, drive_val = (None, None) if drive is None else (
        _pairs(drive[0], "drive training data", config, 1), _pairs(drive[1], "drive validation data", config, 1))
    objective = "cd" if drive_val is None else (   # what best.pt minimises, naming the drive pairs that validate
        f"cd + {settings.drive_weight:g} x drive coverage of {_digest(drive_val)}")
    frozen = frozen_modules(model, settings.freeze)
    if resumed_freeze is not None and resumed_freeze != tuple(settings.freeze):
        raise CheckpointError(f"checkpoint {last_path}: trained with freeze {list(resumed_freeze)}, resumed with "
                              f"{list(settings.freeze)}: resume with the same freeze")
    if resumed_objective is not None and resumed_objective != objective:
        older = resumed_objective.startswith("cd + ") and " of " not in resumed_objective
        raise CheckpointError(f"checkpoint {last_path}: its best checkpoint minimises {resumed_objective}, this run "
                              f"{objective}: " + ("the checkpoint was written before objectives named their drive "
                                                  "pairs; start a new run" if older else
                                                  "resume with the same drive (settings and pairs) and drive_weight"))
    if not any(p.requires_grad for p in model.parameters()):
        raise TrainingError(f"freeze {list(settings.freeze)} leaves no parameter to train")
    tr_n = None   # the targets' normals, for the surface term to their tangent planes
    if settings.surface_planes:
        tr_n = target_normals(tr_y)
        log.info("fitted the tangent planes of %d x %d target points", tr_y.shape[0], tr_y.shape[1])
    model.to(device)
    train_mode(model, frozen)
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=settings.lr)
    if optimizer_state is not None:
        optimizer.load_state_dict(optimizer_state)
    log.info("training GGDNet (%d parameters) on %d samples, validating on %d, device %s",
             model.num_parameters(), tr_x.shape[0], va_x.shape[0], device)

    stopped = False
    done = start_epoch
    for epoch in range(start_epoch, settings.epochs):
        lam = settings.lam_at(epoch)
        for group in optimizer.param_groups:
            group["lr"] = settings.lr_at(epoch)
        train_mode(model, frozen)
        g = torch.Generator().manual_seed(settings.seed * 100003 + epoch)   # resumable shuffling
        perm = torch.randperm(tr_x.shape[0], generator=g)
        drive_order = None if drive_train is None else torch.randperm(drive_train[0].shape[0], generator=g)
        sums: dict[str, float] = {}
        seen = skipped = 0
        t0 = time.monotonic()
        for s in range(0, perm.numel(), settings.batch_size):
            if settings.time_budget_s is not None and time.monotonic() - start > settings.time_budget_s:
                stopped = True
                break
            idx = perm[s:s + settings.batch_size]
            x, gt = tr_x[idx].to(device), tr_y[idx].to(device)
            losses = ggd_loss(model(x, _rows(tr_s, idx, device)), gt, lam=lam, alpha=settings.alpha,
                              beta=settings.beta, gamma=settings.gamma, rho=settings.rho,
                              tangential=settings.tangential, normals=_rows(tr_n, idx, device))
            if drive_train is not None and drive_order is not None:
                losses = _with_drive(losses, model, drive_train, drive_order, s, idx.numel(), lam, settings, device)
            optimizer.zero_grad(set_to_none=True)
            if not _backward(model, losses["total"], settings.max_grad_norm):
                skipped = _skip_step(epoch, s // settings.batch_size + 1, skipped, settings.max_skipped_steps)
                continue
            optimizer.step()
            for k, v in losses.items():
                sums[k] = sums.get(k, 0.0) + v.item() * idx.numel()
            seen += idx.numel()
            steps = s // settings.batch_size + 1
            if steps % PROGRESS_STEPS == 0:
                log.info("epoch %d step %d/%d loss %.4f (%.1f s)", epoch + 1, steps,
                         -(-perm.numel() // settings.batch_size), sums["total"] / seen, time.monotonic() - t0)
        if seen == 0 and not stopped:
            raise _no_finite_step_error(epoch)
        if seen == 0:   # time budget ran out before the first batch of this epoch
            save_checkpoint(last_path, model, preprocessing, optimizer=optimizer.state_dict(), epoch=epoch,
                            history=history, settings=asdict(settings), best_cd=best, objective=objective)
            log.info("time budget of %s s reached before epoch %d; stopping", settings.time_budget_s, epoch + 1)
            break
        record = {"epoch": epoch + 1, "lam": lam, "lr": settings.lr_at(epoch), "seconds": time.monotonic() - t0,
                  "skipped_steps": skipped,
                  **{f"train_{k}": v / seen for k, v in sums.items()},
                  **{f"val_{k}": v for k, v in evaluate(model, va_x, va_y, settings.batch_size, device,
                                                                     va_s).items()}}
        record["val_objective"] = record["val_cd_completion"]
        if drive_val is not None:
            record["val_drive_coverage"] = evaluate_drive(model, *drive_val[:2], settings.batch_size, device,
                                                          drive_val[2])
            record["val_objective"] += settings.drive_weight * record["val_drive_coverage"]
        history.append(record)
        log.info("epoch %d/%d lam %.1f loss %.4f | val CD x1e3 completion %.4f generated %.4f | %.1fs%s",
                 epoch + 1, settings.epochs, lam, record["train_total"], record["val_cd_completion"],
                 record["val_cd_generated"], record["seconds"], " (partial epoch, time budget)" if stopped else "")
        done = epoch if stopped else epoch + 1     # a partial epoch is redone on resume
        extra = {"epoch": done, "history": history, "settings": asdict(settings), "best_cd": best,
                 "objective": objective}
        if not stopped and record["val_objective"] < best:
            best = record["val_objective"]
            extra["best_cd"] = best
            save_checkpoint(best_path, model, preprocessing, **extra)
        save_checkpoint(last_path, model, preprocessing, optimizer=optimizer.state_dict(), **extra)
        if stopped:
            log.info("time budget of %.0f s reached; stopping", settings.time_budget_s)
            break
    return TrainResult(out_dir=out_dir, last_path=last_path, best_path=best_path if best_path.is_file() else None,
                       epochs_done=done, stopped_early=stopped, history=history)


def _digest(tensors: Sequence[torch.Tensor | None]) -> str:
    """The first 12 hex digits of the SHA-256 of `tensors`' values (float32): which data a figure was measured on."""
    digest = hashlib.sha256()
    for tensor in tensors:
        if tensor is not None:
            digest.update(tensor.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return digest.hexdigest()[:12]


def _with_drive(losses: dict[str, torch.Tensor], model: GGDNet,
                drive: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None], order: torch.Tensor, start: int,
                count: int, lam: float, settings: TrainSettings, device: torch.device) -> dict[str, torch.Tensor]:
    """`losses` of a synthetic batch with a batch of drive pairs added: the `count` pairs of `order` from `start`
    on (cycling; the drive is smaller than the synthetic set), weighted `settings.drive_weight`."""
    idx = order[torch.arange(start, start + count) % order.numel()]
    partial, reference, shapes = drive
    terms = drive_loss(model(partial[idx].to(device), _rows(shapes, idx, device)), reference[idx].to(device),
                       lam=lam, alpha=settings.alpha, beta=settings.beta, precision=settings.drive_precision)
    return {**losses, "total": losses["total"] + settings.drive_weight * terms["total"],
            **{f"drive_{k}": v for k, v in terms.items()}}
