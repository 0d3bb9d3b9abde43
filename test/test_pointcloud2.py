"""PointCloud2 codec: layouts, message kinds, malformed input, big-endian, zero-copy."""
from __future__ import annotations

import array
import random
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from gd_completion.errors import PointCloud2Error
from gd_completion.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    INT8,
    INT16,
    INT32,
    UINT8,
    UINT16,
    UINT32,
    CloudLayout,
    FieldSpec,
    cloud_dtype,
    read_points,
    read_xyz,
    write_points,
    xyz_array_to_structured,
)

# struct codes and value ranges of each PointField datatype (independent of the code under test).
STRUCT = {INT8: "b", UINT8: "B", INT16: "h", UINT16: "H", INT32: "i", UINT32: "I", FLOAT32: "f", FLOAT64: "d"}
SIZE = {INT8: 1, UINT8: 1, INT16: 2, UINT16: 2, INT32: 4, UINT32: 4, FLOAT32: 4, FLOAT64: 8}
RANGE = {INT8: (-128, 127), UINT8: (0, 255), INT16: (-32768, 32767), UINT16: (0, 65535),
         INT32: (-2**31, 2**31 - 1), UINT32: (0, 2**32 - 1)}


def _value(rng: random.Random, datatype: int) -> float:
    if datatype in RANGE:
        return rng.randint(*RANGE[datatype])
    v = rng.uniform(-100.0, 100.0)
    return struct.unpack("f", struct.pack("f", v))[0] if datatype == FLOAT32 else v


def build_cloud(field_types: list[tuple[str, int, int]], *, height: int, width: int, seed: int,
                shuffle: bool = True, big_endian: bool = False, max_pad: int = 5, row_pad: int = 0):
    """A reference encoder with `struct`: fields at shuffled offsets with random padding, row padding.

    Returns (message-like namespace, {name: expected values array of shape (N,) or (N, count)}).
    """
    rng = random.Random(seed)
    order = list(field_types)
    if shuffle:
        rng.shuffle(order)
    specs, offset = [], 0
    for name, datatype, count in order:
        offset += rng.randint(0, max_pad)
        specs.append(FieldSpec(name, offset, datatype, count))
        offset += SIZE[datatype] * count
    point_step = offset + rng.randint(0, max_pad)
    row_step = width * point_step + row_pad
    n = height * width
    raw = bytearray(rng.getrandbits(8) for _ in range(height * row_step))  # padding bytes are garbage
    expected = {s.name: [] for s in specs}
    endian = ">" if big_endian else "<"
    for r in range(height):
        for c in range(width):
            base = r * row_step + c * point_step
            for s in specs:
                vals = [_value(rng, s.datatype) for _ in range(s.count)]
                struct.pack_into(f"{endian}{s.count}{STRUCT[s.datatype]}", raw, base + s.offset, *vals)
                expected[s.name].append(vals if s.count > 1 else vals[0])
    msg = SimpleNamespace(height=height, width=width, fields=specs, is_bigendian=big_endian,
                          point_step=point_step, row_step=row_step, data=bytes(raw), is_dense=False)
    return msg, {k: np.array(v).reshape((n, -1) if k_count > 1 else (n,))
                 for (k, v), k_count in zip(expected.items(), [s.count for s in specs])}


ALL_TYPES = [("x", FLOAT32, 1), ("y", FLOAT32, 1), ("z", FLOAT32, 1), ("i8", INT8, 1), ("u8", UINT8, 1),
             ("i16", INT16, 1), ("u16", UINT16, 1), ("i32", INT32, 1), ("u32", UINT32, 1),
             ("f64", FLOAT64, 1), ("rgb", UINT8, 3), ("normal", FLOAT32, 3), ("t2", FLOAT64, 2)]


def _check(points: np.ndarray, expected: dict[str, np.ndarray]) -> None:
    assert set(points.dtype.names) == set(expected)
    for name, values in expected.items():
        np.testing.assert_array_equal(points[name].reshape(values.shape), values.astype(points[name].dtype))
        assert points[name].dtype.isnative


