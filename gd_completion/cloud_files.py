"""Point files (PLY, PCD, NPY/NPZ, KITTI .bin) to and from numpy structured arrays, vectorised."""
from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from gd_completion.atomic import atomic_path, refuse_existing
from gd_completion.datasets.kitti import read_velodyne
from gd_completion.errors import DataFormatError
from gd_completion.hesai.pcd import read_pcd

READ_SUFFIXES = (".ply", ".pcd", ".npy", ".npz", ".bin")
WRITE_SUFFIXES = (".ply", ".pcd", ".npy")

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


def suffix_of(path: str | os.PathLike, allowed: tuple[str, ...], what: str) -> str:
    """The lower-cased suffix of `path`; DataFormatError naming the allowed ones when it is not one of them."""
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise DataFormatError(f"{path}: unknown {what} file extension {suffix or '(none)'!r} "
                              f"(expected {', '.join(allowed)})")
    return suffix


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Structured array of a point file's points, with at least x, y, z; other fields as the file names them.

    .ply (ascii or binary, the `vertex` element), .pcd (ascii or binary), .npy/.npz (a structured array with
    x, y, z, or an (N, 3+) array: columns x, y, z, then `c3`, `c4`, ...; in an .npz the array named `points`,
    else the first), .bin (KITTI velodyne: x, y, z, intensity float32).
    """
    path = Path(path)
    suffix = suffix_of(path, READ_SUFFIXES, "point")
    if not path.is_file():
        raise DataFormatError(f"{path}: no such point file")
    if suffix == ".pcd":
        table = read_pcd(path)
    elif suffix == ".ply":
        table = _read_ply(path)
    elif suffix == ".bin":
        table = _from_columns(read_velodyne(path), path, ("x", "y", "z", "intensity"))
    else:
        table = _read_numpy(path)
    missing = [name for name in "xyz" if table.dtype.names is None or name not in table.dtype.names]
    if missing:
        raise DataFormatError(f"{path}: no field {', '.join(missing)} (fields: {table.dtype.names})")
    return table


def read_xyz(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float32 x, y, z of a point file (see `read_points`)."""
    table = read_points(path)
    return np.stack([table["x"], table["y"], table["z"]], axis=1).astype(np.float32, copy=False)


def write_points_file(path: str | os.PathLike, table: np.ndarray, *, overwrite: bool = False) -> Path:
    """Write a structured array (scalar fields) as binary little-endian .ply, binary .pcd or .npy, atomically;
    an existing `path` is refused (OutputError) unless `overwrite`."""
    path = Path(path)
    suffix = suffix_of(path, WRITE_SUFFIXES, "output")
    refuse_existing(path, overwrite)
    packed = table.astype(np.dtype([(name, table.dtype[name].newbyteorder("<")) for name in _names(table.dtype)]))
    with atomic_path(path) as tmp, open(tmp, "wb") as out:
        if suffix == ".npy":
            np.save(out, packed, allow_pickle=False)
        else:
            out.write((_ply_header if suffix == ".ply" else _pcd_header)(packed).encode("ascii"))
            out.write(packed.tobytes())
    return path


def _ply_header(table: np.ndarray) -> str:
    props = "".join(f"property {_PLY_NAMES[table.dtype[name].str[1:]]} {name}\n" for name in _names(table.dtype))
    return (f"ply\nformat binary_little_endian 1.0\ncomment written by gd_completion\n"
            f"element vertex {len(table)}\n{props}end_header\n")


def _pcd_header(table: np.ndarray) -> str:
    kinds = [table.dtype[name] for name in _names(table.dtype)]
    return ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
            f"FIELDS {' '.join(_names(table.dtype))}\n"
            f"SIZE {' '.join(str(k.itemsize) for k in kinds)}\n"
            f"TYPE {' '.join(k.kind.upper() for k in kinds)}\n"
            f"COUNT {' '.join('1' for _ in kinds)}\n"
            f"WIDTH {len(table)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(table)}\nDATA binary\n")


