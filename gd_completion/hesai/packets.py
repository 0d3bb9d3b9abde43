"""Hesai Pandar40/40P/64 UDP packet layouts as numpy structured dtypes (no per-packet Python parsing)."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gd_completion.errors import DataFormatError

UNIT_DTYPE = np.dtype([("distance", "<u2"), ("reflectivity", "u1")])

# Tail shared by the three models (Pandar64 appends a UDP sequence number).
_TAIL_FIELDS = [
    ("reserved1", "u1", (5,)),
    ("high_temperature", "u1"),
    ("reserved2", "u1", (2,)),
    ("motor_speed", "<u2"),
    ("timestamp_us", "<u4"),
    ("return_mode", "u1"),
    ("factory_info", "u1"),
    ("utc", "u1", (6,)),
]

RETURN_STRONGEST = 0x37
RETURN_LAST = 0x38
RETURN_DUAL = 0x39
RETURN_MODES = {RETURN_STRONGEST: "strongest", RETURN_LAST: "last", RETURN_DUAL: "dual"}


def _pandar40_dtype() -> np.dtype:
    block = np.dtype([("sob", "<u2"), ("azimuth", "<u2"), ("units", UNIT_DTYPE, (40,))])
    return np.dtype([("blocks", block, (10,)), *_TAIL_FIELDS])


def _pandar64_dtype(udp_sequence: bool) -> np.dtype:
    header = [
        ("sob", "<u2"),
        ("laser_num", "u1"),
        ("block_num", "u1"),
        ("first_block_return", "u1"),
        ("dis_unit", "u1"),
        ("return_number", "u1"),
        ("flags", "u1"),
    ]
    block = np.dtype([("azimuth", "<u2"), ("units", UNIT_DTYPE, (64,))])
    fields = [*header, ("blocks", block, (6,)), *_TAIL_FIELDS]
    if udp_sequence:
        fields.append(("udp_sequence", "<u4"))
    return np.dtype(fields)


@dataclass(frozen=True)
class PacketFormat:
    """One sensor model: packet sizes, block/channel counts, timing tables (ns, relative to the packet stamp)."""

    name: str
    dtypes: dict[int, np.dtype]  # packet size -> layout
    n_blocks: int
    n_channels: int
    sob: int  # start-of-block (40/40P, per block) or start-of-packet (64) marker as read little-endian
    year_offset: int
    firing_offset_ns: np.ndarray  # (n_channels,)
    block_base_ns: int
    block_step_ns: int

    @property
    def sizes(self) -> tuple[int, ...]:
        """Accepted packet sizes in bytes."""
        return tuple(self.dtypes)

    def block_offset_ns(self, n_returns: np.ndarray) -> np.ndarray:
        """(n_packets, n_blocks) firing time of each block relative to the packet timestamp."""
        block = np.arange(self.n_blocks)[None, :]
        return self.block_base_ns - self.block_step_ns * ((self.n_blocks - block - 1) // n_returns[:, None])


# Laser firing-time offsets (ns) from the Hesai user manuals (Pandar40P and Pandar64 timing tables).
_P40_FIRING_NS = np.array([
    -42220, -28470, -16040, -3620, -45490, -31740, -47460, -54670, -20620, -33710,
    -40910, -8190, -20620, -27160, -50730, -8190, -14740, -36980, -45490, -52700,
    -23890, -31740, -38950, -11470, -18650, -25190, -48760, -6230, -12770, -35010,
    -21920, -9500, -43520, -29770, -17350, -4920, -42220, -28470, -16040, -3620,
], dtype=np.int64)
_P64_FIRING_NS = np.array([
    -23180, -21876, -20572, -19268, -17964, -16660, -11444, -46796, -7532, -36956, -50732,
    -54668, -40892, -44828, -31052, -34988, -48764, -52700, -38924, -42860, -29084, -33020,
    -46796, -25148, -36956, -50732, -27116, -40892, -44828, -31052, -34988, -48764, -25148,
    -38924, -42860, -29084, -33020, -52700, -6228, -54668, -15356, -27116, -10140, -23180,
    -4924, -21876, -14052, -17964, -8836, -19268, -3620, -20572, -12748, -16660, -7532,
    -11444, -6228, -15356, -10140, -4924, -3620, -14052, -8836, -12748,
], dtype=np.int64)

_P40: dict[str, Any] = dict(
    dtypes={1262: _pandar40_dtype()}, n_blocks=10, n_channels=40, sob=0xEEFF, year_offset=2000,
    firing_offset_ns=_P40_FIRING_NS, block_base_ns=-28580, block_step_ns=55560,
)
MODELS: dict[str, PacketFormat] = {
    "pandar40": PacketFormat(name="pandar40", **_P40),
    "pandar40p": PacketFormat(name="pandar40p", **_P40),
    "pandar64": PacketFormat(
        name="pandar64",
        dtypes={1194: _pandar64_dtype(False), 1198: _pandar64_dtype(True)},
        n_blocks=6, n_channels=64, sob=0xFFEE, year_offset=1900,
        firing_offset_ns=_P64_FIRING_NS, block_base_ns=-42580, block_step_ns=55560,
    ),
}
for _fmt in MODELS.values():
    for _size, _dtype in _fmt.dtypes.items():
        assert _dtype.itemsize == _size, (_fmt.name, _size, _dtype.itemsize)


def detect_model(packet: bytes | np.ndarray, source: str = "<packets>") -> str:
    """Model name from one packet's size and start marker (Pandar40 and 40P share a layout: gives pandar40p)."""
    data = bytes(packet[:2])
    size = len(packet)
    if size == 1262 and data == b"\xff\xee":
        return "pandar40p"
    if size in (1194, 1198) and data == b"\xee\xff":
        return "pandar64"
    raise DataFormatError(
        f"{source}: packet of {size} bytes starting {data.hex()} is not a Pandar40/40P (1262 bytes, ffee) "
        "or Pandar64 (1194/1198 bytes, eeff) packet (truncated packet or unsupported model)"
    )


