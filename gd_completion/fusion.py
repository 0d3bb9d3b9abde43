"""Track fusion: each tracked vehicle's points from all of its frames, accumulated in its own box frame.

A vehicle's points are kept per frame in metres in the box frame of that frame's box (centred on the box,
rotated by -yaw, not divided by the length; then aligned to the track, below), so a later box of a slightly
different length does not rescale old points. `TrackFusion.update` returns each vehicle with the track's
fused partial in the current box's normalised frame (divided by the current length, as `geometry.normalize` does): the
network sees every side the track has shown so far. The partial lists the oldest frame first, so the
farthest point sampling of the network input (and of the measured merge) starts at the same point from
frame to frame (until the bounds drop the oldest frame), which keeps consecutive completions alike
(measured: docs/evaluation/report.md, "track fusion"); the most recent frames count through the bounds,
which drop the oldest frames first.

Bounds: every frame is voxel-downsampled (one point per `voxel_size` voxel and frame; the pipeline
resamples the network input to its fixed size anyway, so this only bounds memory and the resampling
work), whole oldest frames are dropped beyond `max_points_per_track` or `max_frames_per_track`, the least
recently seen tracks are evicted beyond `max_tracks`, and tracks unseen for `expiry_s` (stamp time) expire.

Box jitter: each new frame's points are aligned to the track's fused points before they are stored
(`registration.align_planar`: x, y and yaw, trimmed ICP, bounded in cost and in the correction it may
apply; `FusionLimits.align`, None = off). The frames are stored in the track's own frame (the first
frame's box, every later frame aligned to the points before it) and handed out in the mean placement of
the track's boxes (the inverse of the mean correction applied; a refused or unaligned frame counts as no
correction), not in the current box's placement: the completion keeps its place in the box from frame to
frame instead of following this box's jitter, and sits as far (a few centimetres) from this frame's
measured points as this box is off the mean. A fit that is refused (fewer than `min_pairs` points or
matches, or a correction too large to be jitter) stores the frame as its box placed it; both outcomes are
counted.

A box whose length, width or height jumps by more than `size_change` (relative) starts the track afresh:
the detector reused the id for another object. Vehicles with a negative instance id (no track) and repeats
of an id within one frame are passed through unfused.
"""
from __future__ import annotations

import threading
from collections import OrderedDict, deque
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace

import numpy as np

from gd_completion.geometry import Box3D, denormalize
from gd_completion.limits import check_positive_fields
from gd_completion.preprocess import CroppedVehicle
from gd_completion.registration import AlignSettings, PlanarTransform, align_planar
from gd_completion.sampling import evenly_strided, strided_indices, voxel_first_indices

__all__ = ["FusionLimits", "TrackFusion"]


@dataclass(frozen=True)
class FusionLimits:
    """Bounds of the track fusion (per track and in the number of tracks)."""

    max_tracks: int = 256               # tracks kept at most; the least recently seen is evicted beyond it
    max_points_per_track: int = 20_000  # fused points per track at most (oldest frames dropped first)
    max_frames_per_track: int = 100     # frames per track at most (oldest dropped)
    voxel_size: float = 0.02            # metres in the box frame: one point per voxel and frame
    expiry_s: float = 3.0               # a track not seen for this long (stamp time) is dropped
    size_change: float = 0.25           # relative change of the box length, width or height that resets a
                                        # track (a detector reused the id for another object)
    align: AlignSettings | None = field(default_factory=AlignSettings)  # per-frame jitter alignment; None = off

    def __post_init__(self) -> None:
        if self.align is not None and not isinstance(self.align, AlignSettings):
            raise ValueError(f"FusionLimits.align={self.align!r} must be AlignSettings or None")
        check_positive_fields(self, skip=("align",))


