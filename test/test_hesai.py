"""Hesai decoder: reference clouds of the nebula driver, error cases, `convert hesai` round trip."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from gd_completion.bags.hesai_conversion import PANDAR_SCAN
from gd_completion.bags.messages import header, stamp
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import deserialize, message_class, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer
from gd_completion.errors import DataFormatError, GDCompletionError
from gd_completion.hesai import ScanAssembler, decode_packets, decode_scan, load_calibration, read_pcd
from gd_completion.hesai.decoder import ReturnType
from gd_completion.hesai.packets import packet_time_s, packets_to_array, parse_packets
from gd_completion.pointcloud2 import read_points
from gd_completion.stamp_sync import stamp_to_ns
from gd_completion.tools.convert_hesai import add_hesai_parser

CASES = {
    "40p": ("40p/1673400149412331409", "40p/1673400149711850138.pcd", "Pandar40P.csv", 1673400149711850138),
    "64": ("64/1673403880599376836", "64/1673403880898440686.pcd", "Pandar64.csv", 1673403880898440686),
}


def _root(shared_data: Path) -> Path:
    root = shared_data / "hesai-nebula"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    return root


_CACHE: dict[str, list[tuple[int, list[bytes]]]] = {}


def _messages(bag: Path) -> list[tuple[int, list[bytes]]]:
    """(bag time ns, packets) of every PandarScan message."""
    key = str(bag)
    if key not in _CACHE:
        out = []
        with open_bag(bag) as reader:
            for _conn, ns, raw in iter_raw(reader):
                msg = deserialize(raw, PANDAR_SCAN)
                out.append((ns, [bytes(p.data[: int(p.size)]) for p in msg.packets]))
        _CACHE[key] = out
    return _CACHE[key]


def _xyz(points: np.ndarray) -> np.ndarray:
    return np.stack([points["x"], points["y"], points["z"]], axis=1).astype(np.float64)


def fraction_within(a: np.ndarray, b: np.ndarray, tol: float = 0.01) -> float:
    """Fraction of points of `a` with a point of `b` within `tol` (exact, via a voxel hash of `b`)."""
    if len(a) == 0:
        return 1.0
    if len(b) == 0:
        return 0.0

    def hashed(cells: np.ndarray) -> np.ndarray:
        return cells[:, 0] * 73856093 ^ cells[:, 1] * 19349663 ^ cells[:, 2] * 83492791

    cells_b = np.floor(b / tol).astype(np.int64)
    hb = hashed(cells_b)
    order = np.argsort(hb, kind="stable")
    hb, b_sorted = hb[order], b[order]
    cells_a = np.floor(a / tol).astype(np.int64)
    found = np.zeros(len(a), dtype=bool)
    for shift in np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1]), -1).reshape(-1, 3):
        h = hashed(cells_a + shift)
        lo, hi = np.searchsorted(hb, h, "left"), np.searchsorted(hb, h, "right")
        for j in range(int((hi - lo).max())):
            idx = lo + j
            ok = (idx < hi) & ~found
            if not ok.any():
                continue
            d = np.linalg.norm(a[ok] - b_sorted[idx[ok]], axis=1)
            found[np.flatnonzero(ok)[d <= tol]] = True
    return float(found.mean())


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request, shared_data):
    root = _root(shared_data)
    bag, pcd, csv_name, ref_ns = CASES[request.param]
    return dict(name=request.param, bag=root / bag, messages=_messages(root / bag), reference=read_pcd(root / pcd),
                calibration=load_calibration(root / "calibration" / csv_name), ref_ns=ref_ns,
                csv=root / "calibration" / csv_name)


def _reference_scan(case) -> np.ndarray:
    """The scan that the assembler completes while it is fed the reference message (as the driver does)."""
    assembler = ScanAssembler(case["calibration"])
    found = None
    for ns, packets in case["messages"]:
        scans = assembler.add(packets)
        if ns == case["ref_ns"]:
            assert len(scans) == 1
            found = scans[0]
    assert found is not None
    return found


def test_matches_reference_cloud(case):
    scan = _reference_scan(case)
    ref = _xyz(case["reference"])
    ours = _xyz(scan)
    ref_in_ours, ours_in_ref = fraction_within(ref, ours), fraction_within(ours, ref)
    print(f"{case['name']}: {len(ours)} decoded vs {len(ref)} reference points; "
          f"{ref_in_ours:.5%} of reference within 1 cm, {ours_in_ref:.5%} of decoded within 1 cm")
    assert ref_in_ours >= 0.99
    assert ours_in_ref >= 0.99


def test_scan_fields(case):
    scan = _reference_scan(case)
    n_lasers = case["calibration"].n_lasers
    assert scan.dtype.names == ("x", "y", "z", "intensity", "ring", "timestamp", "return_type")
    assert scan["ring"].max() < n_lasers and len(np.unique(scan["ring"])) > n_lasers // 2
    span = np.ptp(scan["timestamp"])
    assert 0.09 < span < 0.11  # one rotation at 10 Hz
    distance = np.linalg.norm(_xyz(scan), axis=1)
    assert distance.min() >= 0.3 - 1e-4 and distance.max() <= 200.0 + 1e-3
    # Dual return: both echoes present, identical second echoes dropped.
    types = set(np.unique(scan["return_type"]).tolist())
    assert {ReturnType.LAST, ReturnType.STRONGEST, ReturnType.IDENTICAL} <= types


def test_decode_scan_on_packet_rotation(case):
    """decode_scan over the packets of one rotation (cut at packet granularity) is close to the reference."""
    packets = [p for _, ps in case["messages"] for p in ps]
    fmt, array = packets_to_array(packets)
    azimuth = parse_packets(fmt, array)["blocks"]["azimuth"][:, 0].astype(np.int64)
    wraps = np.flatnonzero(np.diff(azimuth) < 0) + 1
    ref = _xyz(case["reference"])
    best = max(
        (fraction_within(ref, _xyz(decode_scan(packets[s:e], case["calibration"], min_range=0.3, max_range=200.0,
                                               fov=(0.0, 360.0)))), s)
        for s, e in zip(wraps[:-1], wraps[1:])
    )
    assert best[0] >= 0.99


def test_dual_return_dedupe(case):
    packets = case["messages"][0][1]
    kept = decode_packets(packets, case["calibration"])
    everything = decode_packets(packets, case["calibration"], dedupe_dual=False)
    identical = int((kept["return_type"] == ReturnType.IDENTICAL).sum())
    assert identical > 0
    assert len(everything) == len(kept) + identical


def test_fov_filter(case):
    packets = case["messages"][1][1]
    points = decode_packets(packets, case["calibration"], fov=(90.0, 180.0))
    azimuth = np.degrees(np.arctan2(points["x"], points["y"])) % 360.0
    assert len(points) > 0
    assert np.all((azimuth >= 90.0 - 0.01) & (azimuth <= 180.0 + 0.01))


# --- errors ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def p40(shared_data):
    root = _root(shared_data)
    return _messages(root / CASES["40p"][0])[0][1][:20], load_calibration(root / "calibration" / "Pandar40P.csv")


@pytest.fixture(scope="module")
def p64(shared_data):
    root = _root(shared_data)
    return _messages(root / CASES["64"][0])[0][1][:20], load_calibration(root / "calibration" / "Pandar64.csv")


def test_truncated_packet(p40):
    packets, calibration = p40
    bad = list(packets)
    bad[7] = bad[7][:1000]
    with pytest.raises(DataFormatError, match=r"packet 7 has 1000 bytes"):
        decode_packets(bad, calibration, source="drive.db3")
    with pytest.raises(DataFormatError, match="drive.db3"):
        decode_packets(bad, calibration, source="drive.db3")


def test_wrong_model(p40, p64):
    with pytest.raises(DataFormatError, match=r"pandar64 packets have 1194 or 1198 bytes"):
        decode_packets(p40[0], p64[1], model="pandar64")
    with pytest.raises(DataFormatError, match=r"not a Pandar40/40P"):
        decode_packets([b"\x00" * 1262], p40[1])
    with pytest.raises(DataFormatError, match=r"unknown Hesai model"):
        decode_packets(p40[0], p40[1], model="pandar128")


def test_calibration_does_not_fit_model(p40, p64):
    with pytest.raises(DataFormatError, match=r"Pandar40P.csv: calibration has 40 lasers"):
        decode_packets(p64[0], p40[1])


def test_unknown_laser_count(p64):
    packets, calibration = p64
    bad = list(packets)
    bad[3] = bad[3][:2] + bytes([32]) + bad[3][3:]
    with pytest.raises(DataFormatError, match=r"packet 3 reports 32 lasers.*unknown laser count"):
        decode_packets(bad, calibration)


def test_unknown_return_mode(p40):
    packets, calibration = p40
    bad = list(packets)
    bad[2] = bad[2][:1254] + b"\x55" + bad[2][1255:]
    with pytest.raises(DataFormatError, match=r"packet 2 has unknown return mode 0x55"):
        decode_packets(bad, calibration)


def test_calibration_errors(tmp_path):
    with pytest.raises(DataFormatError, match="missing.csv: Hesai calibration file not found"):
        load_calibration(tmp_path / "missing.csv")
    cases = {
        "empty.csv": ("", "empty"),
        "header.csv": ("a,b,c\n1,2,3\n", "expected header"),
        "text.csv": ("Laser id,Elevation,Azimuth\n1,abc,0.1\n", "non-numeric"),
        "gap.csv": ("Laser id,Elevation,Azimuth\n1,1.0,0.1\n3,2.0,0.1\n", "without gaps"),
        "short.csv": ("Laser id,Elevation,Azimuth\n1,1.0\n", "fewer than 3 columns|non-numeric"),
        "norows.csv": ("Laser id,Elevation,Azimuth\n", "no laser rows"),
    }
    for name, (text, message) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(DataFormatError, match=rf"{name}: .*({message})"):
            load_calibration(path)


# --- convert hesai ---------------------------------------------------------------------------------------

def _convert(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    add_hesai_parser(parser.add_subparsers(dest="dataset"))
    args = parser.parse_args(["hesai", *argv])
    return args.func(args)


def _read_clouds(bag: Path) -> list[tuple[int, np.ndarray, object]]:
    out = []
    with open_bag(bag) as reader:
        for conn, ns, raw in iter_raw(reader):
            msg = deserialize(raw, conn.msgtype)
            out.append((ns, read_points(msg).copy(), msg))
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_convert_roundtrip(case, tmp_path, storage):
    out = tmp_path / "out"
    assert _convert([str(case["bag"]), str(out), "--calibration", str(case["csv"]), "--storage", storage,
                     "--frame-id", "pandar", "--time", "sensor", "--quiet"]) == 0
    clouds = _read_clouds(out)
    assembler = ScanAssembler(case["calibration"])
    expected = [s for _, ps in case["messages"] for s in assembler.add(ps)][1:]  # first rotation is partial
    assert len(clouds) == len(expected) >= 1
    for (ns, points, msg), scan in zip(clouds, expected):
        assert msg.header.frame_id == "pandar"
        assert points.dtype.names == ("x", "y", "z", "intensity", "ring", "timestamp")
        assert points.dtype["ring"] == np.uint16 and points.dtype["timestamp"] == np.float64
        for name in points.dtype.names:
            np.testing.assert_array_equal(points[name], scan[name])
        assert ns == int(round(scan["timestamp"].min() * 1e9))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    metadata = (out / "metadata.yaml").read_text()
    assert "version: 9" in metadata
    assert ("mcap" if storage == "mcap" else "sqlite3") in metadata


def _receive_and_sensor_times(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """Per packet of the bag: its receive stamp (s, host clock, from the message) and its lidar-clock time (s)."""
    receive, sensor = [], []
    with open_bag(bag) as reader:
        for _conn, _ns, raw in iter_raw(reader):
            msg = deserialize(raw, PANDAR_SCAN)
            packets = [bytes(p.data[: int(p.size)]) for p in msg.packets]
            fmt, array = packets_to_array(packets)
            sensor.append(packet_time_s(fmt, parse_packets(fmt, array)))
            receive.append(np.array([stamp_to_ns(p.stamp) for p in msg.packets], np.float64) * 1e-9)
    return np.concatenate(receive), np.concatenate(sensor)


def test_convert_default_time_is_host(case, tmp_path):
    """Without --time the clouds are on the host clock (the packets' receive stamps), which lines up with other
    topics; these drivers' lidar clocks run years behind it. Points are the same as with --time sensor."""
    parser = argparse.ArgumentParser()
    add_hesai_parser(parser.add_subparsers(dest="dataset"))
    assert parser.parse_args(["hesai", "in", "out", "--calibration", "c.csv"]).time == "host"
    common = [str(case["bag"]), "--calibration", str(case["csv"]), "--quiet"]
    assert _convert([common[0], str(tmp_path / "host"), *common[1:]]) == 0
    assert _convert([common[0], str(tmp_path / "sensor"), *common[1:], "--time", "sensor"]) == 0
    host, sensor = _read_clouds(tmp_path / "host"), _read_clouds(tmp_path / "sensor")
    receive, lidar_clock = _receive_and_sensor_times(case["bag"])
    clock_offset = float(np.median(receive - lidar_clock))
    assert clock_offset > 3.0e7  # about 5.3 years (40P) and 2.5 years (64) apart in these recordings
    assert len(host) == len(sensor) >= 1
    for (ns, points, msg), (_, reference, _) in zip(host, sensor):
        for name in ("x", "y", "z", "intensity", "ring"):
            np.testing.assert_array_equal(points[name], reference[name])
        shift = points["timestamp"] - reference["timestamp"]
        assert np.ptp(shift) < 1e-6 and abs(float(shift[0]) - clock_offset) < 1e-3
        assert ns == stamp_to_ns(msg.header.stamp) == int(round(points["timestamp"].min() * 1e9))
        # measured within the recording, before the packets carrying the points were received
        assert receive.min() - 0.11 < points["timestamp"].min() and points["timestamp"].max() < receive.max() + 1e-3


def test_convert_failure_leaves_no_bag(p40, tmp_path, shared_data):
    root = _root(shared_data)
    source = tmp_path / "broken_in"
    good = _messages(root / CASES["40p"][0])
    packet_type = message_class("pandar_msgs/msg/PandarPacket")
    scan_type = message_class(PANDAR_SCAN)
    with atomic_bag_writer(source, storage="mcap") as writer:
        conn = add_connection(writer, "/pandar_packets", PANDAR_SCAN)
        for i, (ns, packets) in enumerate(good):
            if i == 3:
                packets = [packets[0][:700]] + packets[1:]  # truncated packet in the last message
            data = [np.frombuffer(p.ljust(1500, b"\0"), dtype=np.uint8) for p in packets]
            msg = scan_type(header=header("pandar", ns),
                            packets=[packet_type(stamp=stamp(ns), data=d, size=len(p))
                                     for d, p in zip(data, packets)])
            writer.write(conn, ns, serialize(msg, PANDAR_SCAN))
    out = tmp_path / "out"
    with pytest.raises(DataFormatError, match=r"broken_in.*packet 0 has 700 bytes"):
        _convert([str(source), str(out), "--calibration", str(root / "calibration" / "Pandar40P.csv"), "--quiet"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken_in"]
    with pytest.raises(GDCompletionError):
        _convert([str(source), str(out), "--calibration", str(tmp_path / "nope.csv"), "--quiet"])
    assert not out.exists()
