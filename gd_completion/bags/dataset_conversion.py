"""KITTI and PandaSet recordings written to rosbag2: PointCloud2 per lidar, boxes (Detection3DArray and MarkerArray),
/tf_static."""
from __future__ import annotations

import itertools
import sys
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from gd_completion.bags.messages import detection3d_array_msg, marker_array_msg, pointcloud2_msg, tf_static_msg
from gd_completion.bags.typestore import DETECTION3D_ARRAY, MARKER_ARRAY, POINTCLOUD2, TF_MESSAGE, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer
from gd_completion.datasets import DatasetFrame
from gd_completion.errors import DataFormatError
from gd_completion.pointcloud2 import write_points, xyz_array_to_structured
from gd_completion.progress import progress_bar

KITTI_TOPICS = ("/kitti/points", "/kitti/detections", "/kitti/markers")
TF_STATIC = "/tf_static"


class ConversionCounts(dict[str, int]):
    """Messages written per topic, and the frames whose source was lacking: `empty_scans` (a scan with no points)
    and `unlabelled_frames` (no label file: converted without boxes), by frame name."""

    def __init__(self) -> None:
        super().__init__()
        self.empty_scans: list[str] = []
        self.unlabelled_frames: list[str] = []

    def _lacking(self) -> list[tuple[str, str, list[str]]]:
        """(count and kind, consequence, frame names) per kind of lacking frame that occurred."""
        kinds = ((self.empty_scans, "scan", "with no points", ""),
                 (self.unlabelled_frames, "frame", "without a label file", ": converted without boxes"))
        return [(f"{len(names)} {noun}{'s' if len(names) > 1 else ''} {what}", consequence, names)
                for names, noun, what, consequence in kinds if names]

    def problems(self) -> list[str]:
        """One warning line per kind of lacking frame: how many, the consequence, the first frames' names."""
        return [f"{count}{consequence} ({', '.join(names[:5])}{', ...' if len(names) > 5 else ''})"
                for count, consequence, names in self._lacking()]

    def text(self) -> str:
        """Messages per topic, then how many frames lacked points or labels."""
        lacking = "; ".join(count for count, _, _ in self._lacking())
        return ", ".join(f"{t} {n}" for t, n in self.items()) + (f"; {lacking}" if lacking else "")


def kitti_cloud(frame: DatasetFrame) -> np.ndarray:
    """x y z intensity float32 structured array (the KITTI velodyne layout)."""
    return xyz_array_to_structured(frame.xyz, intensity=np.asarray(frame.intensity, np.float32))


def write_bag(out: Path, storage: str, clouds: Sequence[tuple[str, str]], boxes_topics: tuple[str, str] | None,
              frames: Iterable[tuple[str, DatasetFrame, np.ndarray]],
              tf_static: Sequence[tuple[str, str, np.ndarray]] = (), overwrite: bool = False,
              quiet: bool = False, total: int | None = None) -> ConversionCounts:
    """Write frames to a new bag atomically.

    `clouds`: (topic, frame key) pairs; `frames` yields (cloud topic, frame, structured cloud); boxes of the
    first cloud topic go to `boxes_topics` (Detection3DArray topic, MarkerArray topic). `total`: frames
    expected, for the progress bar. Returns message counts and the frames without points or labels.
    """
    counts = ConversionCounts()
    with (atomic_bag_writer(out, storage=storage, overwrite=overwrite) as writer,
          progress_bar(out.name, "frames", total=total, quiet=quiet) as bar):
        conns = {topic: add_connection(writer, topic, POINTCLOUD2) for topic, _ in clouds}
        det_conn = mark_conn = None
        if boxes_topics is not None:
            det_conn = add_connection(writer, boxes_topics[0], DETECTION3D_ARRAY)
            mark_conn = add_connection(writer, boxes_topics[1], MARKER_ARRAY)
        box_topic_source = clouds[0][0]
        tf_written = False
        for topic, frame, cloud in frames:
            ns = frame.stamp_ns
            if tf_static and not tf_written:
                tf_conn = add_connection(writer, TF_STATIC, TF_MESSAGE, latched=True)
                writer.write(tf_conn, ns, serialize(tf_static_msg(tf_static, ns), TF_MESSAGE))
                counts[TF_STATIC] = 1
                tf_written = True
            msg = pointcloud2_msg(write_points(cloud), frame.frame_id, ns)
            writer.write(conns[topic], ns, serialize(msg, POINTCLOUD2))
            counts[topic] = counts.get(topic, 0) + 1
            if not cloud.size:
                counts.empty_scans.append(frame.name)
            if topic == box_topic_source:
                bar.update(1)
                if not frame.labelled:
                    counts.unlabelled_frames.append(frame.name)
                if boxes_topics is not None and det_conn is not None and mark_conn is not None:
                    det = detection3d_array_msg(frame.boxes, frame.frame_id, ns)
                    writer.write(det_conn, ns, serialize(det, DETECTION3D_ARRAY))
                    mark = marker_array_msg(frame.boxes, frame.frame_id, ns)
                    writer.write(mark_conn, ns, serialize(mark, MARKER_ARRAY))
                    for t in boxes_topics:
                        counts[t] = counts.get(t, 0) + 1
    return counts