@pytest.mark.parametrize("seed", range(24))
def test_random_layouts_decode_and_round_trip(seed: int) -> None:
    rng = random.Random(1000 + seed)
    types = rng.sample(ALL_TYPES[3:], rng.randint(0, len(ALL_TYPES) - 3))
    xyz_type = rng.choice([FLOAT32, FLOAT64])
    types += [(c, xyz_type, 1) for c in "xyz"]
    height, width = rng.choice([(1, 17), (3, 5), (4, 1), (2, 9)])
    msg, expected = build_cloud(types, height=height, width=width, seed=seed,
                                row_pad=rng.choice([0, 0, 3, 16]), big_endian=rng.random() < 0.25)
    points = read_points(msg)
    assert points.shape == (height * width,)
    _check(points, expected)

    xyz = read_xyz(msg)
    assert xyz.dtype == np.float32 and xyz.shape == (height * width, 3)
    for i, c in enumerate("xyz"):
        np.testing.assert_array_equal(xyz[:, i], expected[c].astype(np.float32))

    # Encode and decode again: same values, packed layout.
    layout = write_points(points)
    assert layout.point_step == points.dtype.itemsize
    assert layout.row_step == layout.width * layout.point_step
    assert layout.data.dtype == np.uint8 and layout.data.size == layout.row_step * layout.height
    _check(read_points(layout), expected)


@pytest.mark.parametrize("datatype", [INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64])
@pytest.mark.parametrize("big_endian", [False, True])
def test_every_datatype_extremes(datatype: int, big_endian: bool) -> None:
    if datatype in RANGE:
        values = np.array([RANGE[datatype][0], RANGE[datatype][1], 0, 1])
    else:
        values = np.array([-1.5, 3.25e5, 0.0, np.inf])
    specs = [FieldSpec("x", 0, FLOAT32), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32),
             FieldSpec("v", 13, datatype)]
    point_step = 13 + SIZE[datatype] + 1
    endian = ">" if big_endian else "<"
    raw = bytearray(point_step * len(values))
    for i, v in enumerate(values):
        struct.pack_into(f"{endian}3f", raw, i * point_step, float(i), -float(i), 0.5)
        struct.pack_into(endian + STRUCT[datatype], raw, i * point_step + 13, v.item())
    msg = SimpleNamespace(height=1, width=len(values), fields=specs, is_bigendian=big_endian,
                          point_step=point_step, row_step=point_step * len(values), data=bytes(raw))
    points = read_points(msg)
    np.testing.assert_array_equal(points["v"], values)
    assert points["v"].dtype.isnative and points["v"].dtype.itemsize == SIZE[datatype]
    np.testing.assert_array_equal(read_xyz(msg), [[i, -i, 0.5] for i in range(len(values))])


def test_cloud_dtype_offsets_and_padding() -> None:
    dt = cloud_dtype([FieldSpec("intensity", 16, FLOAT32), FieldSpec("x", 0, FLOAT32),
                      FieldSpec("rgb", 20, UINT8, 3), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32)], 32)
    assert dt.itemsize == 32
    assert dt.fields["intensity"][1] == 16 and dt.fields["x"][1] == 0
    assert dt.fields["rgb"][0].shape == (3,)
    big = cloud_dtype([FieldSpec("x", 0, FLOAT64)], 8, is_bigendian=True)
    assert big.fields["x"][0].byteorder == ">"


def test_hesai_packed_unaligned_layout() -> None:
    """Hesai driver layout: x y z intensity f32, ring u16 at 16, timestamp f64 at 18, point_step 26."""
    xyz = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    specs = [FieldSpec("x", 0, FLOAT32), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32),
             FieldSpec("intensity", 12, FLOAT32), FieldSpec("ring", 16, UINT16), FieldSpec("timestamp", 18, FLOAT64)]
    raw = bytearray()
    for i, p in enumerate(xyz):
        raw += struct.pack("<4fHd", *p, 7.0, i % 40, 1.7e9 + i * 1e-5)
    msg = SimpleNamespace(height=1, width=50, fields=specs, is_bigendian=False, point_step=26, row_step=26 * 50,
                          data=array.array("B", raw))
    np.testing.assert_array_equal(read_xyz(msg), xyz)
    pts = read_points(msg)
    np.testing.assert_array_equal(pts["ring"], np.arange(50) % 40)
    np.testing.assert_allclose(pts["timestamp"], 1.7e9 + np.arange(50) * 1e-5, rtol=0, atol=1e-6)


