"""PointCloud2 <-> numpy structured arrays, duck-typed on the message (rclpy, rosbags or plain objects)."""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np

from gd_completion.errors import PointCloud2Error

__all__ = [
    "INT8", "UINT8", "INT16", "UINT16", "INT32", "UINT32", "FLOAT32", "FLOAT64",
    "DATATYPE_NAMES", "FieldSpec", "CloudLayout", "cloud_dtype", "read_points", "read_xyz",
    "write_points", "xyz_array_to_structured",
]

# sensor_msgs/msg/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)

DATATYPE_NAMES = {
    INT8: "INT8", UINT8: "UINT8", INT16: "INT16", UINT16: "UINT16",
    INT32: "INT32", UINT32: "UINT32", FLOAT32: "FLOAT32", FLOAT64: "FLOAT64",
}
ByteOrder = Literal["<", ">"]
_DATATYPE_TO_NUMPY: dict[int, np.dtype] = {
    INT8: np.dtype("i1"), UINT8: np.dtype("u1"), INT16: np.dtype("i2"), UINT16: np.dtype("u2"),
    INT32: np.dtype("i4"), UINT32: np.dtype("u4"), FLOAT32: np.dtype("f4"), FLOAT64: np.dtype("f8"),
}
_NUMPY_TO_DATATYPE = {(dt.kind, dt.itemsize): code for code, dt in _DATATYPE_TO_NUMPY.items()}
_SUPPORTED = ", ".join(f"{code}={name}" for code, name in DATATYPE_NAMES.items())


class FieldSpec(NamedTuple):
    """One PointField: `name`, byte `offset` in the point, PointField `datatype` code, element `count`."""

    name: str
    offset: int
    datatype: int
    count: int = 1  # type: ignore[assignment]  # PointField's name; shadows tuple.count, unused here


@dataclass
class CloudLayout:
    """An encoded cloud: fields, strides and the raw little-endian bytes (readable by `read_points`)."""

    fields: list[FieldSpec]
    point_step: int
    data: np.ndarray
    width: int
    height: int = 1
    row_step: int = -1
    is_bigendian: bool = False
    is_dense: bool = False

    def __post_init__(self) -> None:
        if self.row_step < 0:
            self.row_step = self.width * self.point_step


class _Decoded(NamedTuple):
    fields: list[FieldSpec]
    dtype: np.dtype
    buf: np.ndarray
    height: int
    width: int
    point_step: int
    row_step: int
    bigendian: bool


def _normalise_fields(fields: Iterable[Any], point_step: int) -> list[FieldSpec]:
    """Validate PointField-like items and return them as FieldSpecs (count 0 is read as 1)."""
    specs: list[FieldSpec] = []
    seen: set[str] = set()
    for f in fields:
        name, offset, datatype = str(f.name), int(f.offset), int(f.datatype)
        count = int(getattr(f, "count", 1))
        if datatype not in _DATATYPE_TO_NUMPY:
            raise PointCloud2Error(
                f"PointCloud2 field '{name}' has unsupported datatype {datatype} (supported: {_SUPPORTED})")
        if name in seen:
            raise PointCloud2Error(f"PointCloud2 field '{name}' appears more than once")
        seen.add(name)
        if offset < 0:
            raise PointCloud2Error(f"PointCloud2 field '{name}' has negative offset {offset}")
        if count < 0:
            raise PointCloud2Error(f"PointCloud2 field '{name}' has negative count {count}")
        count = max(count, 1)  # some drivers write count=0 for scalar fields
        end = offset + _DATATYPE_TO_NUMPY[datatype].itemsize * count
        if end > point_step:
            raise PointCloud2Error(
                f"PointCloud2 point_step {point_step} is smaller than the fields need "
                f"(field '{name}' {DATATYPE_NAMES[datatype]}x{count} at offset {offset} ends at byte {end})")
        specs.append(FieldSpec(name, offset, datatype, count))
    return specs


def _field_format(spec: FieldSpec, byteorder: ByteOrder) -> np.dtype:
    base = _DATATYPE_TO_NUMPY[spec.datatype].newbyteorder(byteorder)
    return np.dtype((base, (spec.count,))) if spec.count > 1 else base


