"""KITTI readers: velodyne scans, calibration, camera-frame labels, tracklets; boxes in the lidar frame."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.datasets import DatasetFrame, normalise_label
from gd_completion.errors import DataFormatError
from gd_completion.geometry import Box3D

LIDAR_FRAME = "velo_link"
CAMERA_FRAME = "camera_rect"  # rectified reference camera (cam 0)
OBJECT_PERIOD_NS = 100_000_000  # the object benchmark has no stamps: 10 Hz synthetic
IGNORED_TYPES = frozenset({"DontCare"})
RAW_CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt")  # in a raw drive's date folder


@dataclass(frozen=True)
class KittiCalib:
    """R0_rect (3x3) and Tr_velo_to_cam (3x4) of one frame or drive."""

    r0_rect: np.ndarray
    tr_velo_to_cam: np.ndarray

    @property
    def velo_to_rect(self) -> np.ndarray:
        """4x4: lidar -> rectified camera (R0_rect . Tr_velo_to_cam)."""
        r0 = np.eye(4)
        r0[:3, :3] = self.r0_rect
        tr = np.eye(4)
        tr[:3, :4] = self.tr_velo_to_cam
        return r0 @ tr

    @property
    def rect_to_velo(self) -> np.ndarray:
        """4x4: rectified camera -> lidar."""
        return np.linalg.inv(self.velo_to_rect)


@dataclass(frozen=True)
class KittiLabel:
    """One KITTI label row (camera frame): type, dimensions (h, w, l), location (bottom centre), rotation_y."""

    type: str
    truncated: float
    occluded: int
    dimensions: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation_y: float
    track_id: int = -1


def read_velodyne(path: str | Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, reflectance from a KITTI .bin; DataFormatError on a size not a multiple of 16."""
    path = Path(path)
    try:
        raw = np.fromfile(path, dtype="<f4")
    except OSError as error:
        raise DataFormatError(f"{path}: cannot read velodyne scan: {error}") from error
    if raw.size * 4 != path.stat().st_size or raw.size % 4:
        raise DataFormatError(f"{path}: size {path.stat().st_size} bytes is not a multiple of 16 "
                              f"(4 float32 per point); truncated or not a KITTI velodyne scan")
    return raw.reshape(-1, 4)


def _parse_matrix_lines(path: Path) -> dict[str, np.ndarray]:
    values: dict[str, np.ndarray] = {}
    try:
        lines = path.read_text().splitlines()
    except OSError as error:
        raise DataFormatError(f"{path}: cannot read calibration: {error}") from error
    for line in lines:
        line = line.strip()
        if not line:
            continue
        key, _, rest = line.partition(":") if ":" in line else line.partition(" ")
        try:
            values[key.strip()] = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            continue  # e.g. calib_time lines of raw calibration
    return values


def read_calib(path: str | Path) -> KittiCalib:
    """Calibration from an object (`R0_rect`, `Tr_velo_to_cam`) or tracking (`R_rect`, `Tr_velo_cam`) file."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: calibration file missing")
    values = _parse_matrix_lines(path)
    r0 = values.get("R0_rect", values.get("R_rect"))
    tr = values.get("Tr_velo_to_cam", values.get("Tr_velo_cam"))
    if r0 is None or tr is None:
        raise DataFormatError(f"{path}: calibration lacks R0_rect or Tr_velo_to_cam")
    if r0.size != 9 or tr.size != 12:
        raise DataFormatError(f"{path}: R0_rect needs 9 values (got {r0.size}), Tr_velo_to_cam 12 (got {tr.size})")
    return KittiCalib(r0.reshape(3, 3), tr.reshape(3, 4))


def read_raw_calib(calib_dir: str | Path) -> KittiCalib:
    """Calibration of a raw drive date folder: `calib_cam_to_cam.txt` (R_rect_00) and `calib_velo_to_cam.txt`."""
    calib_dir = Path(calib_dir)
    c2c, v2c = (calib_dir / name for name in RAW_CALIB_FILES)
    for path in (c2c, v2c):
        if not path.is_file():
            raise DataFormatError(f"{path}: calibration file missing")
    cam = _parse_matrix_lines(c2c)
    velo = _parse_matrix_lines(v2c)
    if "R_rect_00" not in cam or "R" not in velo or "T" not in velo:
        raise DataFormatError(f"{calib_dir}: raw calibration lacks R_rect_00 or velodyne R/T")
    tr = np.hstack([velo["R"].reshape(3, 3), velo["T"].reshape(3, 1)])
    return KittiCalib(cam["R_rect_00"].reshape(3, 3), tr)


def _label_from_fields(fields: Sequence[str], path: Path, line_no: int, track_id: int = -1) -> KittiLabel:
    if len(fields) < 15:
        raise DataFormatError(f"{path}:{line_no}: expected at least 15 columns, got {len(fields)}")
    try:
        h, w, l, x, y, z, ry = (float(v) for v in fields[8:15])
        return KittiLabel(fields[0], float(fields[1]), int(float(fields[2])), (h, w, l), (x, y, z), ry, track_id)
    except ValueError as error:
        raise DataFormatError(f"{path}:{line_no}: bad number: {error}") from error


def _numbered_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """(1-based line number, text) of every line of a text file; DataFormatError naming it when missing."""
    if not path.is_file():
        raise DataFormatError(f"{path}: {what} missing")
    return list(enumerate(path.read_text().splitlines(), 1))


def read_labels(path: str | Path) -> list[KittiLabel]:
    """Object-benchmark label_2 rows (DontCare dropped)."""
    path = Path(path)
    labels = []
    for n, line in _numbered_lines(path, "label file"):
        fields = line.split()
        if fields and fields[0] not in IGNORED_TYPES:
            labels.append(_label_from_fields(fields, path, n))
    return labels


def read_tracking_labels(path: str | Path) -> dict[int, list[KittiLabel]]:
    """Tracking label_02 file -> {frame: labels} (columns: frame, track id, then the object columns)."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"{path}: label file missing")
    frames: dict[int, list[KittiLabel]] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 17:
            raise DataFormatError(f"{path}:{n}: expected at least 17 columns, got {len(fields)}")
        if fields[2] in IGNORED_TYPES:
            continue
        try:
            frame, track = int(fields[0]), int(fields[1])
        except ValueError as error:
            raise DataFormatError(f"{path}:{n}: bad frame or track id: {error}") from error
        frames.setdefault(frame, []).append(_label_from_fields(fields[2:], path, n, track))
    return frames


