"""Lidar beam patterns: built-in HDL-64E / HDL-32E / VLP-32C / Pandar40 / 40P / 64 / PandarGT tables, Hesai CSVs."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.hesai.calibration import Calibration, load_calibration

__all__ = ["BeamPattern", "PATTERN_NAMES"]

# Hesai calibration tables (elevation, azimuth offset; degrees, channel order), as shipped with the sensors.
_PANDAR40 = (
    (7.25, -0.025), (6.249, -0.025), (5.243, -0.026), (4.235, -0.026), (3.222, -2.54), (2.209, -2.541),
    (1.874, 2.49), (1.528, -5.042), (1.194, -2.541), (0.859, 2.49), (0.513, -5.042), (0.178, -2.541),
    (-0.161, 2.49), (-0.499, -5.042), (-0.838, -0.026), (-1.177, 2.49), (-1.514, -5.042), (-1.853, -0.026),
    (-2.191, 4.998), (-2.529, -2.541), (-2.867, -0.026), (-3.204, 4.998), (-3.541, -2.54), (-3.879, -0.026),
    (-4.212, 4.997), (-4.554, -2.54), (-4.888, 2.49), (-5.219, 4.997), (-5.56, -2.539), (-5.893, 2.49),
    (-6.894, 2.49), (-7.89, 2.49), (-8.88, -0.024), (-9.864, -0.023), (-10.841, -0.023), (-11.81, -0.022),
    (-12.767, -2.528), (-13.718, -2.526), (-14.659, -2.523), (-15.589, -2.521),
)
_PANDAR40P = (
    (14.794, -1.042), (10.944, -1.042), (7.971, -1.042), (4.969, -1.042), (2.952, -1.042), (1.94, -1.042),
    (1.6, 3.125), (1.263, -5.208), (0.925, -1.042), (0.587, 3.125), (0.249, -5.208), (-0.088, -1.042),
    (-0.425, 3.125), (-0.763, -5.208), (-1.101, -1.042), (-1.439, 3.125), (-1.776, -5.208), (-2.116, -1.042),
    (-2.453, 3.125), (-2.788, -5.208), (-3.128, -1.042), (-3.463, 3.125), (-3.8, -5.208), (-4.138, -1.042),
    (-4.473, 3.125), (-4.808, -5.208), (-5.145, -1.042), (-5.479, 3.125), (-5.814, -5.208), (-6.149, -1.042),
    (-7.151, -1.042), (-8.147, -1.042), (-9.148, -1.042), (-10.133, -1.042), (-11.12, -1.042), (-12.094, -1.042),
    (-13.062, -1.042), (-14.018, -1.042), (-18.977, -1.042), (-24.985, -1.042),
)
_PANDAR64_ELEV = (
    14.9, 11.05, 8.077, 5.075, 3.058, 2.046, 1.878, 1.706, 1.54, 1.369, 1.202, 1.031, 0.864, 0.693, 0.526, 0.355,
    0.187, 0.018, -0.151, -0.319, -0.49, -0.657, -0.827, -0.995, -1.166, -1.333, -1.504, -1.67, -1.842, -2.01,
    -2.18, -2.347, -2.518, -2.682, -2.855, -3.022, -3.192, -3.357, -3.53, -3.694, -3.866, -4.032, -4.203,
    -4.367, -4.54, -4.702, -4.874, -5.039, -5.211, -5.373, -5.547, -5.708, -5.88, -6.043, -7.045, -8.041,
    -9.042, -10.027, -11.014, -11.988, -12.956, -13.912, -18.871, -24.879,
)
# Pandar64: six outer channels at -1.042 deg, the dense middle block cycles through five offsets.
_PANDAR64_AZ = (-1.042,) * 6 + tuple((1.042, 3.125, 5.208, -5.208, -3.125, -1.042)[i % 6] for i in range(48)) \
    + (-1.042,) * 10
# Velodyne HDL-64E S2 (KITTI): upper block of 32 lasers from +2.0 to -8.33 deg (~1/3 deg apart), lower block
# of 32 from -8.83 to -24.9 deg (~1/2 deg apart); the two blocks are interleaved in firing order.
_HDL64E_ELEV = tuple(np.round(np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.9, 32)]), 4))

# Velodyne HDL-32E (nuScenes): 32 lasers evenly from +10.67 to -30.67 deg (1.333 deg apart), 0.16 deg at 10 Hz.
_HDL32E_ELEV = tuple(np.round(np.linspace(10.67, -30.67, 32), 4))

# Velodyne VLP-32C: 32 lasers from -25 to +15 deg, densest (1/3 deg) around the horizon; 0.2 deg at 10 Hz.
_VLP32C_ELEV = (-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667,
                -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333,
                3.333, 4.667, 7.0, 10.333, 15.0)
# Hesai PandarGT (PandaSet's forward solid-state sensor), matched to the PandarGT points of PandaSet sequence 002
# (frame 10, sensor 1; the sensor origin fitted so that each firing-time group is one row): 60 deg horizontal
# field of view, rows every 0.12 deg at a fixed azimuth from -10.4 deg (lowest row measured) over the 20 deg
# vertical field of view, 0.1 deg between the points of a row.
_PANDARGT_ELEV = tuple(np.round(np.linspace(9.6, -10.4, 167), 4))

PATTERN_NAMES = ("hdl64e", "pandar40", "pandar40p", "pandar64", "hdl32e", "vlp32c", "pandargt")


@dataclass(frozen=True)
class BeamPattern:
    """Lidar: per-channel elevation and azimuth offset (deg), the horizontal step (deg) and the horizontal field
    of view (deg; under 360 for a forward-facing solid-state sensor, which fires only within it)."""

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_offsets_deg: tuple[float, ...]
    horizontal_resolution_deg: float
    #: Horizontal field of view (deg) centred on the sensor's heading; 360 for a rotating lidar.
    fov_deg: float = 360.0

    def __post_init__(self) -> None:
        if not 0 < self.fov_deg <= 360:
            raise ValueError(f"beam pattern {self.name!r}: bad field of view {self.fov_deg}")
        if len(self.elevations_deg) != len(self.azimuth_offsets_deg) or not self.elevations_deg:
            raise ValueError(f"beam pattern {self.name!r}: need as many azimuth offsets as elevations (>0)")
        if not 0 < self.horizontal_resolution_deg <= 10:
            raise ValueError(f"beam pattern {self.name!r}: bad horizontal resolution {self.horizontal_resolution_deg}")

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def n_azimuth(self) -> int:
        """Firings per revolution."""
        return int(round(360.0 / self.horizontal_resolution_deg))

    @classmethod
    def named(cls, name: str) -> BeamPattern:
        """Built-in pattern: "hdl64e" (KITTI, 10 Hz), "pandar40", "pandar40p", "pandar64" (10 Hz, 0.2 deg),
        "hdl32e" (Velodyne HDL-32E, 10 Hz, 0.16 deg), "vlp32c" (Velodyne VLP-32C, 10 Hz, 0.2 deg) and
        "pandargt" (Hesai PandarGT: forward-facing solid state, 60 x 20 deg field of view, 167 rows 0.12 deg
        apart, 0.1 deg horizontal)."""
        key = name.lower().replace("-", "").replace("_", "")
        if key == "hdl64e":
            # KITTI records at 10 Hz: ~2080 firings per turn (0.08 deg is the 5 Hz figure of the data sheet).
            return cls("hdl64e", _HDL64E_ELEV, (0.0,) * 64, 0.1728)
        if key == "pandar40":
            return cls("pandar40", tuple(e for e, _ in _PANDAR40), tuple(a for _, a in _PANDAR40), 0.2)
        if key == "pandar40p":
            return cls("pandar40p", tuple(e for e, _ in _PANDAR40P), tuple(a for _, a in _PANDAR40P), 0.2)
        if key == "pandar64":
            return cls("pandar64", _PANDAR64_ELEV, _PANDAR64_AZ, 0.2)
        if key == "hdl32e":
            return cls("hdl32e", _HDL32E_ELEV, (0.0,) * 32, 0.16)
        if key == "vlp32c":
            return cls("vlp32c", _VLP32C_ELEV, (0.0,) * 32, 0.2)
        if key == "pandargt":
            return cls("pandargt", _PANDARGT_ELEV, (0.0,) * len(_PANDARGT_ELEV), 0.1, fov_deg=60.0)
        raise ValueError(f"unknown beam pattern {name!r}; expected one of {PATTERN_NAMES}")

    @classmethod
    def from_calibration(cls, calibration: Calibration, horizontal_resolution_deg: float = 0.2,
                         name: str | None = None) -> BeamPattern:
        """Pattern of a Hesai angle calibration (channel order); named after its source file by default."""
        return cls(name or Path(calibration.source).stem, tuple(calibration.elevation_deg.tolist()),
                   tuple(calibration.azimuth_offset_deg.tolist()), horizontal_resolution_deg)

    @classmethod
    def from_csv(cls, path: str | Path, horizontal_resolution_deg: float = 0.2, name: str | None = None) -> BeamPattern:
        """Read a Hesai angle calibration CSV with `gd_completion.hesai.load_calibration` (DataFormatError)."""
        return cls.from_calibration(load_calibration(path), horizontal_resolution_deg, name)
