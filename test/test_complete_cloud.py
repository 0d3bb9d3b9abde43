"""`gd-completion complete-cloud` and `gd_completion.complete_cloud` on the shared KITTI sample frames."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gd_completion.cli import main
from gd_completion.cloud_files import read_points, read_xyz, write_points_file
from gd_completion.datasets.kitti import read_labels
from gd_completion.geometry import crop_boxes
from gd_completion.single_cloud import kitti_boxes

REPO = Path(__file__).resolve().parents[1]
FRAME = "000004"  # two cars, both completed with the shipped weights


@pytest.fixture(scope="module")
def kitti(shared_data: Path) -> dict[str, Path]:
    root = shared_data / "kitti-object-sample" / "training"
    return {"scan": root / "velodyne" / f"{FRAME}.bin", "label": root / "label_2" / f"{FRAME}.txt",
            "calib": root / "calib" / f"{FRAME}.txt", "root": root}


def _kitti_args(kitti: dict[str, Path]) -> list[str]:
    return ["--kitti-label", str(kitti["label"]), "--kitti-calib", str(kitti["calib"])]


def _write_ascii_pcd(path: Path, points: np.ndarray) -> None:
    header = ("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
              f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA ascii\n")
    with open(path, "w") as out:
        out.write(header)
        np.savetxt(out, points, fmt="%.9g")


def _write_ascii_ply(path: Path, points: np.ndarray) -> None:
    header = (f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
              "property float z\nproperty float intensity\nelement face 1\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    with open(path, "w") as out:
        out.write(header)
        np.savetxt(out, points, fmt="%.9g")
        out.write("3 0 1 2\n")


def _inputs(tmp: Path, scan: Path) -> dict[str, Path]:
    """The KITTI frame's points (x, y, z, reflectance) in every input format."""
    points = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
    table = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    for k, name in enumerate(table.dtype.names):
        table[name] = points[:, k]
    files = {"bin": scan, "npy": tmp / "plain.npy", "npz": tmp / "cloud.npz", "ply": tmp / "binary.ply",
             "pcd": tmp / "binary.pcd", "ascii.pcd": tmp / "ascii.pcd", "ascii.ply": tmp / "ascii.ply",
             "structured.npy": tmp / "structured.npy"}
    np.save(files["npy"], points)
    np.savez(files["npz"], other=np.zeros((2, 3)), points=points)
    write_points_file(files["ply"], table)
    write_points_file(files["pcd"], table)
    write_points_file(files["structured.npy"], table)
    _write_ascii_pcd(files["ascii.pcd"], points)
    _write_ascii_ply(files["ascii.ply"], points)
    return files


@pytest.fixture(scope="module")
def reference(kitti: dict[str, Path]) -> np.ndarray:
    """The Python API's completion of the frame (the shipped weights)."""
    from gd_completion import complete_cloud
    return complete_cloud(read_xyz(kitti["scan"]), kitti_boxes(kitti["label"], kitti["calib"]), threads=1)


def test_every_format_reads_the_same_points(tmp_path, kitti):
    expected = np.fromfile(kitti["scan"], dtype="<f4").reshape(-1, 4)
    for name, path in _inputs(tmp_path, kitti["scan"]).items():
        np.testing.assert_array_equal(read_xyz(path), expected[:, :3], err_msg=name)
        table = read_points(path)
        extra = "c3" if name in ("npy", "npz") else "intensity"
        np.testing.assert_array_equal(table[extra], expected[:, 3], err_msg=name)


@pytest.mark.parametrize("out_suffix", [".ply", ".pcd", ".npy"])
def test_command_round_trip_every_format(tmp_path, kitti, reference, out_suffix, capsys):
    from gd_completion.pipeline import COMPLETION_DTYPE
    for name, path in _inputs(tmp_path, kitti["scan"]).items():
        out = tmp_path / f"out_{name.replace('.', '_')}{out_suffix}"
        assert main(["complete-cloud", str(path), str(out), *_kitti_args(kitti), "--threads", "1"]) == 0, name
        table = read_points(out)
        assert table.dtype == COMPLETION_DTYPE, name
        np.testing.assert_array_equal(table, reference, err_msg=name)
    assert "wrote" in capsys.readouterr().out


def test_kitti_frame_completes_inside_its_boxes(kitti, reference):
    boxes = kitti_boxes(kitti["label"], kitti["calib"])
    labels = read_labels(kitti["label"])
    vehicle_rows = [k + 1 for k, lab in enumerate(labels) if lab.type in ("Car", "Van", "Truck")]
    assert [b.instance_id for b in boxes] == vehicle_rows == [1, 2]
    assert np.unique(reference["instance_id"]).tolist() == vehicle_rows
    xyz = np.stack([reference["x"], reference["y"], reference["z"]], axis=1)
    for box in boxes:
        mine = reference["instance_id"] == box.instance_id
        generated = mine & (reference["generated"] == 1)
        measured = int((mine & (reference["generated"] == 0)).sum())
        assert measured >= 20
        assert 2048 - min(measured, 512) <= generated.sum() < 2048   # the merge keeps some measured points
        assert set(reference["label"][mine].tolist()) == {1}  # both are cars
        inside = np.zeros(len(xyz), bool)
        inside[crop_boxes(xyz, [box], 0.5)[0]] = True
        assert inside[generated].mean() >= 0.9
        assert inside[mine].mean() >= 0.9