def test_organised_cloud_with_row_padding() -> None:
    msg, expected = build_cloud([("x", FLOAT32, 1), ("y", FLOAT32, 1), ("z", FLOAT32, 1), ("r", UINT16, 1)],
                                height=4, width=6, seed=3, shuffle=False, max_pad=0, row_pad=8)
    assert msg.row_step == msg.width * msg.point_step + 8
    pts = read_points(msg)
    _check(pts, expected)
    np.testing.assert_array_equal(read_xyz(msg), np.stack([expected[c] for c in "xyz"], 1))  # fast path
    shuffled, expected2 = build_cloud([("x", FLOAT32, 1), ("y", FLOAT64, 1), ("z", INT16, 1)],
                                      height=3, width=5, seed=4, row_pad=5)
    np.testing.assert_array_equal(read_xyz(shuffled), np.stack([expected2[c] for c in "xyz"], 1).astype(np.float32))
    # Row-major order: point (row 2, col 5) is element 17.
    raw = np.frombuffer(msg.data, np.uint8)
    start = 2 * msg.row_step + 5 * msg.point_step
    assert pts["x"][17] == raw[start:start + 4].view("<f4")[0]


def test_data_longer_than_needed_is_accepted() -> None:
    msg, expected = build_cloud([("x", FLOAT32, 1), ("y", FLOAT32, 1), ("z", FLOAT32, 1)],
                                height=1, width=4, seed=1)
    msg.data = msg.data + b"\x00" * 7
    _check(read_points(msg), expected)


def test_float64_xyz_becomes_float32() -> None:
    msg, expected = build_cloud([("x", FLOAT64, 1), ("y", FLOAT64, 1), ("z", FLOAT64, 1)],
                                height=1, width=10, seed=2, shuffle=False, max_pad=0)
    xyz = read_xyz(msg)
    assert xyz.dtype == np.float32
    np.testing.assert_array_equal(xyz, np.stack([expected[c] for c in "xyz"], 1).astype(np.float32))


def test_non_finite_points_are_kept() -> None:
    xyz = np.array([[1, 2, 3], [np.nan, 0, 0], [np.inf, -np.inf, 1]], dtype=np.float32)
    layout = write_points(xyz_array_to_structured(xyz))
    out = read_xyz(layout)
    assert out.shape == (3, 3)
    np.testing.assert_array_equal(out, xyz)


# --- real message classes ------------------------------------------------------------------------

def _reference_cloud():
    xyz = np.random.default_rng(5).uniform(-50, 50, size=(40, 3)).astype(np.float32)
    arr = xyz_array_to_structured(xyz, intensity=np.linspace(0, 1, 40, dtype=np.float32),
                                  ring=(np.arange(40) % 16).astype(np.uint16))
    return xyz, arr


def test_rclpy_message() -> None:
    pytest.importorskip("rclpy")
    from sensor_msgs.msg import PointCloud2, PointField

    xyz, arr = _reference_cloud()
    layout = write_points(arr)
    msg = PointCloud2(height=1, width=layout.width, point_step=layout.point_step, row_step=layout.row_step,
                      is_bigendian=False, is_dense=True,
                      fields=[PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                              for f in layout.fields])
    msg.data = array.array("B", layout.data.tobytes())
    assert isinstance(msg.data, array.array)
    np.testing.assert_array_equal(read_xyz(msg), xyz)
    pts = read_points(msg)
    np.testing.assert_array_equal(pts["ring"], arr["ring"])
    assert np.shares_memory(pts, np.frombuffer(msg.data, np.uint8))  # zero-copy view of msg.data


def _rosbags_types():
    typestore_mod = pytest.importorskip("rosbags.typesys")
    store = typestore_mod.get_typestore(typestore_mod.Stores.ROS2_JAZZY)
    return store, store.types["sensor_msgs/msg/PointCloud2"], store.types["sensor_msgs/msg/PointField"]


