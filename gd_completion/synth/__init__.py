"""Synthetic data: procedural vehicles, mesh files, simulated lidar scans, demo drives and training pairs."""
from __future__ import annotations

from typing import Any

from gd_completion.synth.beams import PATTERN_NAMES, BeamPattern
from gd_completion.synth.lidar import ScanResult, scan_meshes, simulate_scan
from gd_completion.synth.meshio import Mesh, box_mesh, load_mesh, load_mesh_folder, sample_surface
from gd_completion.synth.vehicles import VEHICLE_KINDS, generate_vehicle, perturb_mesh, vehicle_label

_LAZY = {
    "SyntheticFrame": "scene", "synthetic_drive": "scene",
    "make_sample": "dataset", "build_dataset": "dataset", "save_dataset": "dataset", "load_dataset": "dataset",
    "SampleOptions": "dataset", "V1_SAMPLING": "dataset", "V2_SAMPLING": "dataset",
}

__all__ = [
    "PATTERN_NAMES", "BeamPattern", "ScanResult", "scan_meshes", "simulate_scan", "Mesh", "box_mesh", "load_mesh",
    "load_mesh_folder", "sample_surface", "VEHICLE_KINDS", "generate_vehicle", "perturb_mesh", "vehicle_label",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    """Import the scene / dataset modules on first use (they pull in gd_completion.geometry)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"gd_completion.synth.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'gd_completion.synth' has no attribute {name!r}")
