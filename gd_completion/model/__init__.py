"""Graph-Guided Deformation network (GGD-Net) for point cloud completion: config, ops, network, losses, checkpoints."""
from __future__ import annotations

from .checkpoint import DEFAULT_WEIGHTS, load_model, read_checkpoint_metadata, save_checkpoint
from .config import GGDConfig
from .losses import chamfer_l2, chamfer_l2_directional, ggd_loss
from .network import GGDNet, GGDOutput
from .ops import farthest_point_sample

__all__ = ["DEFAULT_WEIGHTS", "GGDConfig", "GGDNet", "GGDOutput", "chamfer_l2", "chamfer_l2_directional",
           "farthest_point_sample", "ggd_loss", "load_model", "read_checkpoint_metadata", "save_checkpoint"]