def test_rosbags_message_and_cdr_round_trip() -> None:
    store, PointCloud2, PointField = _rosbags_types()
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    xyz, arr = _reference_cloud()
    layout = write_points(arr)
    msg = PointCloud2(header=Header(stamp=Time(sec=1, nanosec=2), frame_id="lidar"), height=1, width=layout.width,
                      fields=[PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                              for f in layout.fields],
                      is_bigendian=False, point_step=layout.point_step, row_step=layout.row_step,
                      data=layout.data.copy(), is_dense=True)
    pts = read_points(msg)
    assert np.shares_memory(pts, msg.data)
    np.testing.assert_array_equal(read_xyz(msg), xyz)
    # As read back from a bag: CDR bytes -> message with a numpy data array.
    back = store.deserialize_cdr(store.serialize_cdr(msg, PointCloud2.__msgtype__), PointCloud2.__msgtype__)
    assert isinstance(back.data, np.ndarray)
    np.testing.assert_array_equal(read_xyz(back), xyz)
    np.testing.assert_array_equal(read_points(back)["intensity"], arr["intensity"])


# --- zero copy -----------------------------------------------------------------------------------

def test_zero_copy_paths() -> None:
    xyz, arr = _reference_cloud()
    layout = write_points(arr)
    assert np.shares_memory(layout.data, arr)
    pts = read_points(layout)
    assert np.shares_memory(pts, arr)
    assert not np.shares_memory(read_xyz(layout), arr)  # read_xyz always returns a fresh array
    ba = bytearray(layout.data.tobytes())
    msg = SimpleNamespace(**{k: getattr(layout, k) for k in
                             ("height", "width", "fields", "point_step", "row_step", "is_bigendian")}, data=ba)
    pts = read_points(msg)
    ba[0:4] = struct.pack("<f", 123.5)
    assert pts["x"][0] == 123.5  # a view: the change in the buffer shows


def test_write_points_organised_and_big_endian_input() -> None:
    arr = np.zeros((3, 4), dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("t", ">f8")])
    arr["x"] = np.arange(12).reshape(3, 4)
    arr["t"] = 0.25
    layout = write_points(arr)
    assert (layout.height, layout.width, layout.point_step, layout.is_bigendian) == (3, 4, 20, False)
    pts = read_points(layout)
    np.testing.assert_array_equal(pts["x"], np.arange(12))
    np.testing.assert_array_equal(pts["t"], 0.25)


def test_write_points_non_contiguous_and_empty() -> None:
    _, arr = _reference_cloud()
    layout = write_points(arr[::2])
    np.testing.assert_array_equal(read_points(layout)["ring"], arr["ring"][::2])
    empty = write_points(arr[:0])
    assert empty.width == 0 and empty.data.size == 0
    assert read_xyz(empty).shape == (0, 3)


def test_write_points_rejects_unsupported_types() -> None:
    with pytest.raises(PointCloud2Error, match="'bad'.*int64"):
        write_points(np.zeros(3, dtype=[("x", "f4"), ("bad", "i8")]))
    with pytest.raises(PointCloud2Error, match="structured"):
        write_points(np.zeros((3, 3), dtype=np.float32))


def test_xyz_array_to_structured() -> None:
    xyz = np.arange(12, dtype=np.float64).reshape(4, 3)
    arr = xyz_array_to_structured(xyz, label=np.array([1, 2, 3, 4], np.uint8), normal=np.ones((4, 3), np.float32))
    assert arr.dtype["x"] == np.float32 and arr.dtype["label"] == np.uint8 and arr.dtype["normal"].shape == (3,)
    np.testing.assert_array_equal(arr["z"], [2, 5, 8, 11])
    layout = write_points(arr)
    assert [f.count for f in layout.fields if f.name == "normal"] == [3]
    with pytest.raises(PointCloud2Error, match="column 'label'"):
        xyz_array_to_structured(xyz, label=np.zeros(3))
    with pytest.raises(PointCloud2Error, match=r"\(N, 3\)"):
        xyz_array_to_structured(xyz[:, :2])


