"""Vectorised Hesai packet decoding to structured point arrays, and scan assembly at a cut azimuth."""
from __future__ import annotations

from collections.abc import Sequence
from enum import IntEnum
from typing import Any

import numpy as np

from gd_completion.errors import DataFormatError
from gd_completion.hesai.calibration import Calibration
from gd_completion.hesai.packets import (
    RETURN_DUAL,
    RETURN_LAST,
    PacketFormat,
    distance_unit_m,
    packet_time_s,
    packets_to_array,
    parse_packets,
)

POINT_DTYPE = np.dtype([
    ("x", "<f4"),
    ("y", "<f4"),
    ("z", "<f4"),
    ("intensity", "<f4"),
    ("ring", "<u2"),
    ("timestamp", "<f8"),
    ("return_type", "u1"),
])


class ReturnType(IntEnum):
    """Per-point return label (numbering follows the nebula driver's ReturnType)."""

    UNKNOWN = 0
    LAST = 1
    FIRST = 2
    STRONGEST = 3
    IDENTICAL = 6  # dual return where both echoes are the same point


def _check_calibration(fmt: PacketFormat, calibration: Calibration, source: str) -> None:
    if calibration.n_lasers != fmt.n_channels:
        raise DataFormatError(
            f"{calibration.source}: calibration has {calibration.n_lasers} lasers but {source} holds "
            f"{fmt.name} packets with {fmt.n_channels} channels"
        )


