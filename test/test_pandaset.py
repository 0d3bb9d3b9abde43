"""PandaSet -> rosbag2: per-sensor clouds in the lidar frame, stamps, and boxes that stay put in the world."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import deserialize
from gd_completion.box_messages import detections_to_boxes
from gd_completion.cli import main
from gd_completion.datasets.pandaset import PandaSetSequence
from gd_completion.errors import DataFormatError
from gd_completion.pointcloud2 import read_points
from gd_completion.stamp_sync import stamp_to_ns

SEQ = "pandaset-002"
START = 55
INDICES = [55, 59, 60, 61]  # 56-58 have no lidar file; the lidar drives about 3 m over these frames


def _rotate(q: dict, v: np.ndarray) -> np.ndarray:
    """Rotate rows of `v` by the unit quaternion q (dict w, x, y, z): v + 2 u x (u x v + w v)."""
    w = q["w"]
    u = np.array([q["x"], q["y"], q["z"]])
    norm = math.sqrt(w * w + u @ u)
    w, u = w / norm, u / norm
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


@pytest.fixture(scope="module")
def panda_bag(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("panda") / "panda_bag"
    assert main(["convert", "pandaset", str(shared_data / SEQ), str(out), "--start", str(START),
                 "--frames", str(len(INDICES))]) == 0
    topics: dict[str, list] = {}
    with open_bag(out) as reader:
        for conn, stamp, raw in iter_raw(reader, reader.connections):
            topics.setdefault(conn.topic, []).append((stamp, deserialize(raw, conn.msgtype)))
    return out, topics


def test_clouds_per_sensor_in_lidar_frame(panda_bag: tuple[Path, dict], shared_data: Path) -> None:
    _, topics = panda_bag
    root = shared_data / SEQ
    poses = json.loads((root / "lidar" / "poses.json").read_text())
    stamps = json.loads((root / "lidar" / "timestamps.json").read_text())
    assert sorted(topics) == ["/pandar64/detections", "/pandar64/markers", "/pandar64/points", "/pandargt/points"]
    for sensor, topic in ((0, "/pandar64/points"), (1, "/pandargt/points")):
        assert len(topics[topic]) == len(INDICES)
        for index, (stamp, msg) in zip(INDICES, topics[topic]):
            data = np.load(root / "lidar" / f"{index:02d}.npz")
            mask = data["sensor"] == sensor
            pts = read_points(msg)
            assert msg.header.frame_id == "pandar64"
            assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "timestamp"]
            assert len(pts) == int(mask.sum()) > 10_000
            assert stamp == stamp_to_ns(msg.header.stamp) == round(stamps[index] * 1e9)
            xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1).astype(np.float64)
            world = _rotate(poses[index]["heading"], xyz) + [poses[index]["position"][k] for k in "xyz"]
            np.testing.assert_allclose(world, data["xyz"][mask], atol=2e-3)
            np.testing.assert_array_equal(pts["timestamp"], data["t"][mask])
            np.testing.assert_array_equal(pts["intensity"], data["intensity"][mask])
        if sensor == 0:  # the sensor sits at the origin of its own frame: ranges look like a lidar's
            r = np.hypot(xyz[:, 0], xyz[:, 1])
            assert np.median(r) < 40 and r.min() < 5


def test_stationary_car_stays_put_in_world(panda_bag: tuple[Path, dict], shared_data: Path) -> None:
    _, topics = panda_bag
    root = shared_data / SEQ
    poses = json.loads((root / "lidar" / "poses.json").read_text())
    cuboids = {i: json.loads((root / "cuboids" / f"{i:02d}.json").read_text()) for i in INDICES}
    parked = [c for c in cuboids[START] if c["label"] == "Car" and c["stationary"] and c["cuboids.sensor_id"] != 1
              and all(any(d["uuid"] == c["uuid"] for d in frame) for frame in cuboids.values())]
    assert parked
    car = min(parked, key=lambda c: math.hypot(c["position.x"], c["position.y"]))
    world_centres, sensor_centres, ids = [], [], set()
    for index, (_, det) in zip(INDICES, topics["/pandar64/detections"]):
        boxes = detections_to_boxes(det).boxes
        centres = np.array([b.center for b in boxes])
        world = _rotate(poses[index]["heading"], centres) + [poses[index]["position"][k] for k in "xyz"]
        record = next(c for c in cuboids[index] if c["uuid"] == car["uuid"])
        k = int(np.argmin(np.linalg.norm(world - [record[f"position.{a}"] for a in "xyz"], axis=1)))
        np.testing.assert_allclose(world[k], [record[f"position.{a}"] for a in "xyz"], atol=1e-6)
        box = boxes[k]
        assert box.label == "car" and box.size == pytest.approx(
            (record["dimensions.y"], record["dimensions.x"], record["dimensions.z"]))
        heading = _rotate(poses[index]["heading"], np.array([[math.cos(box.yaw), math.sin(box.yaw), 0.0]]))[0]
        assert math.cos(math.atan2(heading[1], heading[0]) - (record["yaw"] + math.pi / 2)) > math.cos(0.03)
        world_centres.append(world[k])
        sensor_centres.append(centres[k])
        ids.add(box.instance_id)
    assert len(ids) == 1  # stable track id
    world_spread = np.ptp(np.array(world_centres), axis=0).max()
    assert world_spread < 0.2  # parked: stays put in the world ...
    assert np.ptp(np.array(sensor_centres), axis=0).max() > 5 * world_spread + 0.5  # ... while the lidar moves


def test_missing_frames_are_listed(shared_data: Path) -> None:
    seq = PandaSetSequence(shared_data / SEQ)
    assert seq.missing_frames() == [56, 57, 58, 71]
    assert len(seq.frame_indices()) == 76


def test_not_a_pandaset_folder(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "bag"
    assert main(["convert", "pandaset", str(tmp_path), str(out)]) == 2
    assert "lidar/" in capsys.readouterr().err and not out.exists()


def test_corrupt_lidar_file(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = tmp_path / "seq"
    (root / "lidar").mkdir(parents=True)
    (root / "cuboids").symlink_to(shared_data / SEQ / "cuboids")
    for name in ("poses.json", "timestamps.json", "00.npz"):
        (root / "lidar" / name).symlink_to(shared_data / SEQ / "lidar" / name)
    (root / "lidar" / "01.npz").write_bytes((shared_data / SEQ / "lidar" / "01.npz").read_bytes()[:5000])
    out = tmp_path / "bag"
    assert main(["convert", "pandaset", str(root), str(out), "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert "01.npz" in err and "error" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


DEVKIT_INDICES = [55, 59, 60]  # a gap (56-58) inside the copied frames


def _write_devkit(src: Path, root: Path, indices: list[int]) -> Path:
    """Official devkit layout of `src` (lidar/NN.pkl.gz, annotations/cuboids/NN.pkl.gz), lidar frames `indices`."""
    pd = pytest.importorskip("pandas")
    (root / "lidar").mkdir(parents=True)
    (root / "annotations" / "cuboids").mkdir(parents=True)
    (root / "meta").symlink_to(src / "meta")
    gzip_fast = {"method": "gzip", "compresslevel": 1}  # the default level 9 takes seconds per frame
    for name in ("poses.json", "timestamps.json"):
        (root / "lidar" / name).symlink_to(src / "lidar" / name)
    for index in indices:
        with np.load(src / "lidar" / f"{index:02d}.npz") as data:
            xyz = data["xyz"].astype(np.float64)
            pd.DataFrame({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "i": data["intensity"].astype(np.float64),
                          "t": data["t"], "d": data["sensor"].astype(np.int64)}).to_pickle(
                root / "lidar" / f"{index:02d}.pkl.gz", compression=gzip_fast)
    for path in sorted((src / "cuboids").glob("*.json")):  # every frame: track ids count over the whole sequence
        pd.DataFrame.from_records(json.loads(path.read_text())).to_pickle(
            root / "annotations" / "cuboids" / f"{path.stem}.pkl.gz", compression=gzip_fast)
    return root


@pytest.fixture(scope="module")
def devkit_root(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_devkit(shared_data / SEQ, tmp_path_factory.mktemp("devkit") / "002", DEVKIT_INDICES)


def test_devkit_layout_reads_like_npz(devkit_root: Path, shared_data: Path) -> None:
    npz, pkl = PandaSetSequence(shared_data / SEQ), PandaSetSequence(devkit_root)
    assert (npz.devkit, pkl.devkit) == (False, True)
    assert pkl.frame_indices() == DEVKIT_INDICES
    assert pkl.missing_frames() == [i for i in range(80) if i not in DEVKIT_INDICES]
    assert pkl.track_ids == npz.track_ids and len(pkl.track_ids) > 100
    assert pkl.cuboid_indices() == npz.cuboid_indices() == list(range(80))
    from gd_completion.evaluation.pandaset_eval import stationary_vehicles
    assert stationary_vehicles(pkl) == stationary_vehicles(npz) and len(stationary_vehicles(npz)) == 56
    for index in DEVKIT_INDICES:
        records = pkl.cuboids(index)
        assert records == npz.cuboids(index) and records
        assert {type(v) for r in records for v in r.values()} <= {str, float, int, bool, type(None)}
        assert any(r["attributes.object_motion"] is None for r in records)  # NaN in the DataFrame -> None
        lidar_npz, lidar_pkl = npz.load_lidar(index), pkl.load_lidar(index)
        for key, array in lidar_npz.items():
            assert lidar_pkl[key].dtype == array.dtype and lidar_pkl[key].shape == array.shape
            np.testing.assert_array_equal(lidar_pkl[key], array)
        for a, b in zip(npz.frame(index, (0, 1)), pkl.frame(index, (0, 1)), strict=True):
            assert (b.name, b.stamp_ns, b.frame_id) == (a.name, a.stamp_ns, a.frame_id)
            assert b.xyz.dtype == np.float32 and len(b.xyz) > 10_000
            np.testing.assert_array_equal(b.xyz, a.xyz)
            np.testing.assert_array_equal(b.intensity, a.intensity)
            np.testing.assert_array_equal(b.extra["timestamp"], a.extra["timestamp"])
            assert (b.boxes, b.source_labels, b.track_ids) == (a.boxes, a.source_labels, a.track_ids)
            assert b.boxes


def test_convert_devkit_layout(devkit_root: Path, shared_data: Path, tmp_path: Path) -> None:
    def messages(bag: Path) -> list[tuple[str, int, bytes]]:
        with open_bag(bag) as reader:
            return [(conn.topic, stamp, bytes(raw)) for conn, stamp, raw in iter_raw(reader, reader.connections)]

    n = str(len(DEVKIT_INDICES))
    assert main(["convert", "pandaset", str(devkit_root), str(tmp_path / "pkl"), "--frames", n]) == 0
    assert main(["convert", "pandaset", str(shared_data / SEQ), str(tmp_path / "npz"), "--start",
                 str(DEVKIT_INDICES[0]), "--frames", n]) == 0
    from_pkl, from_npz = messages(tmp_path / "pkl"), messages(tmp_path / "npz")
    assert len(from_pkl) == len(from_npz) == 4 * len(DEVKIT_INDICES)  # two clouds, detections, markers
    assert sorted(from_pkl) == sorted(from_npz)  # byte for byte


def test_corrupt_devkit_pickle(devkit_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = tmp_path / "seq"
    (root / "lidar").mkdir(parents=True)
    (root / "annotations").symlink_to(devkit_root / "annotations")
    for name in ("poses.json", "timestamps.json", "55.pkl.gz"):
        (root / "lidar" / name).symlink_to(devkit_root / "lidar" / name)
    (root / "lidar" / "59.pkl.gz").write_bytes((devkit_root / "lidar" / "59.pkl.gz").read_bytes()[:5000])
    with pytest.raises(DataFormatError, match=r"59\.pkl\.gz: cannot read pickle"):
        PandaSetSequence(root).load_lidar(59)
    out = tmp_path / "bag"
    assert main(["convert", "pandaset", str(root), str(out), "--start", "55", "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert "59.pkl.gz" in err and "error" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_devkit_layout_without_pandas(devkit_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pandas", None)  # `import pandas` raises ImportError
    with pytest.raises(DataFormatError, match="pip install pandas") as info:
        PandaSetSequence(devkit_root)
    assert str(devkit_root) in str(info.value)