class _Track:
    """One track: its last box and stamp, its frames (newest last) in metres in the box frame."""

    __slots__ = ("box", "correction_sum", "frames", "frames_seen", "last_ns", "points", "target")

    def __init__(self, box: Box3D, stamp_ns: int) -> None:
        self.box = box
        self.last_ns = stamp_ns
        self.frames: deque[np.ndarray] = deque()
        self.points = 0
        self.correction_sum = np.zeros(3)  # (yaw, tx, ty) of the frames' alignments, summed
        self.frames_seen = 0               # frames added since the track started (dropped ones included)
        self.target: np.ndarray | None = None   # the alignment target: evenly strided points of the frames

    def add(self, metres: np.ndarray, limits: FusionLimits) -> np.ndarray:
        """Store a frame's points (dropping the oldest frames beyond the bounds); returns the rows of `metres`
        stored (all of them unless the frame alone is over `max_points_per_track`: then evenly thinned)."""
        keep = strided_indices(len(metres), limits.max_points_per_track)
        if len(keep) < len(metres):
            metres = metres[keep]
        self.frames.append(metres)
        self.points += len(metres)
        while len(self.frames) > 1 and (self.points > limits.max_points_per_track
                                        or len(self.frames) > limits.max_frames_per_track):
            self.points -= len(self.frames.popleft())
        return keep

    def metres(self) -> np.ndarray:
        """(P, 3) float32: every frame's points in metres in the track's frame, oldest frame first."""
        return np.concatenate(list(self.frames)) if self.frames else np.zeros((0, 3), np.float32)

    def fused_normalized(self, metres: np.ndarray) -> np.ndarray:
        """(P, 3) float32: the track's points (`metres()`), in the mean box placement, divided by the current
        length."""
        metres = metres.astype(np.float64)
        if self.correction_sum.any():   # into the mean box placement: undo the mean correction
            metres = PlanarTransform(*(self.correction_sum / self.frames_seen)).undo(metres)
        return (metres / self.box.size[0]).astype(np.float32)


def _size_jump(old: Box3D, new: Box3D, limit: float) -> bool:
    return any(abs(n - o) > limit * o for o, n in zip(old.size, new.size))


