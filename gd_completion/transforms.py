"""A pure transform buffer (the tf2 subset the completer needs) and 3D boxes moved between frames.

`TransformBuffer` is fed tf2_msgs/TFMessage messages (live /tf and /tf_static, or a bag's, deserialised by
rosbags; duck-typed) and answers `lookup(target, source, stamp_ns)` with the 4x4 matrix mapping points in
`source` to `target`. As in tf2, the transform of an edge with header.frame_id = parent and child_frame_id =
child maps points in child to parent; every frame has at most one parent, so the frames form a forest.
"""
from __future__ import annotations

import bisect
import math
import threading
import time
from array import array
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from gd_completion.box_messages import BoxSet
from gd_completion.errors import GDCompletionError
from gd_completion.geometry import Box3D, boxes_to_array
from gd_completion.rotations import quaternion_matrix
from gd_completion.stamp_sync import stamp_to_ns

__all__ = [
    "TransformError", "TransformCounters", "TransformBuffer",
    "transform_boxes", "boxes_to_frame", "boxes_in_frame",
]

# Buffer defaults (see TransformBuffer).
CACHE_S = 10.0           # tf2's default cache length
EXTRAPOLATION_S = 0.05   # one sync tolerance (stamp_sync.SYNC_TOLERANCE_S): half a 10 Hz period
MAX_FRAMES = 1000        # child frames; a vehicle's tf tree has tens
MAX_SAMPLES_PER_FRAME = 10_000  # 1 kHz for 10 s; 64 bytes a sample
_MIN_QUAT_NORM = 1e-6    # a quaternion shorter than this is "zero" (no rotation can be read from it)
_NS = 1_000_000_000
_WIDTH = 7               # tx, ty, tz, qx, qy, qz, qw per dynamic sample


class TransformError(GDCompletionError):
    """A transform that cannot be looked up: unknown frame, frames not connected, stamp outside the data."""


class TransformNotYet(TransformError):
    """The stamp is newer than an edge's newest sample: the transform may still arrive."""


@dataclass
class TransformCounters:
    """What the buffer took and what it skipped (cumulative). Skips never raise."""

    taken: int = 0            # transforms stored
    malformed: int = 0        # unreadable entry, empty frame id, own parent, non-finite value, zero quaternion
    loop: int = 0             # the edge would close a loop (its parent descends from its child)
    too_old: int = 0          # dynamic sample older than cache_s before the newest of its child
    too_many_frames: int = 0  # a new child frame beyond max_frames
    reparented: int = 0       # taken, and the child's earlier parent (and its samples) dropped
    kind_changed: int = 0     # taken: a static transform for a dynamic child, or the other way round

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class _Static:
    parent: str
    matrix: np.ndarray  # (4, 4) parent <- child


@dataclass
class _Dynamic:
    parent: str
    stamps: array   # 'q', ascending, unique
    values: array   # 'd', _WIDTH per sample: translation then unit quaternion (x, y, z, w)


def _frame(raw: Any) -> str:
    """A frame id as stored: text without one leading '/' (ROS 1 style ids still arrive from some drivers)."""
    text = str(raw)
    return text[1:] if text.startswith("/") else text


def _matrix(values: Sequence[float] | np.ndarray) -> np.ndarray:
    """4x4 of (tx, ty, tz, qx, qy, qz, qw)."""
    out = np.eye(4)
    out[:3, :3] = quaternion_matrix(*values[3:7])
    out[:3, 3] = values[:3]
    return out


def _slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions, fraction f in [0, 1]."""
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: normalised linear interpolation is exact to rounding
        q = q0 + f * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    s = math.sin(theta)
    return (math.sin((1.0 - f) * theta) / s) * q0 + (math.sin(f * theta) / s) * q1


def _inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4."""
    out = np.eye(4)
    rt = m[:3, :3].T
    out[:3, :3] = rt
    out[:3, 3] = -rt @ m[:3, 3]
    return out


