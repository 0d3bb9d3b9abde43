"""Exceptions raised by gd_completion; each message names the input and the problem."""
from __future__ import annotations


class GDCompletionError(Exception):
    """Base class of every error gd_completion raises on bad input."""


class PointCloud2Error(GDCompletionError):
    """A PointCloud2 message that cannot be decoded or encoded."""


class BoxError(GDCompletionError):
    """An unusable 3D box (NaN pose, non-positive size, wrong frame)."""


class CheckpointError(GDCompletionError):
    """A model checkpoint that is missing, corrupt or of the wrong kind."""


class BagError(GDCompletionError):
    """A rosbag2 recording that cannot be read or written."""


class DataFormatError(GDCompletionError):
    """A dataset file (KITTI, PandaSet, Hesai, mesh, calibration) with the wrong format."""


class EvaluationError(GDCompletionError):
    """An evaluation input (held-out set, checkpoint list, output folder) is missing or unusable."""


class DeviceError(GDCompletionError):
    """A torch device that this machine does not have (e.g. cuda without a CUDA build or GPU)."""


class OutputError(GDCompletionError):
    """An output (bag, PNG, report, folder) that cannot be written: a file where a folder should be, no permission,
    a full disk."""


class TrainingError(GDCompletionError):
    """Training cannot go on (e.g. too many steps with a non-finite loss or gradient)."""
