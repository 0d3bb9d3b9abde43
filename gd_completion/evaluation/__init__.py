"""Evaluation of vehicle completion: metrics, baselines, synthetic and PandaSet benchmarks, reports."""
from __future__ import annotations

from gd_completion.errors import EvaluationError

from .baselines import BASELINE_NAMES, generation_only, ggd_net, mirror_symmetry, network_outputs, raw_input
from .metrics import (
    CD_SCALE,
    COVERAGE_SCALE,
    FIDELITY_SCALE,
    chamfer,
    chamfer_directional,
    coverage_error,
    fidelity,
    nearest_sq_distance,
)

__all__ = ["BASELINE_NAMES", "EvaluationError", "CD_SCALE", "COVERAGE_SCALE", "FIDELITY_SCALE", "chamfer",
           "chamfer_directional", "coverage_error", "fidelity", "generation_only", "ggd_net", "mirror_symmetry",
           "nearest_sq_distance", "network_outputs", "raw_input"]