def _read(t: Any) -> tuple[str, str, int | None, tuple[float, ...]]:
    """(parent, child, stamp_ns or None when unreadable, values) of a TransformStamped; raises on bad input."""
    parent, child = _frame(t.header.frame_id), _frame(t.child_frame_id)
    if not parent or not child:
        raise ValueError(f"empty frame id (parent {parent!r}, child {child!r})")
    if parent == child:
        raise ValueError(f"frame {child!r} would be its own parent")
    tr, rot = t.transform.translation, t.transform.rotation
    values = tuple(float(v) for v in (tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w))
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite transform {parent!r} -> {child!r}: {values}")
    norm = math.sqrt(sum(v * v for v in values[3:]))
    if norm < _MIN_QUAT_NORM:
        raise ValueError(f"zero quaternion in transform {parent!r} -> {child!r}")
    values = values[:3] + tuple(v / norm for v in values[3:])
    try:
        stamp: int | None = stamp_to_ns(t.header.stamp)
    except (AttributeError, TypeError, ValueError):
        stamp = None
    return parent, child, stamp, values


class TransformBuffer:
    """Transforms from TFMessages, looked up between any two connected frames at a time.

    cache_s: dynamic samples are kept per child frame back to `cache_s` seconds before that child's newest
      sample (10 s, tf2's default); static transforms are kept for ever, the latest per child wins.
    extrapolation_s: a stamp up to this far outside a dynamic edge's samples uses the nearest sample (held, not
      extrapolated); farther is a TransformError (tf2 refuses any extrapolation). 0.05 s, the default cloud/boxes
      sync tolerance: a tf published at 10-20 Hz can lag a cloud stamp by that much.
    max_frames: child frames stored (1000; a vehicle's tree has tens); a transform naming a new child beyond it
      is skipped and counted.
    max_samples_per_frame: dynamic samples per child (10,000 = 1 kHz for 10 s); the oldest go first. With the
      defaults the buffer holds at most 1000 x 10,000 x 64 bytes = 640 MB, in practice a few kB.

    Thread-safe: one subscription may feed it while another thread looks up.
    """

    def __init__(self, cache_s: float = CACHE_S, extrapolation_s: float = EXTRAPOLATION_S,
                 max_frames: int = MAX_FRAMES, max_samples_per_frame: int = MAX_SAMPLES_PER_FRAME) -> None:
        if not (math.isfinite(cache_s) and cache_s >= 0.0):
            raise ValueError(f"cache_s must be a finite number >= 0, got {cache_s}")
        if not (math.isfinite(extrapolation_s) and extrapolation_s >= 0.0):
            raise ValueError(f"extrapolation_s must be a finite number >= 0, got {extrapolation_s}")
        if int(max_frames) < 1 or int(max_samples_per_frame) < 1:
            raise ValueError(f"max_frames and max_samples_per_frame must be >= 1, got {max_frames}, "
                             f"{max_samples_per_frame}")
        self.cache_ns = round(cache_s * _NS)
        self.extrapolation_ns = round(extrapolation_s * _NS)
        self.max_frames = int(max_frames)
        self.max_samples_per_frame = int(max_samples_per_frame)
        self.counters = TransformCounters()
        self.last_problem: str | None = None  # why the latest skipped transform was skipped (for a log line)
        self._edges: dict[str, _Static | _Dynamic] = {}  # child -> its edge to its parent
        self._parent_refs: Counter[str] = Counter()      # frame -> how many children name it as parent
        self._lock = threading.Condition()   # a lock; notified when transforms arrive (`lookup`'s wait)

    # ---- ingestion -------------------------------------------------------------------------------------

    def add_message(self, msg: Any, static: bool) -> int:
        """Store the transforms of a TFMessage (from /tf_static when `static`); how many were taken.

        Never raises on bad content: each skipped transform is counted in `counters` and described in
        `last_problem`."""
        try:
            entries = list(msg.transforms)
        except (AttributeError, TypeError) as exc:
            with self._lock:
                self._skip("malformed", f"not a TFMessage ({type(msg).__name__}): {exc}")
            return 0
        taken = 0
        with self._lock:
            for t in entries:
                taken += self._add(t, static)
            if taken:
                self._lock.notify_all()
        return taken

    def _skip(self, counter: str, why: str) -> int:
        setattr(self.counters, counter, getattr(self.counters, counter) + 1)
        self.last_problem = why
        return 0

    def _add(self, t: Any, static: bool) -> int:
        try:
            parent, child, stamp, values = _read(t)
        except (AttributeError, TypeError, ValueError) as exc:
            return self._skip("malformed", f"unusable transform: {exc}")
        if stamp is None and not static:
            return self._skip("malformed", f"unreadable stamp in transform {parent!r} -> {child!r}")
        edge = self._edges.get(child)
        if edge is None and len(self._edges) >= self.max_frames:
            return self._skip("too_many_frames", f"frame {child!r} beyond max_frames={self.max_frames}")
        if edge is None or edge.parent != parent:
            if self._descends(parent, child):
                return self._skip("loop", f"{parent!r} -> {child!r} would close a loop: {parent!r} descends "
                                          f"from {child!r}")
        if edge is not None and isinstance(edge, _Static) != static:
            self.counters.kind_changed += 1  # the latest kind wins (a frame moved between /tf and /tf_static)
            edge = None
        if edge is not None and edge.parent != parent:
            self.counters.reparented += 1
            edge = None
        if static:
            self._set_edge(child, _Static(parent, _matrix(values)))
        elif stamp is not None:
            dynamic = edge if isinstance(edge, _Dynamic) else _Dynamic(parent, array("q"), array("d"))
            if dynamic is not edge:
                self._set_edge(child, dynamic)
            if not self._insert(dynamic, stamp, values):
                return self._skip("too_old", f"sample of {parent!r} -> {child!r} at {stamp / _NS:.3f} s is older "
                                             f"than the cache ({self.cache_ns / _NS:g} s before "
                                             f"{dynamic.stamps[-1] / _NS:.3f} s)")
        self.counters.taken += 1
        return 1

    def _set_edge(self, child: str, edge: _Static | _Dynamic) -> None:
        old = self._edges.get(child)
        if old is not None:
            self._parent_refs[old.parent] -= 1
            if self._parent_refs[old.parent] <= 0:
                del self._parent_refs[old.parent]
        self._edges[child] = edge
        self._parent_refs[edge.parent] += 1

    def _descends(self, frame: str, ancestor: str) -> bool:
        """Whether `ancestor` is `frame` or one of its ancestors (the tree is kept loop-free)."""
        while True:
            if frame == ancestor:
                return True
            edge = self._edges.get(frame)
            if edge is None:
                return False
            frame = edge.parent

    def _insert(self, edge: _Dynamic, stamp: int, values: tuple[float, ...]) -> bool:
        """Put a sample in time order (same stamp: replaced), prune to the cache; False when too old."""
        stamps, vals = edge.stamps, edge.values
        if stamps and stamp < stamps[-1] - self.cache_ns:
            return False
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            vals[_WIDTH * i:_WIDTH * (i + 1)] = array("d", values)
            return True
        stamps.insert(i, stamp)
        vals[_WIDTH * i:_WIDTH * i] = array("d", values)
        cut = bisect.bisect_left(stamps, stamps[-1] - self.cache_ns)
        cut = max(cut, len(stamps) - self.max_samples_per_frame)
        if cut > 0:
            del stamps[:cut]
            del vals[:_WIDTH * cut]
        return True

    def clear(self) -> None:
        """Forget every transform (e.g. when a bag replay jumps back in time); counters are kept."""
        with self._lock:
            self._edges.clear()
            self._parent_refs.clear()

    # ---- queries ---------------------------------------------------------------------------------------

    def frames(self) -> set[str]:
        """Every frame named by a stored transform (as child or parent)."""
        with self._lock:
            return set(self._edges) | set(self._parent_refs)

    def sample_count(self, child: str | None = None) -> int:
        """Dynamic samples stored for `child` (its parent edge), or in all, when None; static edges count 1."""
        with self._lock:
            edges = self._edges.values() if child is None else [e for c, e in self._edges.items()
                                                                 if c == _frame(child)]
            return sum(len(e.stamps) if isinstance(e, _Dynamic) else 1 for e in edges)

    def lookup(self, target_frame: str, source_frame: str, stamp_ns: int, wait_s: float = 0.0) -> np.ndarray:
        """(4, 4) float64 mapping points in `source_frame` to `target_frame` at `stamp_ns`.

        Dynamic edges are interpolated between the samples around the stamp (translation linear, rotation
        slerp). Identity when the frames are equal. Raises TransformError naming the frames: unknown frame,
        frames in different trees, or a stamp outside an edge's samples by more than extrapolation_s.
        `wait_s`: until the transforms bracket the stamp (no held sample needed), wait up to this long for them to
        arrive (as tf2's `canTransform` with a timeout); then look up as without a wait."""
        target, source = _frame(target_frame), _frame(source_frame)
        what = f"cannot transform {source_frame!r} -> {target_frame!r}"
        if not target or not source:
            raise TransformError(f"{what}: empty frame id")
        try:
            stamp = int(stamp_ns)
        except (TypeError, ValueError) as exc:
            raise TransformError(f"{what}: stamp {stamp_ns!r} is not integer nanoseconds") from exc
        if target == source:
            return np.eye(4)
        with self._lock:
            if wait_s > 0:
                deadline = time.monotonic() + wait_s
                while not self._ready(target, source, stamp, what) and (left := deadline - time.monotonic()) > 0:
                    self._lock.wait(left)
            return self._locked_lookup(target, source, stamp, what, self.extrapolation_ns)

    def ready(self, target_frame: str, source_frame: str, stamp_ns: int) -> bool:
        """Whether a `lookup` at `stamp_ns` cannot improve by waiting for more transforms (what `lookup` with a wait
        waits for; offline, `complete_bag` reads on for it)."""
        target, source = _frame(target_frame), _frame(source_frame)
        if not target or not source or target == source:
            return True
        with self._lock:
            return self._ready(target, source, int(stamp_ns), f"cannot transform {source_frame!r} -> {target_frame!r}")

    def _ready(self, target: str, source: str, stamp: int, what: str) -> bool:
        """Whether waiting cannot improve the lookup: every dynamic edge has samples on both sides of the stamp,
        or it fails for a reason later transforms do not mend (unknown or unconnected frames, a stamp too old)."""
        try:
            self._locked_lookup(target, source, stamp, what, 0)
        except TransformNotYet:
            return False
        except TransformError:
            return True
        return True

    def _locked_lookup(self, target: str, source: str, stamp: int, what: str, tolerance_ns: int) -> np.ndarray:
        """`lookup` under the lock, holding the nearest sample up to `tolerance_ns` outside an edge's samples."""
        src_chain, tgt_chain = self._chain(source, what), self._chain(target, what)
        at = {f: i for i, f in enumerate(tgt_chain)}
        common = next((i for i, f in enumerate(src_chain) if f in at), None)
        if common is None:
            raise TransformError(f"{what}: the frames are not connected ({source!r} is in the tree of "
                                 f"{src_chain[-1]!r}, {target!r} in the tree of {tgt_chain[-1]!r})")
        up_source = self._compose(src_chain[:common], stamp, what, tolerance_ns)
        up_target = self._compose(tgt_chain[:at[src_chain[common]]], stamp, what, tolerance_ns)
        return _inverse(up_target) @ up_source

    def _chain(self, frame: str, what: str) -> list[str]:
        """`frame`, its parent, ... up to its tree's root."""
        if frame not in self._edges and frame not in self._parent_refs:
            known = sorted(set(self._edges) | set(self._parent_refs))
            listed = ", ".join(repr(f) for f in known[:10]) + (", ..." if len(known) > 10 else "")
            raise TransformError(f"{what}: frame {frame!r} is unknown (known: {listed or 'none'})")
        chain = [frame]
        while (edge := self._edges.get(chain[-1])) is not None:
            chain.append(edge.parent)
        return chain

    def _compose(self, children: list[str], stamp: int, what: str, tolerance_ns: int) -> np.ndarray:
        """Matrix mapping points in children[0] to the parent of children[-1] (identity for none)."""
        out = np.eye(4)
        for child in children:
            out = self._edge_matrix(child, stamp, what, tolerance_ns) @ out
        return out

    def _edge_matrix(self, child: str, stamp: int, what: str, tolerance_ns: int) -> np.ndarray:
        edge = self._edges[child]
        if isinstance(edge, _Static):
            return edge.matrix
        stamps, vals = edge.stamps, edge.values
        i = bisect.bisect_left(stamps, stamp)
        if i < len(stamps) and stamps[i] == stamp:
            return _matrix(vals[_WIDTH * i:_WIDTH * (i + 1)])
        if 0 < i < len(stamps):
            t0, t1 = stamps[i - 1], stamps[i]
            f = (stamp - t0) / (t1 - t0)
            v0 = np.asarray(vals[_WIDTH * (i - 1):_WIDTH * i])
            v1 = np.asarray(vals[_WIDTH * i:_WIDTH * (i + 1)])
            q = _slerp(v0[3:], v1[3:], f)
            return _matrix(np.concatenate([v0[:3] + f * (v1[:3] - v0[:3]), q]))
        nearest = 0 if i == 0 else len(stamps) - 1
        gap = stamps[0] - stamp if i == 0 else stamp - stamps[-1]
        if gap <= tolerance_ns:
            return _matrix(vals[_WIDTH * nearest:_WIDTH * (nearest + 1)])
        side = "past" if i == 0 else "future"
        relation = "before the oldest" if i == 0 else "after the newest"
        raise (TransformError if i == 0 else TransformNotYet)(
            f"{what} at {stamp / _NS:.3f} s: edge {edge.parent!r} -> {child!r} would need extrapolation into the "
            f"{side}: its samples cover [{stamps[0] / _NS:.3f}, {stamps[-1] / _NS:.3f}] s, the stamp is "
            f"{gap / _NS:.3f} s {relation} (tolerance {self.extrapolation_ns / _NS:g} s)")


