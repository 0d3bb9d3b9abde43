"""Minimal PCD (v0.7, ascii or binary, uncompressed) reader for reference clouds."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gd_completion.errors import DataFormatError

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4",
          ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("U", 8): "<u8", ("I", 8): "<i8"}


def read_pcd(path: str | Path) -> np.ndarray:
    """Structured array of a PCD file's points (fields as named in the header)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise DataFormatError(f"{path}: cannot read PCD file ({error})") from None
    header: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise DataFormatError(f"{path}: PCD header without a DATA line")
        line = raw[offset:end].decode("ascii", "replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    try:
        names = header["FIELDS"]
        sizes = [int(v) for v in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(names))]
        n_points = int(header["POINTS"][0])
        fields = [(name, _TYPES[(kind, size)], (count,)) if count > 1 else (name, _TYPES[(kind, size)])
                  for name, size, kind, count in zip(names, sizes, types, counts, strict=True)]
    except (KeyError, ValueError, IndexError) as error:
        raise DataFormatError(f"{path}: malformed PCD header ({error})") from None
    dtype = np.dtype(fields)
    mode = header["DATA"][0].lower()
    if mode == "binary":
        if len(raw) - offset < n_points * dtype.itemsize:
            raise DataFormatError(f"{path}: PCD binary data shorter than {n_points} points")
        return np.frombuffer(raw, dtype=dtype, count=n_points, offset=offset).copy()
    if mode == "ascii":
        numbers = np.array(raw[offset:].decode("ascii").split(), dtype=np.float64)
        width = sum(counts)
        if numbers.size < n_points * width:
            raise DataFormatError(f"{path}: PCD ascii data shorter than {n_points} points")
        table = numbers[: n_points * width].reshape(n_points, width)
        out = np.empty(n_points, dtype=dtype)
        column = 0
        for name, count in zip(names, counts, strict=True):
            out[name] = table[:, column] if count == 1 else table[:, column:column + count]
            column += count
        return out
    raise DataFormatError(f"{path}: unsupported PCD DATA mode {mode!r} (ascii or binary only)")
