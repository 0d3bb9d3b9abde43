"""Track identity for any detector: each box gets a track id, from its message or by associating frames.

`TRACK_ID_MODES`: "message" keeps the detector's ids (a tracker's: Detection3D `id`, marker `id`), "associate"
gives ids from a built-in association of consecutive frames' boxes (for detectors without ids, or with
per-frame indices), "off" gives every box id -1 (no track: no fusion, no reuse).

The association predicts each track's centre at the new stamp (constant velocity, smoothed), gates the
candidate pairs by centre distance (`max_distance` metres plus a share of the box length), equal label
and a bounded change of size, and solves the optimal assignment of the remaining pairs on their centre
distance (`scipy.optimize.linear_sum_assignment`). A box left unmatched starts a new track; a track not
matched for `expiry_s` (stamp time) is dropped; a stamp earlier than the last one (a replay restarted)
drops every track.
"""
from __future__ import annotations

import itertools
import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from gd_completion.geometry import Box3D
from gd_completion.limits import check_positive_fields

TRACK_ID_MODES = ("associate", "message", "off")
_FORBIDDEN = 1e9


@dataclass(frozen=True)
class AssociationSettings:
    """Gates and lifetimes of the built-in association."""

    max_distance: float = 2.0       # metres between the predicted and the new centre, plus `length_share` x length
    length_share: float = 0.25      # of the box length, added to the gate (long vehicles turn and move more)
    max_size_change: float = 0.3    # relative change of length, width or height allowed within a track
    expiry_s: float = 3.0           # a track unmatched this long (stamp time) is dropped
    velocity_smoothing: float = 0.5  # weight of the newest displacement in the smoothed velocity
    max_tracks: int = 4096          # tracks kept at most (the least recently matched are dropped)

    def __post_init__(self) -> None:
        check_positive_fields(self)
        if not 0.0 < self.velocity_smoothing <= 1.0:
            raise ValueError(f"velocity_smoothing={self.velocity_smoothing} must be in (0, 1]")


@dataclass
class _Track:
    track_id: int
    center: np.ndarray     # (3,) metres, cloud frame
    velocity: np.ndarray   # (3,) metres per second
    size: np.ndarray       # (3,)
    label: str
    last_ns: int


class BoxAssociator:
    """Gives the boxes of consecutive frames of one stream track ids (`assign`); thread-safe."""

    def __init__(self, settings: AssociationSettings | None = None) -> None:
        self.settings = settings or AssociationSettings()
        self._tracks: list[_Track] = []
        self._ids = itertools.count(1)
        self._latest_ns: int | None = None
        self._lock = threading.Lock()
        self.started = 0   # tracks started so far
        self.matched = 0   # boxes matched to an existing track so far

    def assign(self, stamp_ns: int, boxes: Sequence[Box3D]) -> list[Box3D]:
        """`boxes` (one frame, stamp `stamp_ns`) with `instance_id` replaced by their track ids, same order."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            if self._latest_ns is not None and stamp_ns < self._latest_ns:
                self._tracks.clear()
            self._latest_ns = stamp_ns
            horizon = self.settings.expiry_s * 1e9
            self._tracks = [t for t in self._tracks if stamp_ns - t.last_ns <= horizon]
            pairs = self._match(stamp_ns, boxes)
            out: list[Box3D] = []
            for i, box in enumerate(boxes):
                track = pairs.get(i)
                center, size = np.asarray(box.center, np.float64), np.asarray(box.size, np.float64)
                if track is None:
                    track = _Track(next(self._ids), center, np.zeros(3), size, box.label, stamp_ns)
                    self._tracks.append(track)
                    self.started += 1
                else:
                    dt = (stamp_ns - track.last_ns) * 1e-9
                    if dt > 0:
                        w = self.settings.velocity_smoothing
                        track.velocity = w * (center - track.center) / dt + (1 - w) * track.velocity
                    track.center, track.size, track.last_ns = center, size, stamp_ns
                    self.matched += 1
                out.append(replace(box, instance_id=track.track_id))
            if len(self._tracks) > self.settings.max_tracks:
                self._tracks.sort(key=lambda t: t.last_ns)
                del self._tracks[:len(self._tracks) - self.settings.max_tracks]
            return out

    def _match(self, stamp_ns: int, boxes: Sequence[Box3D]) -> dict[int, _Track]:
        """Box index -> the track it continues (optimal assignment of the gated pairs)."""
        if not self._tracks or not boxes:
            return {}
        s = self.settings
        predicted = np.array([t.center + t.velocity * (stamp_ns - t.last_ns) * 1e-9 for t in self._tracks])
        centers = np.array([b.center for b in boxes], np.float64)
        sizes = np.array([b.size for b in boxes], np.float64)
        cost = np.linalg.norm(centers[:, None, :2] - predicted[None, :, :2], axis=2)
        gate = s.max_distance + s.length_share * sizes[:, 0]
        track_sizes = np.array([t.size for t in self._tracks])
        size_ok = (np.abs(sizes[:, None, :] - track_sizes[None]) <= s.max_size_change * track_sizes[None]).all(axis=2)
        labels = np.array([b.label for b in boxes], dtype=object)
        label_ok = labels[:, None] == np.array([t.label for t in self._tracks], dtype=object)[None, :]
        allowed = (cost <= gate[:, None]) & size_ok & label_ok
        if not allowed.any():
            return {}
        from scipy.optimize import linear_sum_assignment  # on first use: `completer --help` stays light

        rows, cols = linear_sum_assignment(np.where(allowed, cost, _FORBIDDEN))
        return {int(r): self._tracks[c] for r, c in zip(rows, cols) if allowed[r, c]}

    @property
    def counters(self) -> dict[str, int]:
        """Tracks alive now; tracks started and boxes matched to a track so far."""
        with self._lock:
            return {"association_tracks": len(self._tracks), "association_started": self.started,
                    "association_matched": self.matched}


def track_identity(mode: str, boxes: Sequence[Box3D], stamp_ns: int | None,
                   associator: BoxAssociator | None) -> list[Box3D]:
    """The boxes with the track ids of `mode` (see the module docstring); unstamped frames keep their ids under
    "associate" only when no associator is given."""
    if mode == "message":
        return list(boxes)
    if mode == "off":
        return [b if b.instance_id < 0 else replace(b, instance_id=-1) for b in boxes]
    if mode != "associate":
        raise ValueError(f"track id mode {mode!r} must be one of {TRACK_ID_MODES}")
    if associator is None or stamp_ns is None:
        return list(boxes)
    return associator.assign(stamp_ns, boxes)