# ---- boxes -------------------------------------------------------------------------------------------------

def _check_matrix(matrix: np.ndarray) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise TransformError(f"a transform must be a finite 4x4 matrix, got shape {m.shape}")
    return m


def transform_boxes(boxes: Sequence[Box3D], matrix: np.ndarray) -> list[Box3D]:
    """Boxes moved by a rigid 4x4: centre transformed; yaw = heading of the transformed box x-axis projected on
    the target xy plane (exact for rotations about z; a small roll/pitch tilts the box, which stays upright);
    size, label and instance id kept."""
    m = _check_matrix(matrix)
    if not boxes:
        return []
    arr = boxes_to_array(boxes)
    rot = m[:3, :3]
    centers = arr[:, :3] @ rot.T + m[:3, 3]
    # heading (cos, sin, 0) rotated: only the first two columns of rot take part
    hx = rot[0, 0] * np.cos(arr[:, 6]) + rot[0, 1] * np.sin(arr[:, 6])
    hy = rot[1, 0] * np.cos(arr[:, 6]) + rot[1, 1] * np.sin(arr[:, 6])
    yaws = np.arctan2(hy, hx)
    return [replace(b, center=tuple(c), yaw=float(y)) for b, c, y in zip(boxes, centers.tolist(), yaws.tolist())]