class TrackFusion:
    """Per-track accumulator of a vehicle's points in its own box frame (metres: centred on the box, rotated
    by -yaw, NOT divided by the length), bounded per track and in the number of tracks.

    Thread-safe (one lock); meant to see the frames of one stream in stamp order. A stamp earlier than the
    latest seen (a replay restarted) drops every track, counted as expired.
    """

    def __init__(self, limits: FusionLimits | None = None) -> None:
        self.limits = limits or FusionLimits()
        self._tracks: OrderedDict[int, _Track] = OrderedDict()   # least recently seen first
        self._latest_ns: int | None = None
        self._lock = threading.Lock()
        self._expired = 0
        self._reset = 0
        self._evicted = 0
        self._aligned = 0
        self._align_refused = 0

    def update(self, stamp_ns: int, vehicles: Sequence[CroppedVehicle], executor: Executor | None = None
               ) -> list[CroppedVehicle]:
        """Add each vehicle (keyed by `box.instance_id`) to its track; return, in the same order, the vehicles
        with `normalized` the track's fused partial in the current box's normalised frame (oldest frame first;
        the current frame last: its rows `current_source` of `measured`). `measured` and `box` stay the current
        frame's. `executor`: aligns the vehicles' frames to their tracks in parallel (the ICP kernel releases the
        GIL); the result is the same as without it."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            self._restart_if_time_went_back(stamp_ns)
            seen: set[int] = set()
            fused_rows: list[int] = []
            prepared = []
            for row, vehicle in enumerate(vehicles):
                key = vehicle.box.instance_id
                if key < 0 or key in seen:
                    continue
                seen.add(key)
                fused_rows.append(row)
                prepared.append(self._prepare(stamp_ns, vehicle))
            align = self.limits.align
            jobs = [(metres, track.target) for track, metres, _ in prepared]

            def fit(job: tuple[np.ndarray, np.ndarray | None]) -> PlanarTransform | None:
                metres, target = job
                return align_planar(metres, target, align) if align is not None and target is not None \
                    and len(metres) else None
            run = executor.map if executor is not None and len(jobs) > 1 else map
            fits = list(run(fit, jobs))
            out = list(vehicles)
            for row, (track, metres, kept), transform in zip(fused_rows, prepared, fits):
                fused, current = self._store(track, vehicles[row], metres, kept, transform)
                # the frame's surround (points beside its crop) is not pooled for a track: it changes from frame to
                # frame (costing the track's consistency), and the frames' own crops, each cut by its own box,
                # already bring back what one loose box cuts off
                out[row] = replace(vehicles[row], normalized=fused, current_source=current,
                                   surround=np.zeros((0, 3), np.float32))
            return out

    def _prepare(self, stamp_ns: int, vehicle: CroppedVehicle) -> tuple[_Track, np.ndarray, np.ndarray]:
        """The vehicle's track (a new one when it expired or its box jumped in size), its frame's points in metres
        in the box frame voxel-thinned, and the rows of `normalized` those are."""
        key, box = vehicle.box.instance_id, vehicle.box
        track = self._tracks.get(key)
        if track is not None and stamp_ns - track.last_ns > self.limits.expiry_s * 1e9:
            self._expired += 1
            track = None
        elif track is not None and _size_jump(track.box, box, self.limits.size_change):
            self._reset += 1
            track = None
        if track is None:
            track = _Track(box, stamp_ns)
        track.box, track.last_ns = box, stamp_ns
        metres = np.asarray(vehicle.normalized, dtype=np.float32).reshape(-1, 3) * np.float32(box.size[0])
        kept = voxel_first_indices(metres, self.limits.voxel_size)
        return track, metres[kept], kept

    def _store(self, track: _Track, vehicle: CroppedVehicle, metres: np.ndarray, kept: np.ndarray,
               transform: PlanarTransform | None) -> tuple[np.ndarray, np.ndarray]:
        """Store the frame (aligned by `transform` when the fit was accepted) in its track; the fused partial and
        the rows of `measured` its last rows are."""
        if self.limits.align is not None and track.target is not None and len(metres):
            if transform is None:
                self._align_refused += 1
            else:
                metres = transform.apply(metres)
                self._aligned += 1
                track.correction_sum += (transform.yaw, transform.tx, transform.ty)
        track.frames_seen += 1
        kept = kept[track.add(metres, self.limits)]
        self._tracks.pop(vehicle.box.instance_id, None)
        self._tracks[vehicle.box.instance_id] = track
        everything = track.metres()   # one concatenation per update: the fused partial and the next target
        if self.limits.align is not None:
            track.target = evenly_strided(everything, self.limits.align.max_target_points)
        fused = track.fused_normalized(everything)
        while len(self._tracks) > self.limits.max_tracks:
            self._tracks.popitem(last=False)
            self._evicted += 1
        return fused, kept

    def _restart_if_time_went_back(self, stamp_ns: int) -> int:
        """Drop every track when `stamp_ns` is earlier than the latest stamp seen; returns how many."""
        dropped = 0
        if self._latest_ns is not None and stamp_ns < self._latest_ns:
            dropped = len(self._tracks)
            self._expired += dropped
            self._tracks.clear()
        self._latest_ns = stamp_ns
        return dropped

    def fused_measured(self, vehicle: CroppedVehicle) -> np.ndarray:
        """(P, 3) float32: the points of a vehicle as `update` returned it (its track's fused partial, or its
        own points when it has no track) back in the cloud frame of its box, for publishing."""
        return denormalize(np.asarray(vehicle.normalized, dtype=np.float32).reshape(-1, 3), vehicle.box)

    def expire(self, now_ns: int) -> int:
        """Drop the tracks unseen for more than `expiry_s` before `now_ns`; returns how many."""
        now_ns = int(now_ns)
        with self._lock:
            dropped = self._restart_if_time_went_back(now_ns)
            horizon = self.limits.expiry_s * 1e9
            stale = [k for k, t in self._tracks.items() if now_ns - t.last_ns > horizon]
            for key in stale:
                del self._tracks[key]
            self._expired += len(stale)
            return dropped + len(stale)

    @property
    def counters(self) -> dict[str, int]:
        """Tracks alive now, and tracks expired, reset (size jump) and evicted (over `max_tracks`) so far; frames
        aligned to their track and alignments refused (the frame stored as its box placed it) so far."""
        with self._lock:
            return {"tracks_alive": len(self._tracks), "tracks_expired": self._expired,
                    "tracks_reset": self._reset, "tracks_evicted": self._evicted,
                    "frames_aligned": self._aligned, "alignments_refused": self._align_refused}