def packets_to_array(
    packets: Sequence[bytes] | np.ndarray, model: str = "auto", source: str = "<packets>"
) -> tuple[PacketFormat, np.ndarray]:
    """Stack packets into a (n_packets, packet_size) uint8 array and check their size against the model."""
    if isinstance(packets, np.ndarray) and packets.ndim == 2:
        if packets.shape[0] == 0:
            raise DataFormatError(f"{source}: no packets to decode")
        array = np.ascontiguousarray(packets, dtype=np.uint8)
        first = array[0]
    else:
        if len(packets) == 0:
            raise DataFormatError(f"{source}: no packets to decode")
        first = packets[0]
        array = None
    name = detect_model(first, f"{source}: packet 0") if model == "auto" else model
    if name not in MODELS:
        raise DataFormatError(f"{source}: unknown Hesai model {name!r} (expected one of {sorted(MODELS)})")
    fmt = MODELS[name]
    if array is None:
        sizes = np.fromiter((len(p) for p in packets), dtype=np.int64, count=len(packets))
        valid = np.isin(sizes, list(fmt.dtypes))
        expected = int(sizes[valid][0]) if valid.any() else fmt.sizes[0]
        bad = np.flatnonzero(sizes != expected)
        if bad.size:
            index = int(bad[0])
            raise DataFormatError(
                f"{source}: packet {index} has {int(sizes[index])} bytes; {fmt.name} packets have "
                f"{' or '.join(map(str, fmt.sizes))} bytes (truncated packet or wrong model)"
            )
        array = np.frombuffer(b"".join(packets), dtype=np.uint8).reshape(len(packets), expected)
    if array.shape[1] not in fmt.dtypes:
        raise DataFormatError(
            f"{source}: packets have {array.shape[1]} bytes; {fmt.name} packets have "
            f"{' or '.join(map(str, fmt.sizes))} bytes (truncated packet or wrong model)"
        )
    return fmt, array


def parse_packets(fmt: PacketFormat, array: np.ndarray, source: str = "<packets>") -> np.ndarray:
    """Structured (n_packets,) view of the packets, after checking markers, laser count and return mode."""
    parsed = array.view(fmt.dtypes[array.shape[1]]).reshape(array.shape[0])
    if fmt.n_channels == 64:
        bad = np.flatnonzero(parsed["sob"] != fmt.sob)
        if bad.size:
            raise DataFormatError(f"{source}: packet {int(bad[0])} lacks the Pandar64 start marker eeff")
        bad = np.flatnonzero(parsed["laser_num"] != fmt.n_channels)
        if bad.size:
            raise DataFormatError(
                f"{source}: packet {int(bad[0])} reports {int(parsed['laser_num'][bad[0]])} lasers; "
                f"{fmt.name} has {fmt.n_channels} (unknown laser count)"
            )
        bad = np.flatnonzero(parsed["block_num"] != fmt.n_blocks)
        if bad.size:
            raise DataFormatError(
                f"{source}: packet {int(bad[0])} reports {int(parsed['block_num'][bad[0]])} blocks; "
                f"{fmt.name} has {fmt.n_blocks}"
            )
    else:
        bad = np.flatnonzero(np.any(parsed["blocks"]["sob"] != fmt.sob, axis=1))
        if bad.size:
            raise DataFormatError(f"{source}: packet {int(bad[0])} has a block without the ffee block marker")
    bad = np.flatnonzero(~np.isin(parsed["return_mode"], list(RETURN_MODES)))
    if bad.size:
        raise DataFormatError(
            f"{source}: packet {int(bad[0])} has unknown return mode 0x{int(parsed['return_mode'][bad[0]]):02x}"
        )
    bad = np.flatnonzero(np.any(parsed["blocks"]["azimuth"] >= 36000, axis=1))
    if bad.size:
        raise DataFormatError(f"{source}: packet {int(bad[0])} has a block azimuth >= 360 degrees")
    return parsed


def distance_unit_m(fmt: PacketFormat, parsed: np.ndarray) -> np.ndarray:
    """(n_packets,) distance unit in metres (Pandar64 header byte, 4 mm for Pandar40/40P)."""
    if fmt.n_channels == 64:
        unit = parsed["dis_unit"].astype(np.float64) * 1e-3
        return np.where(unit > 0, unit, 0.004)
    return np.full(parsed.shape[0], 0.004)


def packet_time_s(fmt: PacketFormat, parsed: np.ndarray) -> np.ndarray:
    """(n_packets,) packet timestamp in seconds since the epoch: tail UTC date-time (whole s) + microseconds."""
    utc = parsed["utc"].astype(np.int64)
    year = utc[:, 0] + np.where(utc[:, 0] >= 70, 1900, 2000)  # manuals differ: years since 1900 or 2000
    month = np.clip(utc[:, 1], 1, 12)
    day = np.clip(utc[:, 2], 1, 31)
    months = (year - 1970) * 12 + (month - 1)
    dates = months.astype("datetime64[M]").astype("datetime64[D]") + (day - 1)
    seconds = dates.astype(np.int64) * 86400 + utc[:, 3] * 3600 + utc[:, 4] * 60 + utc[:, 5]
    return seconds.astype(np.float64) + parsed["timestamp_us"].astype(np.float64) * 1e-6
