"""PandaSet reader (npz/json or devkit pickle layout): world-frame points and cuboids moved into the lidar frame."""
from __future__ import annotations

import json
import math
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion.datasets import DatasetFrame, normalise_label
from gd_completion.errors import DataFormatError
from gd_completion.geometry import Box3D
from gd_completion.pointcloud2 import xyz_array_to_structured
from gd_completion.rotations import quaternion_matrix

SENSOR_TOPICS = {0: "/pandar64/points", 1: "/pandargt/points"}
BOX_TOPICS = ("/pandar64/detections", "/pandar64/markers")
# poses.json holds one lidar pose per frame (the Pandar64's); PandarGT has no separate extrinsic in this
# layout, so both sensors are expressed in that frame.
SENSOR_FRAME = "pandar64"

LIDAR_COLUMNS = ("x", "y", "z", "i", "t", "d")  # devkit DataFrame columns: world xyz, intensity, time, sensor id


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataFormatError(f"{path}: file missing") from None
    except (OSError, ValueError) as error:
        raise DataFormatError(f"{path}: cannot read JSON: {error}") from error


def _import_pandas(root: Path) -> Any:
    try:
        import pandas
    except ImportError:
        raise DataFormatError(f"{root}: this folder has the PandaSet devkit layout (*.pkl.gz), which needs pandas: "
                              "pip install pandas") from None
    return pandas


def _load_pickle(pandas: Any, path: Path) -> Any:
    """A gzip-compressed pickled DataFrame (devkit layout)."""
    try:
        frame = pandas.read_pickle(path, compression="gzip")
    except FileNotFoundError:
        raise DataFormatError(f"{path}: file missing") from None
    except Exception as error:  # gzip, pickle or pandas errors of a corrupt file
        raise DataFormatError(f"{path}: cannot read pickle: {error}") from error
    if not isinstance(frame, pandas.DataFrame):
        raise DataFormatError(f"{path}: expected a pandas DataFrame, got {type(frame).__name__}")
    return frame


def _plain(pandas: Any, value: Any) -> Any:
    """numpy/pandas scalar -> Python scalar; NaN/NA (a missing attribute) -> None, as in the JSON layout."""
    if isinstance(value, np.generic):
        value = value.item()
    return None if pandas.api.types.is_scalar(value) and pandas.isna(value) else value


def world_box_to_sensor(record: dict, rotation: np.ndarray, translation: np.ndarray, instance_id: int) -> Box3D:
    """PandaSet cuboid (world; dimensions.y = length, heading = yaw + pi/2) -> Box3D in the sensor frame.

    Roll and pitch of the sensor are dropped from the box orientation (Box3D has a yaw only).
    """
    try:
        centre_w = np.array([record["position.x"], record["position.y"], record["position.z"]], dtype=np.float64)
        size = (float(record["dimensions.y"]), float(record["dimensions.x"]), float(record["dimensions.z"]))
        heading_w = float(record["yaw"]) + math.pi / 2.0
    except (KeyError, TypeError, ValueError) as error:
        raise DataFormatError(f"cuboid {record.get('uuid', '?')}: bad record: {error}") from error
    centre = rotation.T @ (centre_w - translation)
    direction = rotation.T @ np.array([math.cos(heading_w), math.sin(heading_w), 0.0])
    yaw = math.atan2(direction[1], direction[0])
    return Box3D(tuple(centre), size, yaw, normalise_label(str(record.get("label", ""))), instance_id)