def test_no_input_points_and_skips(tmp_path, kitti, capsys):
    root = kitti["root"]
    out = tmp_path / "frame1.npy"
    args = ["complete-cloud", str(root / "velodyne" / "000001.bin"), str(out), "--no-input-points", "--threads", "1",
            "--kitti-label", str(root / "label_2" / "000001.txt"), "--kitti-calib", str(root / "calib" / "000001.txt")]
    assert main(args) == 0
    table = np.load(out)
    assert np.unique(table["instance_id"]).tolist() == [1]  # the truck; the far car (row 2) has 9 points
    assert len(table) == 2048 and 0 < (table["generated"] == 0).sum() < 512   # the merge's measured points
    assert table["label"].tolist() == [3] * 2048
    err = capsys.readouterr().err
    assert "skipped box 2 (car at 58.8, 16.6, -0.8): too few points: 9 in the box, 20 needed" in err
    assert main(args) == 2  # exists already
    assert "output exists already (use --overwrite" in capsys.readouterr().err


def test_box_option_and_json_match_the_labels(tmp_path, kitti, reference):
    boxes = kitti_boxes(kitti["label"], kitti["calib"])
    texts = [",".join(f"{v!r}" for v in (*b.center, *b.size, b.yaw)) + f",{b.label}" for b in boxes]
    out = tmp_path / "boxes.npy"
    argv = ["complete-cloud", str(kitti["scan"]), str(out), "--threads", "1"]
    assert main([*argv, *(a for t in texts for a in ("--box", t))]) == 0
    np.testing.assert_array_equal(np.load(out), reference)
    spec = tmp_path / "boxes.json"
    spec.write_text(json.dumps([{"center": b.center, "size": b.size, "yaw": b.yaw, "label": b.label,
                                 "id": b.instance_id + 10} for b in boxes]))
    assert main([*argv, "--boxes", str(spec), "--overwrite"]) == 0
    shifted = reference.copy()
    shifted["instance_id"] += 10
    np.testing.assert_array_equal(np.load(out), shifted)


def test_api_accepts_tuples_and_caches_the_model(kitti, reference):
    from gd_completion import complete_cloud
    from gd_completion.single_cloud import cloud_settings, completer
    boxes = kitti_boxes(kitti["label"], kitti["calib"])
    tuples = [(*b.center, *b.size, b.yaw, b.label) for b in boxes]
    np.testing.assert_array_equal(complete_cloud(read_xyz(kitti["scan"]), tuples, threads=1), reference)
    assert completer(cloud_settings(threads=1)) is completer(cloud_settings(threads=1))
    # offline: what it writes never depends on the machine's load (the node's 2 s frame budget skipped vehicles
    # of this frame on a loaded machine)
    assert completer(cloud_settings(threads=1)).limits.time_budget_s == math.inf


@pytest.mark.parametrize(("argv", "message"), [
    (["cloud.txt", "out.ply", "--box", "0,0,0,4,2,1.5,0"], "cloud.txt: unknown point file extension '.txt'"),
    (["SCAN", "out.xyz", "--box", "0,0,0,4,2,1.5,0"], "out.xyz: unknown output file extension '.xyz'"),
    (["SCAN", "out.ply", "--box", "1,2,3,4"], "--box '1,2,3,4': expected cx,cy,cz,length,width,height,yaw"),
    (["SCAN", "out.ply", "--box", "1,2,3,4,2,x,0"], "--box '1,2,3,4,2,x,0': expected"),
    (["SCAN", "out.ply", "--box", "0,0,0,-4,2,1.5,0"], "unusable box: non-positive size"),
    (["SCAN", "out.ply", "--box", "500,500,0,4,2,1.5,0"], "no point of the cloud (115976 points) lies in any"),
    (["SCAN", "out.ply"], "no boxes: give --box, --boxes or --kitti-label"),
    (["missing.pcd", "out.ply", "--box", "0,0,0,4,2,1.5,0"], "missing.pcd: no such point file"),
    (["BAD", "out.ply", "--box", "0,0,0,4,2,1.5,0"], "not a PLY file"),
], ids=["extension", "output-extension", "box-fields", "box-number", "box-size", "box-without-points", "no-boxes",
        "missing", "unreadable"])
def test_bad_input_exits_2_with_one_line(tmp_path, kitti, argv, message, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"\x00garbage")
    subst = {"SCAN": str(kitti["scan"]), "BAD": str(bad)}
    argv = [subst.get(a, str(tmp_path / a) if a.endswith((".ply", ".pcd", ".txt", ".xyz")) else a) for a in argv]
    assert main(["complete-cloud", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gd-completion complete-cloud: error: "), err
    assert message in err[0]
    assert not (tmp_path / "out.ply").exists()


@pytest.mark.integration
def test_import_is_cheap_and_api_matches_the_command(tmp_path, kitti):
    out = tmp_path / "cli.npy"
    code = ("from gd_completion.cli import main\n"
            f"assert main(['complete-cloud', {str(kitti['scan'])!r}, {str(out)!r}, '--kitti-label', "
            f"{str(kitti['label'])!r}, '--kitti-calib', {str(kitti['calib'])!r}]) == 0\n")
    light = subprocess.run([sys.executable, "-c", "import sys, gd_completion\n"
                            "from gd_completion import complete_cloud\n"
                            "print(sorted(m for m in ('torch', 'numpy') if m in sys.modules))"],
                           cwd=REPO, capture_output=True, text=True, timeout=120, check=True)
    assert light.stdout.strip() == "['numpy']"  # numpy for the readers; torch only when a cloud is completed
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=300)
    from gd_completion import complete_cloud
    api = complete_cloud(read_xyz(kitti["scan"]), kitti_boxes(kitti["label"], kitti["calib"]))
    np.testing.assert_array_equal(np.load(out), api)
