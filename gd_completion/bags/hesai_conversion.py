"""Raw Hesai packet bags (pandar_msgs/PandarScan) to bags of PointCloud2 scans, one per rotation."""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.recfunctions import repack_fields

from gd_completion.bags.messages import pointcloud2_msg
from gd_completion.bags.reader import iter_raw, open_bag
from gd_completion.bags.typestore import POINTCLOUD2, deserialize, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer
from gd_completion.errors import BagError
from gd_completion.hesai import ScanAssembler
from gd_completion.hesai.calibration import Calibration
from gd_completion.hesai.packets import packet_time_s, packets_to_array, parse_packets
from gd_completion.pointcloud2 import write_points
from gd_completion.progress import progress_bar
from gd_completion.stamp_sync import stamp_to_ns

PANDAR_SCAN = "pandar_msgs/msg/PandarScan"
DEFAULT_OUTPUT_TOPIC = "/pandar_points"
DEFAULT_FRAME_ID = "hesai_lidar"
CLOUD_FIELDS = ("x", "y", "z", "intensity", "ring", "timestamp")


@dataclass(frozen=True)
class HesaiConversion:
    """What `convert_hesai` wrote: scans (PointCloud2 messages) and their points in all."""

    scans: int
    points: int


def _input_connections(reader: Any, topic: str | None, source: Path) -> list[Any]:
    conns = [c for c in reader.connections if c.msgtype == PANDAR_SCAN and (topic is None or c.topic == topic)]
    if not conns:
        wanted = f"topic {topic} of type {PANDAR_SCAN}" if topic else f"a {PANDAR_SCAN} topic"
        raise BagError(f"{source}: no {wanted} in the bag")
    if topic is None and len({c.topic for c in conns}) > 1:
        raise BagError(f"{source}: several {PANDAR_SCAN} topics ({sorted({c.topic for c in conns})}); "
                       "choose one with --input-topic")
    return conns


def iter_scans(source: Path, assembler: ScanAssembler, *, topic: str | None = None, host_time: bool = True,
               keep_partial: bool = False) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (stamp ns, structured scan) for every rotation in the bag (stamp = earliest point time)."""
    offset_s = 0.0
    emitted = 0
    with open_bag(source) as reader:
        conns = _input_connections(reader, topic, source)
        for conn, bag_ns, raw in iter_raw(reader, conns):
            msg = deserialize(raw, PANDAR_SCAN, f"{source} ({conn.topic} at {bag_ns})")
            assembler.source = f"{source} ({conn.topic} at {bag_ns})"
            packets = [bytes(p.data[: int(p.size)]) for p in msg.packets]
            if not packets:
                continue
            scans = assembler.add(packets)
            if host_time:
                fmt, array = packets_to_array(packets, assembler.model_name, f"{source} ({conn.topic} at {bag_ns})")
                sensor = packet_time_s(fmt, parse_packets(fmt, array))
                host = np.array([stamp_to_ns(p.stamp) for p in msg.packets], dtype=np.float64) * 1e-9
                offset_s = float(np.median(host - sensor))
            for scan in scans:
                emitted += 1
                if emitted == 1 and not keep_partial:
                    continue  # the recording starts mid-rotation
                yield _stamped(scan, offset_s)
        if keep_partial:
            for scan in assembler.flush():
                yield _stamped(scan, offset_s)


def _stamped(scan: np.ndarray, offset_s: float) -> tuple[int, np.ndarray]:
    if offset_s:
        scan = scan.copy()
        scan["timestamp"] += offset_s
    start = float(scan["timestamp"].min()) if scan.size else 0.0
    return int(round(start * 1e9)), scan


def convert_hesai(source: str | Path, out: str | Path, calibration: Calibration, *, model: str = "auto",
                  frame_id: str = DEFAULT_FRAME_ID, input_topic: str | None = None,
                  output_topic: str = DEFAULT_OUTPUT_TOPIC, storage: str = "mcap", overwrite: bool = False,
                  min_range: float = 0.3, max_range: float = 200.0, scan_phase: float = 0.0, host_time: bool = True,
                  keep_partial: bool = False, quiet: bool = False) -> HesaiConversion:
    """Decode one packet bag into a new bag of PointCloud2 scans on `output_topic` (fields `CLOUD_FIELDS`), cut at
    `scan_phase` degrees; the output appears under its final name only when complete.

    `host_time`: stamps and point times on the host clock (the packets' receive stamps), else the lidar's own.
    `keep_partial`: also the incomplete first and last rotations. Raises BagError when no rotation was decoded.
    """
    source, out = Path(source), Path(out)
    assembler = ScanAssembler(calibration, model=model, scan_phase=scan_phase, min_range=min_range,
                              max_range=max_range, source=str(source))
    count, points = 0, 0
    with (atomic_bag_writer(out, storage=storage, overwrite=overwrite) as writer,
          progress_bar(out.name, "scans", quiet=quiet) as bar):
        conn = add_connection(writer, output_topic, POINTCLOUD2)
        for ns, scan in iter_scans(source, assembler, topic=input_topic, host_time=host_time,
                                   keep_partial=keep_partial):
            msg = pointcloud2_msg(write_points(repack_fields(scan[list(CLOUD_FIELDS)])), frame_id, ns)
            writer.write(conn, ns, serialize(msg, POINTCLOUD2))
            count += 1
            points += scan.size
            bar.update(1)
        if count == 0:
            raise BagError(f"{source}: no complete rotation decoded (use --keep-partial for short recordings)")
    return HesaiConversion(count, points)