class PandaSetSequence:
    """One sequence folder, in either layout (detected per folder from the lidar files):

    - npz/json: lidar/NN.npz, lidar/poses.json, lidar/timestamps.json, cuboids/NN.json;
    - official devkit: lidar/NN.pkl.gz (DataFrames x, y, z, i, t, d), lidar/poses.json, lidar/timestamps.json,
      annotations/cuboids/NN.pkl.gz (one row per cuboid, same columns as the JSON records); needs pandas.

    Unpickling runs code from the file: give only trusted dataset folders in the devkit layout.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.lidar_dir = self.root / "lidar"
        if not self.lidar_dir.is_dir():
            raise DataFormatError(f"{self.root}: no lidar/ folder (expected a PandaSet sequence such as 002/)")
        self.poses = _load_json(self.lidar_dir / "poses.json")
        self.timestamps = _load_json(self.lidar_dir / "timestamps.json")
        if not isinstance(self.poses, list) or not isinstance(self.timestamps, list):
            raise DataFormatError(f"{self.lidar_dir}: poses.json and timestamps.json must be lists")
        if len(self.poses) != len(self.timestamps):
            raise DataFormatError(f"{self.lidar_dir}: {len(self.poses)} poses but {len(self.timestamps)} timestamps")
        self.devkit = not any(self.lidar_dir.glob("*.npz")) and any(self.lidar_dir.glob("*.pkl.gz"))
        self._pandas = _import_pandas(self.root) if self.devkit else None
        self.lidar_suffix = ".pkl.gz" if self.devkit else ".npz"
        self.cuboid_dir = self.root / "annotations" / "cuboids" if self.devkit else self.root / "cuboids"
        self.cuboid_suffix = ".pkl.gz" if self.devkit else ".json"

    def frame_count(self) -> int:
        """Frames listed in timestamps.json."""
        return len(self.timestamps)

    def frame_indices(self) -> list[int]:
        """Frames that have a lidar file."""
        return [i for i in range(self.frame_count()) if (self.lidar_dir / f"{i:02d}{self.lidar_suffix}").is_file()]

    def missing_frames(self) -> list[int]:
        """Frames listed in timestamps.json without a lidar file."""
        present = set(self.frame_indices())
        return [i for i in range(self.frame_count()) if i not in present]

    def stamp_ns(self, index: int) -> int:
        """Frame time (ns since the epoch) from lidar/timestamps.json."""
        return int(round(float(self.timestamps[index]) * 1e9))

    def pose(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(R 3x3, t 3): sensor -> world of frame `index`."""
        try:
            p = self.poses[index]
            rotation = quaternion_matrix(*(float(p["heading"][k]) for k in "xyzw"))
            translation = np.array([float(p["position"][k]) for k in "xyz"])
        except (KeyError, IndexError, TypeError, ValueError) as error:
            raise DataFormatError(f"{self.lidar_dir / 'poses.json'}: frame {index}: bad pose: {error}") from error
        return rotation, translation

    def cuboid_indices(self) -> list[int]:
        """Frames that have a cuboid file."""
        return sorted(int(p.name[:-len(self.cuboid_suffix)]) for p in self.cuboid_dir.glob(f"*{self.cuboid_suffix}")
                      if p.name[:-len(self.cuboid_suffix)].isdigit())

    def cuboids(self, index: int) -> list[dict]:
        """Raw cuboid records of frame `index` (world frame), plain dicts of Python scalars in both layouts."""
        return self._load_cuboids(self.cuboid_dir / f"{index:02d}{self.cuboid_suffix}")

    def _load_cuboids(self, path: Path) -> list[dict]:
        if self.devkit:
            records = [{str(k): _plain(self._pandas, v) for k, v in record.items()}
                       for record in _load_pickle(self._pandas, path).to_dict("records")]
        else:
            records = _load_json(path)
        if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
            raise DataFormatError(f"{path}: expected a list of cuboids")
        return records

    @cached_property
    def track_ids(self) -> dict[str, int]:
        """uuid -> stable integer id (order of first appearance over the sequence, from 1)."""
        ids: dict[str, int] = {}
        for path in sorted(self.cuboid_dir.glob(f"*{self.cuboid_suffix}")):
            for record in self._load_cuboids(path):
                ids.setdefault(str(record.get("uuid")), len(ids) + 1)
        return ids

    def load_lidar(self, index: int) -> dict[str, np.ndarray]:
        """Frame `index` as checked arrays: xyz float32 (N,3) world, intensity float32, t float64, sensor uint8."""
        path = self.lidar_dir / f"{index:02d}{self.lidar_suffix}"
        arrays = self._load_pickle_lidar(path) if self.devkit else self._load_npz_lidar(path)
        n = len(arrays["xyz"])
        if arrays["xyz"].ndim != 2 or arrays["xyz"].shape[1] != 3 or any(
                len(arrays[k]) != n for k in ("intensity", "t", "sensor")):
            raise DataFormatError(f"{path}: arrays xyz/intensity/t/sensor have inconsistent shapes")
        return arrays

    def _load_pickle_lidar(self, path: Path) -> dict[str, np.ndarray]:
        table = _load_pickle(self._pandas, path)
        missing = [c for c in LIDAR_COLUMNS if c not in table.columns]
        if missing:
            raise DataFormatError(f"{path}: missing columns {missing} (expected {', '.join(LIDAR_COLUMNS)})")
        try:
            return {"xyz": table[["x", "y", "z"]].to_numpy(np.float32), "intensity": table["i"].to_numpy(np.float32),
                    "t": table["t"].to_numpy(np.float64), "sensor": table["d"].to_numpy(np.uint8)}
        except (TypeError, ValueError) as error:
            raise DataFormatError(f"{path}: bad column values: {error}") from error

    @staticmethod
    def _load_npz_lidar(path: Path) -> dict[str, np.ndarray]:
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in ("xyz", "intensity", "t", "sensor")}
        except FileNotFoundError:
            raise DataFormatError(f"{path}: lidar file missing") from None
        except KeyError as error:
            raise DataFormatError(f"{path}: missing array {error}") from error
        except Exception as error:  # zip/pickle errors of a corrupt npz
            raise DataFormatError(f"{path}: cannot read npz: {error}") from error
        return arrays

    def boxes(self, index: int, sensor: int = 0) -> tuple[list[Box3D], list[str], list[str]]:
        """Cuboids of frame `index` seen by `sensor` (sensor_id -1 or `sensor`) in the sensor frame.

        Returns (boxes, original labels, uuids).
        """
        rotation, translation = self.pose(index)
        boxes, labels, uuids = [], [], []
        for record in self.cuboids(index):
            if int(record.get("cuboids.sensor_id", -1)) not in (-1, sensor):
                continue
            uuid = str(record.get("uuid"))
            boxes.append(world_box_to_sensor(record, rotation, translation, self.track_ids.get(uuid, 0)))
            labels.append(str(record.get("label", "")))
            uuids.append(uuid)
        return boxes, labels, uuids

    def frame(self, index: int, sensors: Sequence[int] = (0,)) -> list[DatasetFrame]:
        """One DatasetFrame per sensor for frame `index`, points in the lidar frame (float32)."""
        arrays = self.load_lidar(index)
        rotation, translation = self.pose(index)
        stamp = self.stamp_ns(index)
        boxes, labels, uuids = self.boxes(index, 0)
        out = []
        for sensor in sensors:
            mask = arrays["sensor"] == sensor
            xyz = ((arrays["xyz"][mask].astype(np.float64) - translation) @ rotation).astype(np.float32)
            out.append(DatasetFrame(name=f"{index:02d}", stamp_ns=stamp, frame_id=SENSOR_FRAME, xyz=xyz,
                                    intensity=arrays["intensity"][mask].astype(np.float32), boxes=boxes,
                                    source_labels=labels, track_ids=uuids,
                                    extra={"timestamp": arrays["t"][mask].astype(np.float64)}))
        return out


def hesai_cloud(frame: DatasetFrame) -> np.ndarray:
    """Structured cloud with the Hesai driver's (HesaiLidar_General_ROS PointXYZIT) fields x, y, z, intensity
    (float32) and timestamp (s, float64; zero when the frame has none); no `ring`: neither layout keeps it."""
    timestamp = frame.extra.get("timestamp", np.zeros(len(frame.xyz)))
    return xyz_array_to_structured(frame.xyz, intensity=np.asarray(frame.intensity, np.float32),
                                   timestamp=np.asarray(timestamp, np.float64))
