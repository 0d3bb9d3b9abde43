"""Checkpoints of GGDNet: plain tensors + config dict, loaded with torch.load(weights_only=True)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from ..atomic import atomic_path, output_error
from ..errors import CheckpointError
from ..preprocess import Preprocessing
from .config import GGDConfig
from .network import GGDNet

DEFAULT_WEIGHTS = Path(__file__).parents[1] / "weights" / "ggd_vehicles.pt"
FORMAT = "gd_completion.ggdnet"
FORMAT_VERSION = 1


def save_checkpoint(path: str | os.PathLike, model: GGDNet, preprocessing: Preprocessing | None = None,
                    **extra: Any) -> Path:
    """Write model weights, config, the preprocessing contract the model was trained with (default: the
    contract's defaults) and `extra` (plain tensors/str/int/float/dicts) atomically to `path`."""
    path = Path(path)
    reserved = {"format", "format_version", "config", "preprocessing", "state_dict"} & set(extra)
    if reserved:
        raise ValueError(f"save_checkpoint: reserved keys in extra: {sorted(reserved)}")
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "config": model.config.to_dict(),
            "preprocessing": (preprocessing or Preprocessing()).to_dict(),
            "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}, **extra}
    with atomic_path(path) as tmp:
        try:
            torch.save(data, tmp)
        except RuntimeError as exc:   # torch's zip writer reports a full disk or a failed write this way
            raise output_error(path, exc) from exc
    return path


def read_checkpoint(path: str | os.PathLike, device: str | torch.device = "cpu") -> dict[str, Any]:
    """The whole checkpoint dict, validated; CheckpointError naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: file not found")
    try:
        data = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # truncated zip, pickle garbage, disallowed globals...
        # torch's own message suggests weights_only=False, i.e. running the file's code: not repeated here
        raise CheckpointError(f"checkpoint {path}: cannot be read as a weights-only torch checkpoint (corrupt, "
                              f"truncated, not a torch file, or it holds Python objects) [{type(exc).__name__}]"
                              ) from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path}: not a gd_completion GGDNet checkpoint (no format={FORMAT!r})")
    if data.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path}: unsupported format_version {data.get('format_version')!r}")
    if not isinstance(data.get("state_dict"), dict) or not isinstance(data.get("config"), dict):
        raise CheckpointError(f"checkpoint {path}: missing config or state_dict")
    return data


def read_checkpoint_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """Everything in the checkpoint except weights and optimizer state (config, epoch, metrics...)."""
    data = read_checkpoint(path)
    return {k: v for k, v in data.items() if k not in ("state_dict", "optimizer")}


def model_from_checkpoint(data: dict[str, Any], path: str | os.PathLike, device: str | torch.device = "cpu") -> GGDNet:
    """Build the GGDNet of a checkpoint dict returned by `read_checkpoint`."""
    try:
        config = GGDConfig.from_dict(data["config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: invalid config: {exc}") from exc
    model = GGDNet(config)
    try:
        model.load_state_dict(data["state_dict"], strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[:3]
        raise CheckpointError(f"checkpoint {path}: weights do not match its config: {' '.join(first)}") from exc
    return model.to(device).eval()


def preprocessing_from_checkpoint(data: dict[str, Any], path: str | os.PathLike) -> Preprocessing:
    """The checkpoint's `preprocessing` entry; a checkpoint from before the contract gets its defaults."""
    try:
        return Preprocessing.from_dict(data.get("preprocessing"))
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: invalid preprocessing: {exc}") from exc


def load_model(path: str | os.PathLike = DEFAULT_WEIGHTS, device: str | torch.device = "cpu") -> GGDNet:
    """Load a GGDNet (config from the checkpoint) in eval mode on `device`; CheckpointError on bad files."""
    return model_from_checkpoint(read_checkpoint(path, device), path, device)


def load_checkpoint(path: str | os.PathLike = DEFAULT_WEIGHTS, device: str | torch.device = "cpu"
                    ) -> tuple[GGDNet, Preprocessing]:
    """(model in eval mode on `device`, the preprocessing it was trained with); CheckpointError on bad files."""
    data = read_checkpoint(path, device)
    return model_from_checkpoint(data, path, device), preprocessing_from_checkpoint(data, path)