def convert_kitti(src: Path, out: Path, *, storage: str = "mcap", limit: int | None = None,
                  sequence: str | None = None, overwrite: bool = False, quiet: bool = False) -> ConversionCounts:
    """KITTI object split, tracking sequence or raw drive -> bag with /kitti/points, detections, markers."""
    from gd_completion.datasets import kitti

    layout = kitti.detect_layout(src)
    if layout == "object":
        root = src / "training" if (src / "training" / "velodyne").is_dir() else src
        frames = kitti.iter_object_frames(root, limit=limit)
    elif layout == "tracking":
        if sequence is None:
            sequences = sorted(p.name for p in (src / "velodyne").iterdir() if p.is_dir())
            sequence = sequences[0] if sequences else "0000"
        frames = kitti.iter_tracking_frames(src, sequence, limit=limit)
    else:
        frames = kitti.iter_raw_frames(src, limit=limit)
    iterator = iter(frames)
    first = next(iterator, None)  # bad input fails here, before a bag is opened
    if first is None:
        raise DataFormatError(f"{src}: no frames to convert")
    tf = []
    if first.calib is not None:
        tf.append((kitti.LIDAR_FRAME, kitti.CAMERA_FRAME, first.calib.rect_to_velo))
    topic, det_topic, mark_topic = KITTI_TOPICS
    return write_bag(out, storage, [(topic, kitti.LIDAR_FRAME)], (det_topic, mark_topic),
                     ((topic, f, kitti_cloud(f)) for f in itertools.chain([first], iterator)), tf_static=tf,
                     overwrite=overwrite, quiet=quiet)


def convert_pandaset(src: Path, out: Path, *, storage: str = "mcap", limit: int | None = None,
                     sensors: Sequence[int] = (0, 1), start: int = 0, overwrite: bool = False,
                     quiet: bool = False) -> ConversionCounts:
    """PandaSet sequence folder (npz/json or devkit pickle layout) -> bag with one cloud topic per sensor and boxes.

    Frames from `start` on (at most `limit`); frames without a lidar file are skipped with a note on stderr
    (none with `quiet`).
    """
    from gd_completion.datasets import pandaset

    seq = pandaset.PandaSetSequence(src)
    indices = [i for i in seq.frame_indices() if i >= start][:limit]
    if not indices:
        raise DataFormatError(f"{src}: no lidar frames from frame {start} on")
    for i in seq.missing_frames():
        if indices[0] <= i <= indices[-1] and not quiet:
            print(f"{src}: frame {i:02d}: lidar file missing, skipped", file=sys.stderr)
    for index in (sensor for sensor in sensors if sensor not in pandaset.SENSOR_TOPICS):
        raise DataFormatError(f"{src}: unknown sensor id {index} (0 = Pandar64, 1 = PandarGT)")

    def frames() -> Iterator[tuple[str, DatasetFrame, np.ndarray]]:
        for index in indices:
            per_sensor = seq.frame(index, sensors)
            for sensor, frame in zip(sensors, per_sensor):
                yield pandaset.SENSOR_TOPICS[sensor], frame, pandaset.hesai_cloud(frame)

    topics = [(pandaset.SENSOR_TOPICS[s], pandaset.SENSOR_FRAME) for s in sensors]
    return write_bag(out, storage, topics, pandaset.BOX_TOPICS, frames(), overwrite=overwrite, quiet=quiet,
                     total=len(indices))