def label_to_box(label: KittiLabel, calib: KittiCalib, instance_id: int) -> Box3D:
    """Camera-frame label -> lidar-frame Box3D (centre = location - (0, h/2, 0); yaw = -rotation_y - pi/2)."""
    h, w, l = label.dimensions
    centre_cam = np.array([label.location[0], label.location[1] - h / 2.0, label.location[2], 1.0])
    centre = calib.rect_to_velo @ centre_cam
    yaw = -label.rotation_y - math.pi / 2.0
    yaw = math.atan2(math.sin(yaw), math.cos(yaw))
    return Box3D(tuple(centre[:3]), (l, w, h), yaw, normalise_label(label.type), instance_id)


def labels_to_boxes(labels: Sequence[KittiLabel], calib: KittiCalib) -> tuple[list[Box3D], list[str]]:
    """Lidar-frame boxes (instance id = track id, else 1-based row index) and the original KITTI types."""
    boxes = [label_to_box(lab, calib, lab.track_id if lab.track_id >= 0 else k + 1) for k, lab in enumerate(labels)]
    return boxes, [lab.type for lab in labels]


def iter_object_frames(root: str | Path, *, limit: int | None = None, start_ns: int = 0) -> Iterator[DatasetFrame]:
    """Frames of the object benchmark (`root` = the split folder holding velodyne/, label_2/, calib/)."""
    root = Path(root)
    velo_dir = root / "velodyne"
    if not velo_dir.is_dir():
        raise DataFormatError(f"{root}: no velodyne/ folder (expected a KITTI object split such as training/)")
    scans = sorted(velo_dir.glob("*.bin"))
    if not scans:
        raise DataFormatError(f"{velo_dir}: no .bin scans")
    for k, scan in enumerate(scans[:limit]):
        calib = read_calib(root / "calib" / f"{scan.stem}.txt")
        label_path = root / "label_2" / f"{scan.stem}.txt"
        labelled = label_path.exists()
        boxes, names = labels_to_boxes(read_labels(label_path) if labelled else [], calib)
        cloud = read_velodyne(scan)
        yield DatasetFrame(name=scan.stem, stamp_ns=start_ns + k * OBJECT_PERIOD_NS, frame_id=LIDAR_FRAME,
                           xyz=cloud[:, :3], intensity=cloud[:, 3], boxes=boxes, source_labels=names,
                           track_ids=[str(b.instance_id) for b in boxes], calib=calib, labelled=labelled)


def read_timestamps(path: str | Path) -> np.ndarray:
    """Raw-drive timestamps.txt ('YYYY-MM-DD hh:mm:ss.fffffffff') -> int64 ns since the epoch."""
    path = Path(path)
    out = []
    for n, line in _numbered_lines(path, "timestamps file"):
        line = line.strip()
        if not line:
            continue
        try:
            day, clock = line.split()
            whole, _, frac = clock.partition(".")
            base = np.datetime64(f"{day}T{whole}", "s").astype(np.int64)
            out.append(int(base) * 1_000_000_000 + int((frac + "000000000")[:9]))
        except ValueError as error:
            raise DataFormatError(f"{path}:{n}: bad timestamp {line!r}: {error}") from error
    return np.array(out, dtype=np.int64)


