"""KITTI -> rosbag2 -> back: point counts, points and lidar-frame boxes equal the source; bad input fails cleanly."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import deserialize
from gd_completion.box_messages import MARKER_CUBE, detections_to_boxes, markers_to_boxes
from gd_completion.cli import main
from gd_completion.datasets import kitti
from gd_completion.geometry import box_corners
from gd_completion.pointcloud2 import read_points
from gd_completion.stamp_sync import stamp_to_ns

KITTI = "kitti-object-sample/training"


def _calib(path: Path) -> np.ndarray:
    """4x4 rectified camera -> lidar, parsed independently of the reader."""
    rows = dict(line.split(":", 1) for line in path.read_text().splitlines() if ":" in line)
    r0 = np.eye(4)
    r0[:3, :3] = np.array(rows["R0_rect"].split(), float).reshape(3, 3)
    tr = np.eye(4)
    tr[:3, :] = np.array(rows["Tr_velo_to_cam"].split(), float).reshape(3, 4)
    return np.linalg.inv(r0 @ tr)


def _expected_corners(label_path: Path, calib_path: Path) -> tuple[list[np.ndarray], list[tuple]]:
    """Devkit-style corners: built in the camera frame around the bottom centre, rotated by ry about y."""
    cam_to_velo = _calib(calib_path)
    out, sizes = [], []
    for line in label_path.read_text().splitlines():
        f = line.split()
        if not f or f[0] == "DontCare":
            continue
        h, w, l, x, y, z, ry = map(float, f[8:15])
        sizes.append((l, w, h))
        xs = np.array([l, l, -l, -l, l, l, -l, -l]) / 2
        ys = np.array([0, 0, 0, 0, -h, -h, -h, -h])
        zs = np.array([w, -w, -w, w, w, -w, -w, w]) / 2
        rot = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
        cam = rot @ np.vstack([xs, ys, zs]) + np.array([[x], [y], [z]])
        out.append((cam_to_velo @ np.vstack([cam, np.ones(8)]))[:3].T)
    return out, sizes


def _same_box(corners_a: np.ndarray, corners_b: np.ndarray, tol: float = 1e-4) -> bool:
    """Equal as point sets (corner order conventions differ)."""
    d = np.linalg.norm(corners_a[:, None, :] - corners_b[None, :, :], axis=2)
    return bool((d.min(axis=1) < tol).all() and (d.min(axis=0) < tol).all())


def _rotation(q) -> np.ndarray:
    """3x3 matrix of a unit quaternion message (x, y, z, w)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _assert_camera_transform(tf_message, cam_to_velo: np.ndarray, stamp_ns: int) -> None:
    """/tf_static holds velo_link -> camera_rect: translation and rotation of the calibration's camera -> lidar."""
    (tf,) = tf_message.transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("velo_link", "camera_rect")
    assert stamp_to_ns(tf.header.stamp) == stamp_ns
    t, q = tf.transform.translation, tf.transform.rotation
    np.testing.assert_allclose([t.x, t.y, t.z], cam_to_velo[:3, 3], atol=1e-9)
    assert math.isclose(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2, 1.0, abs_tol=1e-12)
    np.testing.assert_allclose(_rotation(q), cam_to_velo[:3, :3], atol=1e-6)  # orthonormal to ~5e-8 already
    # Columns: the camera's axes in the lidar frame; it looks along the lidar's +x (z forward, x right, y down)
    np.testing.assert_allclose(_rotation(q), [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=0.02)


def _read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    out: dict[str, list] = {}
    with open_bag(path) as reader:
        for conn, stamp, raw in iter_raw(reader, reader.connections):
            out.setdefault(conn.topic, []).append((stamp, deserialize(raw, conn.msgtype)))
    return out


@pytest.fixture(scope="module")
def kitti_bag(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("kitti") / "kitti_bag"
    assert main(["convert", "kitti", str(shared_data / KITTI), str(out)]) == 0
    return out


def test_points_round_trip(kitti_bag: Path, shared_data: Path) -> None:
    topics = _read_bag(kitti_bag)
    scans = sorted((shared_data / KITTI / "velodyne").glob("*.bin"))
    clouds = topics["/kitti/points"]
    assert len(clouds) == len(scans) == 6
    for k, ((stamp, msg), scan) in enumerate(zip(clouds, scans)):
        source = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
        pts = read_points(msg)
        assert msg.header.frame_id == "velo_link"
        assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity"]
        assert len(pts) == len(source) == scan.stat().st_size // 16
        np.testing.assert_array_equal(np.stack([pts[n] for n in ("x", "y", "z", "intensity")], 1), source)
        assert stamp == stamp_to_ns(msg.header.stamp) == k * 100_000_000  # 10 Hz synthetic stamps


def test_boxes_in_lidar_frame(kitti_bag: Path, shared_data: Path) -> None:
    topics = _read_bag(kitti_bag)
    root = shared_data / KITTI
    n_vehicles = 0
    for (_, det), (_, markers), scan in zip(topics["/kitti/detections"], topics["/kitti/markers"],
                                            sorted((root / "velodyne").glob("*.bin"))):
        expected, sizes = _expected_corners(root / "label_2" / f"{scan.stem}.txt", root / "calib" / f"{scan.stem}.txt")
        for boxes in (detections_to_boxes(det).boxes, markers_to_boxes(markers).boxes):
            assert len(boxes) == len(expected)
            np.testing.assert_allclose([b.size for b in boxes], sizes)
            for box, corners in zip(boxes, expected):
                # exact centre (mean of the corners), heading = the box's front edge direction projected to
                # the lidar xy plane; the camera's 0.5 degree tilt is dropped, so corners agree to ~1 % of the length
                np.testing.assert_allclose(box.center, corners.mean(axis=0), atol=1e-5)
                front = corners[[0, 1, 4, 5]].mean(axis=0) - corners.mean(axis=0)
                assert math.cos(box.yaw - math.atan2(front[1], front[0])) > math.cos(0.02), (scan.stem, box)
                assert _same_box(box_corners(box), corners, tol=0.02 + 0.01 * box.size[0]), (scan.stem, box)
        n_vehicles += sum(b.label in ("car", "van", "truck") for b in detections_to_boxes(det).boxes)
        cubes = [m for m in markers.markers if m.type == MARKER_CUBE]
        assert [m.ns for m in cubes] == [b.label for b in detections_to_boxes(det).boxes]
        assert det.header.frame_id == "velo_link"
    assert n_vehicles > 0
    (tf_message,) = [msg for _, msg in topics["/tf_static"]]
    _assert_camera_transform(tf_message, _calib(root / "calib" / "000000.txt"), stamp_ns=0)


def test_box_transform_matches_points(kitti_bag: Path, shared_data: Path) -> None:
    """The best-sampled car of the sample has its points inside the converted box."""
    frames = list(kitti.iter_object_frames(shared_data / KITTI))
    from gd_completion.geometry import crop_boxes

    best = max((len(idx), f.name) for f in frames for idx, b in zip(crop_boxes(f.xyz, f.boxes, 0.0), f.boxes)
               if b.label == "car")
    assert best[0] > 300


def test_tracking_layout(shared_data: Path, tmp_path: Path) -> None:
    """A tracking-style sequence built from the object frames gives the same boxes (with track ids)."""
    root = tmp_path / "tracking"
    (root / "velodyne" / "0000").mkdir(parents=True)
    (root / "label_02").mkdir()
    (root / "calib").mkdir()
    src = shared_data / KITTI
    (root / "velodyne" / "0000" / "000000.bin").symlink_to(src / "velodyne" / "000001.bin")
    calib = (src / "calib" / "000001.txt").read_text().replace("R0_rect:", "R_rect").replace(
        "Tr_velo_to_cam:", "Tr_velo_cam")
    (root / "calib" / "0000.txt").write_text(calib)
    rows = [f"0 {k + 7} {line}" for k, line in enumerate((src / "label_2" / "000001.txt").read_text().splitlines())]
    (root / "label_02" / "0000.txt").write_text("\n".join(rows) + "\n")
    tracked = next(kitti.iter_tracking_frames(root, "0000"))
    obj = next(f for f in kitti.iter_object_frames(src) if f.name == "000001")
    assert len(tracked.boxes) == len(obj.boxes)
    for a, b in zip(tracked.boxes, obj.boxes):
        assert np.allclose(a.center, b.center) and a.size == b.size and a.yaw == b.yaw and a.label == b.label
    assert [b.instance_id for b in tracked.boxes] == [k + 7 for k in range(len(rows))
                                                      if rows[k].split()[2] != "DontCare"]
    out = tmp_path / "tracking_bag"
    assert main(["convert", "kitti", str(root), str(out), "--storage", "sqlite3"]) == 0
    assert len(_read_bag(out)["/kitti/points"]) == 1


def test_raw_layout_with_tracklets(shared_data: Path, tmp_path: Path) -> None:
    """Raw drive folder: timestamps.txt gives the stamps, tracklet translation is the bottom centre."""
    drive = tmp_path / "2011_09_26_drive_0001_sync"
    data = drive / "velodyne_points" / "data"
    data.mkdir(parents=True)
    for k in range(2):
        (data / f"{k:010d}.bin").symlink_to(shared_data / KITTI / "velodyne" / f"00000{k}.bin")
    (drive / "velodyne_points" / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.067700456\n")
    (drive / "tracklet_labels.xml").write_text(
        "<boost_serialization><tracklets><count>1</count><item><objectType>Car</objectType><h>1.5</h><w>1.6</w>"
        "<l>4.0</l><first_frame>1</first_frame><poses><count>1</count><item><tx>10</tx><ty>2</ty><tz>-1.7</tz>"
        "<rx>0</rx><ry>0</ry><rz>0.3</rz></item></poses></item></tracklets></boost_serialization>")
    frames = list(kitti.iter_raw_frames(drive))
    assert frames[1].stamp_ns - frames[0].stamp_ns == 103_311_011
    assert frames[0].boxes == []
    (box,) = frames[1].boxes
    assert box.center == pytest.approx((10, 2, -0.95)) and box.size == (4.0, 1.6, 1.5) and box.yaw == 0.3


def test_raw_drive_calibration_gives_tf_static(shared_data: Path, tmp_path: Path) -> None:
    """A raw drive's date folder calibration (R_rect_00, velodyne R and T; here the object sample's values in the
    raw files' layout) becomes the /tf_static transform velo_link -> camera_rect."""
    object_calib = shared_data / KITTI / "calib" / "000000.txt"
    rows = dict(line.split(":", 1) for line in object_calib.read_text().splitlines() if ":" in line)
    tr = np.array(rows["Tr_velo_to_cam"].split(), float).reshape(3, 4)
    date = tmp_path / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    data = drive / "velodyne_points" / "data"
    data.mkdir(parents=True)
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\nS_00: 1.392000e+03 5.120000e+02\n"
        f"R_rect_00: {rows['R0_rect'].strip()}\n")
    (date / "calib_velo_to_cam.txt").write_text(
        "calib_time: 15-Mar-2012 11:37:16\n" + "R: " + " ".join(f"{v:.12e}" for v in tr[:, :3].ravel()) + "\n"
        + "T: " + " ".join(f"{v:.12e}" for v in tr[:, 3]) + "\ndelta_f: 0.000000e+00 0.000000e+00\n")
    for k in range(2):
        (data / f"{k:010d}.bin").symlink_to(shared_data / KITTI / "velodyne" / f"00000{k}.bin")
    (drive / "velodyne_points" / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.067700456\n")
    out = tmp_path / "raw_bag"
    assert main(["convert", "kitti", str(drive), str(out), "--quiet"]) == 0
    topics = _read_bag(out)
    assert len(topics["/kitti/points"]) == 2
    (tf_message,) = [msg for _, msg in topics["/tf_static"]]
    first_stamp = topics["/kitti/points"][0][0]
    assert first_stamp == 1317042145964389445
    _assert_camera_transform(tf_message, _calib(object_calib), stamp_ns=first_stamp)


def test_raw_drive_without_calibration_has_no_tf_static(shared_data: Path, tmp_path: Path) -> None:
    drive = tmp_path / "drive"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    (drive / "velodyne_points" / "data" / "0000000000.bin").symlink_to(shared_data / KITTI / "velodyne" / "000000.bin")
    (drive / "velodyne_points" / "timestamps.txt").write_text("2011-09-26 13:02:25.964389445\n")
    assert main(["convert", "kitti", str(drive), str(tmp_path / "bag"), "--quiet"]) == 0
    assert sorted(_read_bag(tmp_path / "bag")) == ["/kitti/detections", "/kitti/markers", "/kitti/points"]


@pytest.mark.parametrize("problem", ["bin_size", "missing_calib", "bad_calib"])
def test_bad_input_exit_code_and_no_output(problem: str, shared_data: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture) -> None:
    root = tmp_path / "training"
    shutil.copytree(shared_data / KITTI / "label_2", root / "label_2")
    shutil.copytree(shared_data / KITTI / "calib", root / "calib")
    (root / "velodyne").mkdir()
    for k in range(2):
        (root / "velodyne" / f"00000{k}.bin").symlink_to(shared_data / KITTI / "velodyne" / f"00000{k}.bin")
    if problem == "bin_size":
        (root / "velodyne" / "000001.bin").unlink()
        raw = (shared_data / KITTI / "velodyne" / "000001.bin").read_bytes()
        (root / "velodyne" / "000001.bin").write_bytes(raw[:-6])
        needle = "000001.bin"
    elif problem == "missing_calib":
        (root / "calib" / "000001.txt").unlink()
        needle = "000001.txt"
    else:
        (root / "calib" / "000000.txt").write_text("P0: 1 2 3\n")
        needle = "000000.txt"
    out = tmp_path / "out_bag"
    assert main(["convert", "kitti", str(root), str(out)]) == 2
    err = capsys.readouterr().err
    assert needle in err and "error" in err
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_empty_scan_and_missing_label_are_warned_and_counted(shared_data: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    """A copy of the sample with 000002.bin emptied and 000004's label file deleted converts, with one warning
    line per cause on stderr and the counts in the summary; those frames keep their stamps."""
    root = tmp_path / "training"
    shutil.copytree(shared_data / KITTI, root)
    (root / "velodyne" / "000002.bin").write_bytes(b"")
    (root / "label_2" / "000004.txt").unlink()
    out = tmp_path / "bag"
    assert main(["convert", "kitti", str(root), str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        f"gd-completion convert: warning: {root}: 1 scan with no points (000002)",
        f"gd-completion convert: warning: {root}: 1 frame without a label file: converted without boxes (000004)"]
    assert captured.out.strip().endswith("; 1 scan with no points; 1 frame without a label file")
    topics = _read_bag(out)
    clouds = [msg for _, msg in topics["/kitti/points"]]
    assert [c.width for c in clouds][2] == 0 and all(c.width > 100_000 for k, c in enumerate(clouds) if k != 2)
    boxes = [detections_to_boxes(msg).boxes for _, msg in topics["/kitti/detections"]]
    expected = [len(kitti.read_labels(root / "label_2" / f"00000{k}.txt")) if k != 4 else 0 for k in range(6)]
    assert [len(b) for b in boxes] == expected and expected[2] > 0  # the empty scan keeps its labels
    assert [stamp for stamp, _ in topics["/kitti/points"]] == [k * kitti.OBJECT_PERIOD_NS for k in range(6)]