# --- empty and malformed -------------------------------------------------------------------------

def _msg(**overrides):
    base = dict(height=1, width=2, is_bigendian=False, point_step=12, row_step=24, data=bytes(24),
                fields=[FieldSpec("x", 0, FLOAT32), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32)])
    base.update(overrides)
    return SimpleNamespace(**base)


def test_empty_clouds() -> None:
    for msg in (_msg(width=0, row_step=0, data=b""), _msg(height=0, data=b""),
                _msg(width=0, row_step=0, data=b"", fields=[], point_step=0)):
        assert read_points(msg).shape == (0,)
        assert read_xyz(msg).shape == (0, 3) and read_xyz(msg).dtype == np.float32


@pytest.mark.parametrize("overrides, pattern", [
    (dict(fields=[FieldSpec("x", 0, FLOAT32), FieldSpec("y", 4, FLOAT32)]), r"no 'z' field \(fields: x, y\)"),
    (dict(fields=[FieldSpec("intensity", 0, FLOAT32)]), r"no 'x', 'y', 'z' field"),
    (dict(fields=[FieldSpec("x", 0, FLOAT32), FieldSpec("y", 4, 9), FieldSpec("z", 8, FLOAT32)]),
     r"field 'y' has unsupported datatype 9"),
    (dict(fields=[FieldSpec("x", 0, 0), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32)]),
     r"field 'x' has unsupported datatype 0"),
    (dict(data=bytes(23)), r"data has 23 bytes, shorter than height\*row_step = 1\*24 = 24"),
    (dict(height=2, width=1, row_step=16, data=bytes(24)), r"data has 24 bytes.*2\*16 = 32"),
    (dict(point_step=10, row_step=20, data=bytes(20)), r"point_step 10 is smaller than the fields need \(field 'z'"),
    (dict(row_step=20), r"row_step 20 is smaller than width\*point_step = 2\*12"),
    (dict(point_step=0, row_step=0, fields=[]), r"point_step 0 must be positive"),
    (dict(fields=[FieldSpec("x", 0, FLOAT32), FieldSpec("x", 4, FLOAT32), FieldSpec("z", 8, FLOAT32)]),
     r"field 'x' appears more than once"),
    (dict(fields=[FieldSpec("x", -4, FLOAT32), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32)]),
     r"field 'x' has negative offset -4"),
    (dict(fields=[FieldSpec("x", 0, FLOAT32, 2), FieldSpec("y", 8, FLOAT32)], point_step=12),
     r"no 'z'"),
])
def test_malformed_messages_raise(overrides: dict, pattern: str) -> None:
    with pytest.raises(PointCloud2Error, match=pattern):
        read_xyz(_msg(**overrides))


def test_xyz_with_count_above_one_is_refused() -> None:
    msg = _msg(fields=[FieldSpec("x", 0, FLOAT32, 2), FieldSpec("y", 8, FLOAT32), FieldSpec("z", 4, FLOAT32)])
    assert read_points(msg)["x"].shape == (2, 2)
    with pytest.raises(PointCloud2Error, match="field 'x' has count 2"):
        read_xyz(msg)


def test_read_points_checks_layout_too() -> None:
    with pytest.raises(PointCloud2Error, match="shorter than"):
        read_points(_msg(data=bytes(10)))
    # read_points does not need x/y/z
    assert read_points(_msg(fields=[FieldSpec("intensity", 0, FLOAT32)])).dtype.names == ("intensity",)


def test_count_zero_is_read_as_one() -> None:
    msg = _msg(fields=[FieldSpec("x", 0, FLOAT32, 0), FieldSpec("y", 4, FLOAT32, 0), FieldSpec("z", 8, FLOAT32, 0)],
               data=np.arange(6, dtype="<f4").tobytes())
    np.testing.assert_array_equal(read_xyz(msg), [[0, 1, 2], [3, 4, 5]])


def test_cloud_layout_defaults_row_step() -> None:
    layout = CloudLayout([FieldSpec("x", 0, FLOAT32)], 4, np.zeros(12, np.uint8), width=3)
    assert layout.row_step == 12 and layout.height == 1
