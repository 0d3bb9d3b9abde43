"""Completion reuse: per track, its last completion in the box frame, and when it is due to be run again.

Most vehicles of a street are parked or move with their box, so their completion from the last frame is
nearly the one this frame would give. `CompletionCache` keeps each track's last completion (normalised box
frame, as the pipeline published it) with the measured points it was made from, and `decide` says whether
the network must run again for this frame's points:

- no completion yet (never completed, or the track expired);
- new measured information: the share of this frame's points farther than `distance` metres from the points
  the completion was made from is at least `new_points` (a side not seen before, a vehicle come closer);
- the box's length, width or height changed by more than `size_change` (relative) since;
- the completion is older than `max_age_s` (stamp time).

`Decision.urgency` (>= 1 when due) ranks the due tracks for a frame budget (`pipeline`): a track that is
not re-completed this frame is published from its cache. A stamp earlier than the latest seen (a replay
restarted) drops every entry; entries unseen for `expiry_s` expire; beyond `max_tracks` the least recently
used is dropped.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from gd_completion.limits import check_positive_fields
from gd_completion.sampling import strided_indices, voxel_first_indices

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = ["DUE_UNCACHED", "CachedCompletion", "CompletionCache", "Decision", "ReuseSettings"]

MAX_QUERY_POINTS = 128   # this frame's points tested for new information at most (evenly strided)


@dataclass(frozen=True)
class ReuseSettings:
    """When a track's cached completion is reused instead of running the network (see the module docstring)."""

    new_points: float = 0.25     # share of this frame's points that are new (farther than `distance`) to re-run
    distance: float = 0.2        # metres from the points of the last completion
    size_change: float = 0.05    # relative change of the box length, width or height that re-runs
    max_age_s: float = 2.0       # seconds (stamp time): a completion older than this is re-run
    budget_s: float = math.inf   # seconds of network work per frame (pipeline scheduler); inf: every due track runs
    expiry_s: float = 3.0        # an entry unseen this long (stamp time) is dropped
    max_tracks: int = 1024       # entries kept at most (least recently used dropped)

    def __post_init__(self) -> None:
        check_positive_fields(self, skip=("budget_s",))
        if not 0.0 < self.new_points <= 1.0:
            raise ValueError(f"ReuseSettings.new_points={self.new_points} must be in (0, 1]")
        if math.isnan(self.budget_s) or self.budget_s <= 0:
            raise ValueError(f"ReuseSettings.budget_s={self.budget_s} must be positive (inf: no budget)")


@dataclass
class CachedCompletion:
    """A track's last completion: normalised points, which rows were measured points, its box size and stamp."""

    points: np.ndarray          # (n, 3) float32, normalised box frame of the box it was made in
    measured: np.ndarray        # (n,) bool: rows that copy the measured points it was made from
    size: tuple[float, ...]
    stamp_ns: int
    reference: cKDTree          # the measured points it was made from, metres in the box frame (voxel-thinned)
    last_seen_ns: int
    box_frame: np.ndarray | None = None   # the refined box in that box's frame (`BoxFrame` vector), if any

    def __post_init__(self) -> None:
        self.generated = self.points[~self.measured]   # what is published beside this frame's measured points


@dataclass(frozen=True)
class Decision:
    """Whether a track's network completion is due this frame, how urgently, and its cache entry (if any)."""

    due: bool
    urgency: float                     # max of the criteria over their thresholds (>= 1 when due); inf: no entry
    reason: str                        # "none", "new_points", "size", "age" or "" (not due)
    cached: CachedCompletion | None


# The decision for a vehicle with nothing cached (never completed, no track id, a repeated id): its network run is due.
DUE_UNCACHED = Decision(True, math.inf, "none", None)


def _metres(normalized: np.ndarray, length: float) -> np.ndarray:
    return np.asarray(normalized, np.float32).reshape(-1, 3) * np.float32(length)


class CompletionCache:
    """Each track's last completion, keyed by track id; thread-safe (one lock)."""

    def __init__(self, settings: ReuseSettings | None = None) -> None:
        self.settings = settings or ReuseSettings()
        self._entries: OrderedDict[int, CachedCompletion] = OrderedDict()
        self._latest_ns: int | None = None
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def decide(self, key: int, stamp_ns: int, size: tuple[float, ...], current: np.ndarray) -> Decision:
        """Decision for track `key` whose box has `size` and whose points this frame are `current` (normalised by
        that box)."""
        s = self.settings
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                entry.last_seen_ns = int(stamp_ns)
                self._entries.move_to_end(key)
        if entry is None:
            return DUE_UNCACHED
        ratios = {"age": (stamp_ns - entry.stamp_ns) * 1e-9 / s.max_age_s,
                  "size": max(abs(n - o) / o for o, n in zip(entry.size, size)) / s.size_change}
        points = _metres(current, size[0])
        if len(points):
            points = points[strided_indices(len(points), MAX_QUERY_POINTS)]
            distance, _ = entry.reference.query(points, k=1, distance_upper_bound=s.distance)
            ratios["new_points"] = float(np.mean(~np.isfinite(distance))) / s.new_points
        reason, urgency = max(ratios.items(), key=lambda item: item[1])
        due = urgency >= 1.0
        return Decision(due, urgency, reason if due else "", entry)

    def store(self, key: int, stamp_ns: int, size: tuple[float, ...], points: np.ndarray,
              measured: np.ndarray, source: np.ndarray, box_frame: np.ndarray | None = None) -> None:
        """Keep `points` (normalised, `measured` rows copying measurements) as track `key`'s completion, made at
        `stamp_ns` from the normalised points `source` of a box of `size` (and the refined box's `box_frame`)."""
        from scipy.spatial import cKDTree  # on first use: `completer --help` stays light

        metres = _metres(source, size[0])
        reference = cKDTree(metres[voxel_first_indices(metres, self.settings.distance / 2)] if len(metres)
                            else np.full((1, 3), 1e6, np.float32))   # nothing measured: every point is new
        entry = CachedCompletion(np.asarray(points, np.float32), np.asarray(measured, bool),
                                 tuple(float(v) for v in size), int(stamp_ns), reference, int(stamp_ns), box_frame)
        with self._lock:
            self._entries[key] = entry
            self._entries.move_to_end(key)
            while len(self._entries) > self.settings.max_tracks:
                self._entries.popitem(last=False)

    def expire(self, now_ns: int) -> int:
        """Drop every entry when `now_ns` is earlier than the latest stamp seen, else those unseen for more than
        `expiry_s`; returns how many."""
        now_ns = int(now_ns)
        with self._lock:
            if self._latest_ns is not None and now_ns < self._latest_ns:
                dropped = len(self._entries)
                self._entries.clear()
            else:
                horizon = self.settings.expiry_s * 1e9
                stale = [k for k, e in self._entries.items() if now_ns - e.last_seen_ns > horizon]
                for key in stale:
                    del self._entries[key]
                dropped = len(stale)
            self._latest_ns = now_ns
            return dropped