def _decode(
    fmt: PacketFormat,
    parsed: np.ndarray,
    calibration: Calibration,
    *,
    min_range: float,
    max_range: float,
    fov: tuple[float, float],
    dedupe_dual: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of all packets plus, per point, its flat block index and corrected azimuth (degrees, [0, 360))."""
    n_packets, n_blocks, n_channels = parsed.shape[0], fmt.n_blocks, fmt.n_channels
    blocks = parsed["blocks"]
    units = blocks["units"]  # (P, B, C), strided view into the packets
    raw = np.ascontiguousarray(units["distance"])
    mode = parsed["return_mode"]
    dual = mode == RETURN_DUAL
    n_returns = np.where(dual, 2, 1)

    # Candidate points: non-zero echoes; in dual mode blocks come in (last, strongest) pairs with one azimuth,
    # and a second echo equal to the first is the same point (labelled IDENTICAL, kept once).
    keep = raw > 0
    identical = np.zeros(raw.shape, dtype=bool)
    if dual.any():
        pairs = raw.reshape(n_packets, n_blocks // 2, 2, n_channels)
        same = (pairs[:, :, 0, :] == pairs[:, :, 1, :]) & dual[:, None, None]
        identical.reshape(pairs.shape)[:, :, 0, :] = same
        if dedupe_dual:
            keep.reshape(pairs.shape)[:, :, 1, :] &= ~same
    index = np.flatnonzero(keep.ravel())

    channel = (index % n_channels).astype(np.intp)
    flat_block = index // n_channels
    packet = flat_block // n_blocks
    block = flat_block % n_blocks

    distance = raw.ravel()[index].astype(np.float32) * distance_unit_m(fmt, parsed).astype(np.float32)[packet]
    block_azimuth = blocks["azimuth"].ravel()
    azimuth = (block_azimuth[flat_block].astype(np.float32) * np.float32(0.01)
               + calibration.azimuth_offset_deg.astype(np.float32)[channel])
    azimuth += np.where(azimuth < 0, np.float32(360.0), np.float32(0.0))
    azimuth -= np.where(azimuth >= 360.0, np.float32(360.0), np.float32(0.0))
    ok = (distance >= min_range) & (distance <= max_range)
    lo, hi = fov
    if not (lo <= 0.0 and hi >= 360.0):
        rel = np.mod(azimuth - np.float32(lo), np.float32(360.0))
        ok &= rel <= np.float32(np.mod(hi - lo, 360.0) if hi - lo < 360.0 else 360.0)
    if not ok.all():
        index, channel, flat_block, packet, block = index[ok], channel[ok], flat_block[ok], packet[ok], block[ok]
        distance, azimuth = distance[ok], azimuth[ok]

    # Return label per point.
    single_type = np.where(mode == RETURN_LAST, ReturnType.LAST, ReturnType.STRONGEST).astype(np.uint8)
    point_type = single_type[packet]
    in_dual = dual[packet]
    if in_dual.any():
        dual_type = np.where(block % 2 == 1, np.uint8(ReturnType.STRONGEST), np.uint8(ReturnType.LAST))
        dual_type[identical.ravel()[index]] = ReturnType.IDENTICAL
        point_type = np.where(in_dual, dual_type, point_type)

    az = np.deg2rad(azimuth)
    elevation = np.deg2rad(calibration.elevation_deg.astype(np.float32))
    cos_el, sin_el = np.cos(elevation), np.sin(elevation)
    points = np.empty(index.size, dtype=POINT_DTYPE)
    xy = distance * cos_el[channel]
    points["x"] = xy * np.sin(az)
    points["y"] = xy * np.cos(az)
    points["z"] = distance * sin_el[channel]
    points["intensity"] = units["reflectivity"].ravel()[index]
    points["ring"] = channel
    offset_ns = fmt.block_offset_ns(n_returns)[packet, block] + fmt.firing_offset_ns[channel]
    points["timestamp"] = packet_time_s(fmt, parsed)[packet] + offset_ns * 1e-9
    points["return_type"] = point_type
    return points, flat_block, azimuth


def decode_packets(
    packets: Sequence[bytes] | np.ndarray,
    calibration: Calibration,
    *,
    model: str = "auto",
    min_range: float = 0.3,
    max_range: float = 200.0,
    fov: tuple[float, float] = (0.0, 360.0),
    dedupe_dual: bool = True,
    source: str = "<packets>",
) -> np.ndarray:
    """Decode packets (all at once, vectorised) into a POINT_DTYPE array, in packet/block/channel order."""
    fmt, array = packets_to_array(packets, model, source)
    _check_calibration(fmt, calibration, source)
    parsed = parse_packets(fmt, array, source)
    points, _, _ = _decode(
        fmt, parsed, calibration, min_range=min_range, max_range=max_range, fov=fov, dedupe_dual=dedupe_dual
    )
    return points


def decode_scan(
    packets: Sequence[bytes] | np.ndarray,
    calibration: Calibration,
    *,
    min_range: float = 0.3,
    max_range: float = 200.0,
    fov: tuple[float, float] = (0.0, 360.0),
    model: str = "auto",
    dedupe_dual: bool = True,
    source: str = "<packets>",
) -> np.ndarray:
    """Points of one scan's packets (x,y,z,intensity,ring,timestamp,return_type); see `ScanAssembler` for cutting."""
    return decode_packets(
        packets, calibration, model=model, min_range=min_range, max_range=max_range, fov=fov,
        dedupe_dual=dedupe_dual, source=source,
    )


class ScanAssembler:
    """Cuts a stream of packets into full rotations at `scan_phase` (degrees), like the reference driver.

    Each point belongs to the rotation in which its corrected azimuth (block azimuth + laser offset)
    passes the phase, so lasers with a negative offset can put points of the block just after the
    cut into the previous rotation. A rotation is therefore emitted only once the stream has moved
    past the cut by more than the largest offset. `add(packets)` decodes the new packets once and
    returns the scans they complete; `flush()` returns the rest. The first and last scans of a
    stream are usually partial rotations.
    """

    def __init__(
        self,
        calibration: Calibration,
        *,
        model: str = "auto",
        scan_phase: float = 0.0,
        min_range: float = 0.3,
        max_range: float = 200.0,
        fov: tuple[float, float] = (0.0, 360.0),
        dedupe_dual: bool = True,
        source: str = "<packets>",
    ) -> None:
        self.calibration = calibration
        self.model = model
        self.scan_phase = float(scan_phase) % 360.0
        self.options: dict[str, Any] = dict(min_range=min_range, max_range=max_range, fov=fov, dedupe_dual=dedupe_dual)
        self.source = source
        self.packets_seen = 0
        self.late_points_dropped = 0
        self._fmt: PacketFormat | None = None
        self._margin = float(max(0.0, -np.min(calibration.azimuth_offset_deg))) + 1.0
        self._rotation = 0  # rotation of the latest block
        self._last_block_rel: float | None = None
        self._next_emit = 0
        self._points: list[np.ndarray] = []
        self._rotations: list[np.ndarray] = []

    @property
    def model_name(self) -> str:
        """The model of the stream (fixed by the first packets), or the requested one before any packet."""
        return self._fmt.name if self._fmt is not None else self.model

    def add(self, packets: Sequence[bytes] | np.ndarray) -> list[np.ndarray]:
        """Decode `packets` and return the scans they complete (possibly none), oldest first."""
        if len(packets) == 0:
            return []
        source = f"{self.source} (batch from stream packet {self.packets_seen})"
        fmt, array = packets_to_array(packets, self.model_name, source)
        if self._fmt is None:
            _check_calibration(fmt, self.calibration, source)
            self._fmt = fmt
        parsed = parse_packets(fmt, array, source)
        self.packets_seen += len(packets)
        points, flat_block, azimuth = _decode(fmt, parsed, self.calibration, **self.options)

        # Block azimuths relative to the phase; a new rotation starts where they wrap around.
        block_rel = np.mod(parsed["blocks"]["azimuth"].astype(np.float64).ravel() * 0.01 - self.scan_phase, 360.0)
        first = self._last_block_rel if self._last_block_rel is not None else block_rel[0]
        previous = np.concatenate(([first], block_rel[:-1]))
        wraps = np.flatnonzero(block_rel < previous - 180.0)
        self._last_block_rel = float(block_rel[-1])

        # A point moves to the neighbouring rotation when its own azimuth lies across the cut from its block's.
        point_rel = np.mod(azimuth.astype(np.float64) - self.scan_phase, 360.0)
        own = block_rel[flat_block]
        rotation = (self._rotation + np.searchsorted(wraps, flat_block, side="right")
                    + (own - point_rel > 180.0) - (point_rel - own > 180.0))
        self._rotation += len(wraps)
        late = rotation < self._next_emit
        if late.any():
            self.late_points_dropped += int(late.sum())
            points, rotation = points[~late], rotation[~late]
        self._points.append(points)
        self._rotations.append(rotation)

        complete = self._rotation - (1 if self._last_block_rel > self._margin else 2)
        return [self._take(k) for k in range(self._next_emit, complete + 1)]

    def _take(self, k: int) -> np.ndarray:
        points = np.concatenate(self._points)
        rotation = np.concatenate(self._rotations)
        mine = rotation == k
        self._points, self._rotations = [points[~mine]], [rotation[~mine]]
        self._next_emit = k + 1
        return points[mine]

    def flush(self) -> list[np.ndarray]:
        """The remaining (incomplete) rotations, oldest first; the assembler is empty afterwards."""
        if not self._points:
            return []
        rotation = np.concatenate(self._rotations)
        last = int(rotation.max()) if rotation.size else self._next_emit - 1
        scans = [self._take(k) for k in range(self._next_emit, last + 1)]
        self._points, self._rotations = [], []
        return [scan for scan in scans if scan.size]