def boxes_to_frame(boxes: Sequence[Box3D], source_frame: str, target_frame: str, stamp_ns: int,
                   buffer: TransformBuffer, wait_s: float = 0.0) -> list[Box3D]:
    """Boxes given in `source_frame` expressed in `target_frame` at `stamp_ns` (waiting up to `wait_s` for
    transforms not yet received: `TransformBuffer.lookup`); TransformError when the buffer cannot give it."""
    return transform_boxes(boxes, buffer.lookup(target_frame, source_frame, stamp_ns, wait_s))


def transforms_pending(box_set: BoxSet, frame_id: str, stamp_ns: int, buffer: TransformBuffer) -> bool:
    """Whether moving `box_set`'s boxes into `frame_id` at `stamp_ns` could still improve with later transforms
    (`TransformBuffer.ready` false for one of their frames)."""
    return any(not buffer.ready(frame_id, f, stamp_ns) for f in set(box_set.frame_ids) if f != frame_id)


def boxes_in_frame(box_set: BoxSet, frame_id: str, stamp_ns: int, buffer: TransformBuffer | None,
                   problems: list[str] | None = None, wait_s: float = 0.0) -> tuple[list[Box3D], int]:
    """The boxes of `box_set` in `frame_id` at `stamp_ns` (input order), and how many had no transform.

    Boxes already in `frame_id` are kept as they are; the others are transformed, one lookup per frame, when
    `buffer` has the transform (live, waiting up to `wait_s` for one not yet received), else counted (the lookup's
    message is appended to `problems` when given).
    With buffer None: exactly `box_set.split_by_frame(frame_id)`."""
    if buffer is None:
        return box_set.split_by_frame(frame_id)
    groups: dict[str, list[int]] = {}
    for i, f in enumerate(box_set.frame_ids):
        groups.setdefault(f, []).append(i)
    out: list[Box3D | None] = [None] * len(box_set.boxes)
    missing = 0
    for frame, idx in groups.items():
        members = [box_set.boxes[i] for i in idx]
        if frame == frame_id:
            moved = members
        else:
            try:
                moved = boxes_to_frame(members, frame, frame_id, stamp_ns, buffer, wait_s)
            except TransformError as exc:
                missing += len(idx)
                if problems is not None:
                    problems.append(str(exc))
                continue
        for i, b in zip(idx, moved):
            out[i] = b
    return [b for b in out if b is not None], missing
