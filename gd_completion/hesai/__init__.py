"""Hesai Pandar40 / Pandar40P / Pandar64 raw packets to point clouds, without a ROS runtime."""
from __future__ import annotations

from gd_completion.hesai.calibration import Calibration, load_calibration
from gd_completion.hesai.decoder import (
    POINT_DTYPE,
    ReturnType,
    ScanAssembler,
    decode_packets,
    decode_scan,
)
from gd_completion.hesai.packets import MODELS, PacketFormat, detect_model, packets_to_array, parse_packets
from gd_completion.hesai.pcd import read_pcd

__all__ = [
    "Calibration",
    "MODELS",
    "POINT_DTYPE",
    "PacketFormat",
    "ReturnType",
    "ScanAssembler",
    "decode_packets",
    "decode_scan",
    "detect_model",
    "load_calibration",
    "packets_to_array",
    "parse_packets",
    "read_pcd",
]