def _from_columns(array: np.ndarray, path: Path, names: tuple[str, ...] = ("x", "y", "z")) -> np.ndarray:
    """(N, K >= 3) numeric array -> structured array with fields `names`, then c3, c4, ..."""
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "fiu":
        raise DataFormatError(f"{path}: expected an (N, 3+) numeric array of points, got shape {array.shape} "
                              f"dtype {array.dtype}")
    columns = [*names[: array.shape[1]], *(f"c{k}" for k in range(len(names), array.shape[1]))]
    out = np.empty(len(array), dtype=[(name, array.dtype) for name in columns])
    for k, name in enumerate(columns):
        out[name] = array[:, k]
    return out


def _read_numpy(path: Path) -> np.ndarray:
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            with loaded:
                if not loaded.files:
                    raise DataFormatError(f"{path}: the .npz holds no array")
                array = loaded["points" if "points" in loaded.files else loaded.files[0]]
        else:
            array = loaded
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise DataFormatError(f"{path}: cannot read numpy file ({error})") from None
    if array.dtype.names is not None:
        return array.reshape(-1)
    return _from_columns(array, path)


def _read_ply(path: Path) -> np.ndarray:
    """The `vertex` element of a PLY file (ascii, binary little or big endian); list properties only after it."""
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise DataFormatError(f"{path}: cannot read PLY file ({error.strerror})") from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DataFormatError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    body = raw.index(b"\n", end) + 1
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []  # name, count, [(property, numpy type)]
    try:
        for line in raw[:end].decode("ascii").splitlines():
            words = line.split()
            if not words:
                continue
            if words[0] == "format":
                fmt = _PLY_FORMATS[words[1]]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property":
                kind = "list" if words[1] == "list" else _PLY_TYPES[words[1]]
                elements[-1][2].append((words[-1], kind))
    except (KeyError, ValueError, IndexError, UnicodeDecodeError) as error:
        raise DataFormatError(f"{path}: malformed PLY header ({error!r})") from None
    if fmt is None:
        raise DataFormatError(f"{path}: PLY header without a format line")
    offset = 0  # bytes (binary) or lines (ascii) of the elements before the vertices
    for name, count, props in elements:
        if any(kind == "list" for _, kind in props):
            raise DataFormatError(f"{path}: PLY element {name!r} has a list property "
                                  "(supported only in elements after the vertices)")
        dtype = np.dtype([(prop, fmt + kind if fmt else kind) for prop, kind in props])
        if name == "vertex":
            return _ply_vertices(raw, body, offset, count, dtype, bool(fmt), path)
        offset += count * (dtype.itemsize if fmt else 1)
    raise DataFormatError(f"{path}: PLY file without a vertex element")


def _ply_vertices(raw: bytes, body: int, offset: int, count: int, dtype: np.dtype, binary: bool,
                  path: Path) -> np.ndarray:
    if binary:
        if len(raw) - body - offset < count * dtype.itemsize:
            raise DataFormatError(f"{path}: PLY data shorter than {count} vertices")
        return np.frombuffer(raw, dtype=dtype, count=count, offset=body + offset).astype(dtype.newbyteorder("="))
    lines = raw[body:].split(b"\n", offset + count)[offset:offset + count]
    try:
        values = np.array(b" ".join(lines).split(), dtype=np.float64)
    except ValueError as error:
        raise DataFormatError(f"{path}: bad number in PLY vertex data ({error})") from None
    width = len(_names(dtype))
    if len(lines) < count or values.size != count * width:
        raise DataFormatError(f"{path}: PLY ascii data does not hold {count} vertices of {width} values")
    table = values.reshape(count, width)
    out = np.empty(count, dtype=dtype)
    for k, name in enumerate(_names(dtype)):
        out[name] = table[:, k]
    return out


def _names(dtype: np.dtype) -> tuple[str, ...]:
    """The field names of a structured dtype (ValueError for a plain one)."""
    if dtype.names is None:
        raise ValueError(f"not a structured dtype: {dtype}")
    return dtype.names