def read_tracklets(path: str | Path) -> dict[int, list[Box3D]]:
    """tracklet_labels.xml -> {frame: lidar-frame boxes}; the tracklet translation is the box bottom centre."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as error:
        raise DataFormatError(f"{path}: cannot parse tracklets: {error}") from error
    frames: dict[int, list[Box3D]] = {}
    tracklets = root.find("tracklets")
    if tracklets is None:
        raise DataFormatError(f"{path}: no <tracklets> element")
    for track_id, item in enumerate(tracklets.findall("item")):
        try:
            kind = item.findtext("objectType", "")
            h, w, l = (float(_text(item, tag)) for tag in ("h", "w", "l"))
            first = int(_text(item, "first_frame"))
            poses = item.find("poses")
            for k, pose in enumerate(poses.findall("item") if poses is not None else []):
                tx, ty, tz, rz = (float(_text(pose, tag)) for tag in ("tx", "ty", "tz", "rz"))
                frames.setdefault(first + k, []).append(
                    Box3D((tx, ty, tz + h / 2.0), (l, w, h), rz, normalise_label(kind), track_id))
        except (TypeError, ValueError) as error:
            raise DataFormatError(f"{path}: tracklet {track_id}: bad value: {error}") from error
    return frames


def _text(element: ET.Element, tag: str) -> str:
    """The text of `element`'s child `tag`; TypeError naming it when it is missing."""
    text = element.findtext(tag)
    if text is None:
        raise TypeError(f"<{tag}> missing")
    return text


def iter_raw_frames(drive: str | Path, *, limit: int | None = None) -> Iterator[DatasetFrame]:
    """Frames of a raw drive folder (velodyne_points/data/*.bin + timestamps.txt, optional tracklet_labels.xml);
    the calibration comes from the date folder above it (`calib_cam_to_cam.txt`, `calib_velo_to_cam.txt`) when
    it has one. Tracklet boxes are in the lidar frame already."""
    drive = Path(drive)
    data = drive / "velodyne_points" / "data"
    if not data.is_dir():
        raise DataFormatError(f"{drive}: no velodyne_points/data folder (expected a KITTI raw drive)")
    scans = sorted(data.glob("*.bin"))
    stamps = read_timestamps(drive / "velodyne_points" / "timestamps.txt")
    if len(stamps) < len(scans):
        raise DataFormatError(f"{drive / 'velodyne_points' / 'timestamps.txt'}: {len(stamps)} stamps for "
                              f"{len(scans)} scans")
    tracklet_path = drive / "tracklet_labels.xml"
    tracks = read_tracklets(tracklet_path) if tracklet_path.exists() else {}
    date_dir = drive.resolve().parent
    calib = read_raw_calib(date_dir) if any((date_dir / name).exists() for name in RAW_CALIB_FILES) else None
    for scan in scans[:limit]:
        index = int(scan.stem)
        cloud = read_velodyne(scan)
        boxes = tracks.get(index, [])
        yield DatasetFrame(name=scan.stem, stamp_ns=int(stamps[index]), frame_id=LIDAR_FRAME, xyz=cloud[:, :3],
                           intensity=cloud[:, 3], boxes=boxes, source_labels=[b.label for b in boxes],
                           track_ids=[str(b.instance_id) for b in boxes], calib=calib,
                           labelled=tracklet_path.exists())


def iter_tracking_frames(root: str | Path, sequence: str, *, limit: int | None = None) -> Iterator[DatasetFrame]:
    """Frames of a tracking sequence: velodyne/SSSS/*.bin, label_02/SSSS.txt, calib/SSSS.txt (10 Hz stamps)."""
    root = Path(root)
    velo_dir = root / "velodyne" / sequence
    if not velo_dir.is_dir():
        raise DataFormatError(f"{velo_dir}: no such tracking sequence folder")
    calib = read_calib(root / "calib" / f"{sequence}.txt")
    label_path = root / "label_02" / f"{sequence}.txt"
    per_frame = read_tracking_labels(label_path) if label_path.exists() else {}
    for scan in sorted(velo_dir.glob("*.bin"))[:limit]:
        index = int(scan.stem)
        boxes, names = labels_to_boxes(per_frame.get(index, []), calib)
        cloud = read_velodyne(scan)
        yield DatasetFrame(name=scan.stem, stamp_ns=index * OBJECT_PERIOD_NS, frame_id=LIDAR_FRAME,
                           xyz=cloud[:, :3], intensity=cloud[:, 3], boxes=boxes, source_labels=names,
                           track_ids=[str(b.instance_id) for b in boxes], calib=calib,
                           labelled=label_path.exists())


def detect_layout(path: str | Path) -> str:
    """'object' (split folder), 'raw' (drive folder) or 'tracking' (split folder with label_02)."""
    path = Path(path)
    if (path / "velodyne_points" / "data").is_dir():
        return "raw"
    if (path / "label_02").is_dir() or ((path / "velodyne").is_dir() and any(
            p.is_dir() for p in (path / "velodyne").iterdir())):
        return "tracking"
    if (path / "velodyne").is_dir():
        return "object"
    if (path / "training" / "velodyne").is_dir():
        return "object"
    raise DataFormatError(f"{path}: not a KITTI object split, tracking split or raw drive folder")
