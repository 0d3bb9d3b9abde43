"""Hesai angle calibration CSV (`Laser id, Elevation, Azimuth` in degrees) loader."""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.errors import DataFormatError


@dataclass(frozen=True)
class Calibration:
    """Per-laser elevation and azimuth offset (degrees), index = channel in the packet."""

    elevation_deg: np.ndarray
    azimuth_offset_deg: np.ndarray
    source: str = "<calibration>"

    @property
    def n_lasers(self) -> int:
        """Number of lasers in the table."""
        return int(self.elevation_deg.shape[0])


def parse_calibration(text: str, source: str = "<calibration>") -> Calibration:
    """Parse calibration CSV text; rows must be lasers 1..N in any order."""
    rows = [row for row in csv.reader(io.StringIO(text)) if row and any(cell.strip() for cell in row)]
    if not rows:
        raise DataFormatError(f"{source}: empty Hesai calibration file")
    header = [cell.strip().lower() for cell in rows[0]]
    if len(header) < 3 or not (header[0].startswith("laser") or header[0].startswith("channel")):
        raise DataFormatError(
            f"{source}: expected header 'Laser id,Elevation,Azimuth' (or 'Channel,...'), got {rows[0]!r}"
        )
    if "elevation" not in header[1] or "azimuth" not in header[2]:
        raise DataFormatError(f"{source}: expected columns 2 and 3 to be Elevation and Azimuth, got {rows[0]!r}")
    body = rows[1:]
    if not body:
        raise DataFormatError(f"{source}: calibration has a header but no laser rows")
    try:
        table = np.array([[float(cell) for cell in row[:3]] for row in body], dtype=np.float64)
    except ValueError as error:
        raise DataFormatError(f"{source}: non-numeric value in calibration rows ({error})") from None
    if any(len(row) < 3 for row in body):
        raise DataFormatError(f"{source}: calibration row with fewer than 3 columns")
    if not np.all(np.isfinite(table)):
        raise DataFormatError(f"{source}: non-finite value in calibration rows")
    ids = table[:, 0].astype(np.int64)
    n = len(ids)
    if not np.array_equal(np.sort(ids), np.arange(1, n + 1)) or not np.array_equal(ids, table[:, 0]):
        raise DataFormatError(f"{source}: laser ids must be the integers 1..{n} without gaps or repeats")
    order = np.argsort(ids)
    elevation, azimuth = table[order, 1], table[order, 2]
    if np.any(np.abs(elevation) > 90.0) or np.any(np.abs(azimuth) > 180.0):
        raise DataFormatError(f"{source}: elevation/azimuth out of range (degrees expected)")
    return Calibration(elevation_deg=elevation, azimuth_offset_deg=azimuth, source=source)


def load_calibration(path: str | Path) -> Calibration:
    """Read a Hesai angle calibration CSV; `DataFormatError` names the file on any problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataFormatError(f"{path}: Hesai calibration file not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DataFormatError(f"{path}: cannot read Hesai calibration file ({error})") from None
    return parse_calibration(text, source=str(path))