def cloud_dtype(fields: Sequence[Any], point_step: int, *, is_bigendian: bool = False) -> np.dtype:
    """Structured dtype (itemsize `point_step`) for PointField-like `fields`, in any order, with padding."""
    point_step = int(point_step)
    if point_step < 0:
        raise PointCloud2Error(f"PointCloud2 point_step {point_step} is negative")
    specs = _normalise_fields(fields, point_step)
    order: ByteOrder = ">" if is_bigendian else "<"
    try:
        return np.dtype({
            "names": [s.name for s in specs],
            "formats": [_field_format(s, order) for s in specs],
            "offsets": [s.offset for s in specs],
            "itemsize": point_step,
        })
    except (ValueError, TypeError) as exc:
        raise PointCloud2Error(f"PointCloud2 fields {[s.name for s in specs]} give no valid dtype: {exc}") from exc


def _as_uint8(data: Any) -> np.ndarray:
    """1-D uint8 view of `data` (bytes, bytearray, memoryview, array.array or ndarray); lists are copied."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8 or data.ndim != 1 or not data.flags.c_contiguous:
            data = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
        return data
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def _decode(msg: Any) -> _Decoded:
    """Read and check the layout of a PointCloud2-like message."""
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    bigendian = bool(getattr(msg, "is_bigendian", False))
    if height < 0 or width < 0:
        raise PointCloud2Error(f"PointCloud2 has negative size height={height} width={width}")
    fields = list(msg.fields)
    dtype = cloud_dtype(fields, point_step, is_bigendian=bigendian)
    specs = _normalise_fields(fields, point_step)
    buf = _as_uint8(msg.data)
    if height * width > 0:
        if point_step <= 0:
            raise PointCloud2Error(f"PointCloud2 point_step {point_step} must be positive for a non-empty cloud")
        if row_step < width * point_step:
            raise PointCloud2Error(
                f"PointCloud2 row_step {row_step} is smaller than width*point_step = {width}*{point_step}")
        if buf.size < height * row_step:
            raise PointCloud2Error(
                f"PointCloud2 data has {buf.size} bytes, shorter than height*row_step = "
                f"{height}*{row_step} = {height * row_step}")
    return _Decoded(specs, dtype, buf, height, width, point_step, row_step, bigendian)


def read_points(msg: Any) -> np.ndarray:
    """All points as a structured array of shape (height*width,), native byte order.

    A view of `msg.data` (no copy) for little-endian clouds without row padding; organised clouds with
    row padding and big-endian clouds are copied.
    """
    d = _decode(msg)
    n = d.height * d.width
    if n == 0:
        return np.empty(0, dtype=d.dtype.newbyteorder("<") if d.bigendian else d.dtype)
    if d.height == 1 or d.row_step == d.width * d.point_step:
        out = np.ndarray((n,), dtype=d.dtype, buffer=d.buf, offset=0, strides=(d.point_step,))
    else:
        grid = np.ndarray((d.height, d.width), dtype=d.dtype, buffer=d.buf, offset=0,
                          strides=(d.row_step, d.point_step))
        out = grid.reshape(n)  # copies: rows are not evenly spaced
    if d.bigendian:
        out = out.astype(d.dtype.newbyteorder("<"))
    return out


def read_xyz(msg: Any) -> np.ndarray:
    """x, y, z of every point as a new (height*width, 3) float32 array (non-finite points kept)."""
    d = _decode(msg)
    h, w = d.height, d.width
    if h * w == 0:
        return np.empty((0, 3), dtype=np.float32)  # an empty cloud needs no fields
    by_name = {s.name: s for s in d.fields}
    missing = [c for c in "xyz" if c not in by_name]
    if missing:
        raise PointCloud2Error(
            f"PointCloud2 has no {', '.join(repr(c) for c in missing)} field "
            f"(fields: {', '.join(s.name for s in d.fields) or 'none'})")
    xyz = [by_name[c] for c in "xyz"]
    for s in xyz:
        if s.count != 1:
            raise PointCloud2Error(f"PointCloud2 field '{s.name}' has count {s.count}; x/y/z need count 1")
    out = np.empty((h, w, 3), dtype=np.float32)
    order: ByteOrder = ">" if d.bigendian else "<"
    base = _DATATYPE_TO_NUMPY[xyz[0].datatype]
    if (all(s.datatype == xyz[0].datatype for s in xyz)
            and xyz[1].offset == xyz[0].offset + base.itemsize
            and xyz[2].offset == xyz[0].offset + 2 * base.itemsize):
        # Fast path: x, y, z adjacent with one type -> one strided view, one copy.
        view = np.ndarray((h, w, 3), dtype=base.newbyteorder(order), buffer=d.buf, offset=xyz[0].offset,
                          strides=(d.row_step, d.point_step, base.itemsize))
        np.copyto(out, view, casting="unsafe")
    else:
        for i, s in enumerate(xyz):
            dt = _DATATYPE_TO_NUMPY[s.datatype].newbyteorder(order)
            view = np.ndarray((h, w), dtype=dt, buffer=d.buf, offset=s.offset, strides=(d.row_step, d.point_step))
            np.copyto(out[:, :, i], view, casting="unsafe")
    return out.reshape(h * w, 3)


def _fields_from_dtype(dtype: np.dtype) -> list[FieldSpec]:
    if dtype.names is None:
        raise PointCloud2Error(f"write_points needs a structured array, got dtype {dtype}")
    specs = []
    for name in dtype.names:
        fdt, offset = dtype.fields[name][:2]  # type: ignore[index]  # a structured dtype: fields is set
        base, shape = (fdt.subdtype if fdt.subdtype is not None else (fdt, ()))
        code = _NUMPY_TO_DATATYPE.get((base.kind, base.itemsize)) if base.kind in "iuf" else None
        if code is None:
            raise PointCloud2Error(
                f"field '{name}' has numpy type {base} which PointCloud2 cannot carry "
                f"(use int8/16/32, uint8/16/32, float32 or float64)")
        specs.append(FieldSpec(name, int(offset), code, int(np.prod(shape, dtype=np.int64)) if shape else 1))
    return specs


def write_points(array: np.ndarray) -> CloudLayout:
    """Encode a structured array (shape (N,) or organised (H, W)) as a packed little-endian CloudLayout.

    point_step is the dtype's itemsize and `data` is a uint8 view of `array` (no copy) when the array is
    contiguous and little-endian.
    """
    array = np.asarray(array)
    if array.ndim not in (1, 2):
        raise PointCloud2Error(f"write_points needs a 1-D or 2-D structured array, got shape {array.shape}")
    specs = _fields_from_dtype(array.dtype)
    le_dtype = array.dtype.newbyteorder("<")
    if le_dtype != array.dtype:
        array = array.astype(le_dtype)
    array = np.ascontiguousarray(array)
    height, width = (1, array.shape[0]) if array.ndim == 1 else array.shape
    point_step = array.dtype.itemsize
    data = array.reshape(-1).view(np.uint8) if array.size else np.empty(0, dtype=np.uint8)
    return CloudLayout(specs, point_step, data, width=int(width), height=int(height), row_step=int(width) * point_step)


def xyz_array_to_structured(xyz: np.ndarray, **extra_columns: np.ndarray) -> np.ndarray:
    """Structured array with float32 x, y, z from an (N, 3) array plus one field per extra column.

    Each extra column keeps its dtype; a column of shape (N, k) becomes a field with count k.
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise PointCloud2Error(f"xyz must have shape (N, 3), got {xyz.shape}")
    n = xyz.shape[0]
    descr: list[tuple] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = {}
    for name, col in extra_columns.items():
        col = np.asarray(col)
        if col.ndim == 0 or col.shape[0] != n or col.ndim > 2:
            raise PointCloud2Error(f"column '{name}' has shape {col.shape}; expected ({n},) or ({n}, k)")
        if (col.dtype.kind not in "iuf" or (col.dtype.kind, col.dtype.itemsize) not in _NUMPY_TO_DATATYPE):
            raise PointCloud2Error(f"column '{name}' has numpy type {col.dtype} which PointCloud2 cannot carry")
        base = col.dtype.newbyteorder("<")
        descr.append((name, base, (col.shape[1],)) if col.ndim == 2 else (name, base))
        columns[name] = col
    out = np.empty(n, dtype=descr)
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, col in columns.items():
        out[name] = col
    return out
