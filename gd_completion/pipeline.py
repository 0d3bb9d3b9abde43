"""Completion pipeline: crop and normalise every vehicle of a frame (`preprocess`), complete it, map back."""
from __future__ import annotations

import math
import os
import threading
import time
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gd_completion.association import TRACK_ID_MODES, AssociationSettings, BoxAssociator, track_identity
from gd_completion.class_maps import UNMAPPED
from gd_completion.errors import DeviceError
from gd_completion.fusion import TrackFusion
from gd_completion.geometry import Box3D, box_problem, denormalize, finite_mask, normalize
from gd_completion.labels import DEFAULT_LABELS, LABEL_IDS
from gd_completion.limits import FrameLimits, screen_boxes
from gd_completion.merge import PLANE_SHARE, check_plane_share, merge_with_pool
from gd_completion.model.box_refiner import box_from_frame
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint
from gd_completion.model.network import GGDNet, box_shape
from gd_completion.preprocess import POOL_MARGIN, CroppedVehicle, Preprocessing, check_pool_margin, crop_vehicles
from gd_completion.registration import align_planar
from gd_completion.reuse import DUE_UNCACHED, CachedCompletion, CompletionCache, Decision, ReuseSettings
from gd_completion.sampling import resample_indices
from gd_completion.settings import CompletionSettings
from gd_completion.spacing import even_spacing

__all__ = ["COMPLETION_DTYPE", "DEFAULT_LABELS", "LABEL_IDS", "FrameCompletion", "FrameStats", "VehicleCompleter",
           "check_device", "completion_to_structured", "default_threads"]

COMPLETION_DTYPE = np.dtype(
    [("x", np.float32), ("y", np.float32), ("z", np.float32),
     ("instance_id", np.int32), ("label", np.uint8), ("generated", np.uint8)]
)


@dataclass
class FrameStats:
    """What happened to the vehicles and points of one frame."""

    completed: int = 0
    skipped: Counter = field(default_factory=Counter)
    skipped_boxes: list[tuple[Box3D, str]] = field(default_factory=list)   # each skipped box and its reason
    nonfinite_points: int = 0
    ignored_labels: int = 0
    unmapped_class_ids: int = 0    # boxes whose numeric class id no class map names (`class_maps.UNMAPPED`)
    completions_run: int = 0       # vehicles the network completed this frame
    completions_reused: int = 0    # vehicles published from their track's cached completion (`reuse`)
    completions_deferred: int = 0  # of those, due for a re-run but left to a later frame by the budget

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    def skip(self, box: Box3D, reason: str) -> None:
        """Count `box` as skipped for `reason` (a key of `skipped`, a `skipped_<reason>` counter of the node)."""
        self.skipped[reason] += 1
        self.skipped_boxes.append((box, reason))


@dataclass
class FrameCompletion:
    """Completed vehicles of one frame, in the cloud's frame; one row per output point."""

    points: np.ndarray  # (M, 3) float32
    instance_id: np.ndarray  # (M,) int32
    label: np.ndarray  # (M,) uint8, LABEL_IDS
    generated: np.ndarray  # (M,) uint8: 0 measured point, 1 generated (by the network, or a mirrored measurement)
    stats: FrameStats
    boxes: list[Box3D] = field(default_factory=list)   # per completed vehicle, in output order: its refined box
    # (where the box refiner places the true box; the given box for a model without one), published id and label


# One vehicle's network result: its completion (normalised), per point the row of the partial it copies (-1:
# generated), and the refined box in the given box's normalised frame (`BoxFrame` vector; None without a refiner).
VehicleResult = tuple[np.ndarray, np.ndarray, "np.ndarray | None"]


def completion_to_structured(completion: FrameCompletion) -> np.ndarray:
    """Pack a FrameCompletion into a structured array (x, y, z, instance_id, label, generated)."""
    out = np.empty(len(completion.points), dtype=COMPLETION_DTYPE)
    out["x"], out["y"], out["z"] = completion.points.T
    out["instance_id"] = completion.instance_id
    out["label"] = completion.label
    out["generated"] = completion.generated
    return out


def check_device(device: str) -> None:
    """DeviceError (one clear line) when `device` is not a torch device this machine has."""
    try:
        kind = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise DeviceError(f"device {device!r}: not a torch device ({exc})") from exc
    if kind.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceError(f"device {device!r} requested, but this torch build or machine has no CUDA device "
                              "(torch.cuda.is_available() is False); use device cpu")
        if kind.index is not None and kind.index >= torch.cuda.device_count():
            raise DeviceError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif kind.type != "cpu":
        raise DeviceError(f"device {device!r}: only cpu and cuda[:N] are supported")


def default_threads() -> int:
    """Vehicle threads when none are asked for: one per CPU core available to this process."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


class VehicleCompleter:
    """Completes every vehicle of a frame with the GGD-Net, one vehicle per task on `threads` CPU threads.

    Each vehicle is computed on its own (bitwise the same result alone or in any frame). On the CPU,
    `threads` > 1 completes that many vehicles at once, each on one torch thread: the network's searches
    and small layers use a second intra-op thread poorly, so vehicles in parallel use the cores best.
    """

    def __init__(
        self,
        model: GGDNet,
        *,
        preprocessing: Preprocessing | None = None,
        limits: FrameLimits | None = None,
        labels: Sequence[str] = DEFAULT_LABELS,
        include_input_points: bool = True,
        device: str = "cpu",
        threads: int = 1,
        fusion: TrackFusion | None = None,
        publish_fused_points: bool = False,
        measured_merge: bool = True,
        mirror_plane: float = PLANE_SHARE,
        even_spacing: bool = True,
        pool_margin: float = POOL_MARGIN,
        track_ids: str = "message",
        association: AssociationSettings | None = None,
        reuse: ReuseSettings | None = None,
    ) -> None:
        self.model = model.to(device).eval()
        self.device = torch.device(device)
        self.preprocessing = preprocessing or Preprocessing()
        self.limits = limits or FrameLimits()
        self.labels = frozenset(labels)
        self.include_input_points = bool(include_input_points)
        self.fusion = fusion
        self.publish_fused_points = bool(publish_fused_points)
        self.measured_merge = bool(measured_merge)
        self.mirror_plane = check_plane_share(mirror_plane)   # share of the seen side's plane offset (`merge`)
        self.even_spacing = bool(even_spacing)
        self.pool_margin = check_pool_margin(pool_margin)   # metres: points kept aside for the merge (`crop_vehicles`)
        if track_ids not in TRACK_ID_MODES:
            raise ValueError(f"track_ids={track_ids!r} must be one of {TRACK_ID_MODES}")
        self.track_ids = track_ids
        self.associator = BoxAssociator(association)
        self.cache = CompletionCache(reuse) if reuse is not None else None
        self._vehicle_seconds = 0.0   # recent mean wall time of one vehicle's network completion (budget planning)
        self.num_input = model.config.num_input
        self.num_output = model.config.num_output
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.threads = int(threads) if self.device.type == "cpu" else 1
        self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="gd-vehicle") if self.threads > 1 else None

    @classmethod
    def from_checkpoint(
        cls, path: str | Path | None = None, *, device: str = "cpu", num_threads: int | None = None,
        min_points: int | None = None, crop_margin: float | None = None, **options
    ) -> VehicleCompleter:
        """Load a checkpoint (the shipped weights when `path` is None or empty) with its preprocessing.

        `num_threads`: CPU threads completing vehicles in parallel, one torch thread each (None or 0:
        one per core). Sets torch's intra-op threads of this process to 1. `min_points`, `crop_margin`:
        override the checkpoint's preprocessing (None keeps it).
        """
        check_device(device)
        if torch.device(device).type == "cpu":
            torch.set_num_threads(1)
        model, preprocessing = load_checkpoint(path or DEFAULT_WEIGHTS, device=device)
        overrides: dict[str, Any] = {k: v for k, v in (("min_points", min_points), ("crop_margin", crop_margin))
                                     if v is not None}
        return cls(model, preprocessing=replace(preprocessing, **overrides), device=device,
                   threads=int(num_threads or default_threads()), **options)

    @classmethod
    def from_settings(cls, settings: CompletionSettings) -> VehicleCompleter:
        """The completer of `settings` (`settings.CompletionSettings`: the node's parameters or the offline
        tools' flags). `num_threads` 0 is one per core here; the node resolves its own rule before."""
        return cls.from_checkpoint(
            settings.model_path or None, device=settings.device, num_threads=settings.num_threads or None,
            min_points=settings.min_points or None,
            crop_margin=settings.crop_margin if settings.crop_margin >= 0 else None, limits=settings.limits,
            labels=settings.labels, include_input_points=settings.include_input_points,
            measured_merge=settings.measured_merge, mirror_plane=settings.mirror_plane,
            even_spacing=settings.even_spacing,
            pool_margin=settings.pool_margin, track_ids=settings.track_ids,
            association=settings.association, reuse=settings.reuse,
            fusion=TrackFusion(settings.fusion) if settings.track_fusion else None,
            publish_fused_points=settings.publish_fused_points)

    def reset_tracks(self) -> None:
        """Forget every track (association, completion cache, fused points), keeping their settings: a new
        recording starts."""
        self.associator = BoxAssociator(self.associator.settings)
        if self.cache is not None:
            self.cache = CompletionCache(self.cache.settings)
        if self.fusion is not None:
            self.fusion = TrackFusion(self.fusion.limits)

    def warm_up(self) -> None:
        """Complete one synthetic vehicle: compiles the CPU kernels (cached on disk after the first time,
        seconds before that) so that the first real frame is not the slow one."""
        rng = np.random.default_rng(0)
        cloud = (rng.random((self.num_input + 1, 3)) - 0.5) * np.array([1.0, 0.4, 0.35])
        # merge and spacing on whatever the settings say: either may be turned on live
        self._complete_all([cloud.astype(np.float32)], [(4.5, 1.8, 1.6)], True, math.inf, None, spacing=True)
        align_planar(cloud + np.array([0.01, 0.0, 0.0]), cloud)   # track fusion's ICP kernel (fusion may be turned on)

    def close(self) -> None:
        """Stop the vehicle threads (idempotent)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def prepare(self, points: np.ndarray, boxes: Sequence[Box3D], stats: FrameStats) -> list[CroppedVehicle]:
        """Drop non-finite points, filter, validate and screen boxes (`limits.screen_boxes`), crop; the
        vehicles nearest first. Counts every skip in `stats`."""
        points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        finite = finite_mask(points)
        stats.nonfinite_points += int(len(points) - finite.sum())
        if not finite.all():
            points = points[finite]
        usable: list[Box3D] = []
        for box in boxes:
            if box.label.startswith(UNMAPPED):
                stats.unmapped_class_ids += 1
            elif box.label not in self.labels:
                stats.ignored_labels += 1
            elif box_problem(box) is not None:
                stats.skip(box, "degenerate_box")
            else:
                usable.append(box)
        kept, screened = screen_boxes(usable, self.limits)
        for i, reason in screened:
            stats.skip(usable[i], reason)
        vehicles, too_few = crop_vehicles(points, [usable[i] for i in kept], self.preprocessing, self.pool_margin)
        for box in too_few:
            stats.skip(box, "too_few_points")
        limit = self.limits.max_points_per_vehicle   # the points kept aside count too: the merge pools them
        for vehicle in (v for v in vehicles if len(v.measured) + len(v.aside) > limit):
            stats.skip(vehicle.box, "too_many_points")
        return [v for v in vehicles if len(v.measured) + len(v.aside) <= limit]

    def complete_normalized(self, partials: Sequence[np.ndarray], sizes: Sequence[Sequence[float]] | None = None,
                            asides: Sequence[np.ndarray] | None = None) -> np.ndarray:
        """Complete vehicles given in the normalised box frame, their boxes' sizes (length, width, height)
        beside them (needed by a box-conditioned model) and optionally the points their crops kept aside
        (`CroppedVehicle.aside`); returns (B, num_output, 3) float32 (with `measured_merge`, the merged points of
        `merge.merge_with_pool`)."""
        if not len(partials):
            return np.zeros((0, self.num_output, 3), np.float32)
        done = self._complete_all(partials, sizes, self.measured_merge, math.inf, None, asides=asides,
                                  spacing=self.even_spacing)
        return np.stack([result[0] for result in done if result is not None])   # no deadline: all are done

    def _complete_all(self, partials: Sequence[np.ndarray], sizes: Sequence[Sequence[float]] | None, merge: bool,
                      deadline: float, cancel: threading.Event | None, finish_by: bool = False,
                      asides: Sequence[np.ndarray] | None = None, spacing: bool = True
                      ) -> list[VehicleResult | None]:
        """Each vehicle's (completion, measured rows) in order (`_complete_one`, with `merge` and `spacing` read
        once for all of them); None for those not started before
        `deadline` (time.monotonic) or after `cancel` was set. `finish_by`: a vehicle after the first starts only
        when it is expected to finish by `deadline` (the recent mean time of one vehicle)."""
        if sizes is not None and len(sizes) != len(partials):
            raise ValueError(f"{len(partials)} partial clouds but {len(sizes)} box sizes")
        if asides is not None and len(asides) != len(partials):
            raise ValueError(f"{len(partials)} partial clouds but {len(asides)} sets of points kept aside")

        def one(item: tuple[int, np.ndarray, Sequence[float] | None, np.ndarray | None]) -> VehicleResult | None:
            index, partial, size, aside = item
            started = time.monotonic()
            expected = self._vehicle_seconds if finish_by and index > 0 else 0.0
            if started + expected > deadline or (cancel is not None and cancel.is_set()):
                return None
            result = self._complete_one(partial, size, merge, aside, spacing)
            self._vehicle_seconds += 0.2 * (time.monotonic() - started - self._vehicle_seconds)
            return result
        run = self._pool.map if self._pool is not None else map
        count = len(partials)
        return list(run(one, zip(range(count), partials, sizes if sizes is not None else [None] * count,
                                 asides if asides is not None else [None] * count)))

    def _complete_one(self, partial: np.ndarray, size: Sequence[float] | None, merge: bool,
                      aside: np.ndarray | None = None, spacing: bool = True) -> VehicleResult:
        """Resample one vehicle to the network's input size (`preprocess.network_input`) and complete it (one
        task of the thread pool): (num_output, 3) float32 points in the normalised frame (with `spacing`, the
        network's points evenly spaced: `spacing.even_spacing`) and, per point, the
        row of `partial` it copies (-1: generated); with `merge`, merged with a pool of all its measured points
        (`merge.merge_with_pool`; a single frame's crop or a track's fused partial alike, and the points kept aside
        `aside`, whose rows follow the partial's), else all generated; and the refined box's frame vector (None
        without a refiner)."""
        partial = np.asarray(partial, np.float32).reshape(-1, 3)
        rows = resample_indices(len(partial), partial, self.num_input)
        shape = box_shape([size]).to(self.device) if size is not None else None
        with torch.inference_mode():   # thread-local: set in the thread that runs the model
            out = self.model(torch.from_numpy(partial[rows]).unsqueeze(0).to(self.device), shape)
            completion = out.completion[0].float().cpu().numpy()
            graph = out.neighbours[0].cpu().numpy() if spacing else None
            frame = out.box_frame[0].double().cpu().numpy() if out.box_frame is not None else None
        if graph is not None:
            completion = even_spacing(completion, graph=graph)
        if not merge:
            return completion, np.full(len(completion), -1, np.int64), frame
        merged = merge_with_pool(completion, partial, aside=aside, size=size, plane_share=self.mirror_plane)
        return merged.points, merged.measured_row, frame

    def complete_frame(self, points: np.ndarray, boxes: Sequence[Box3D],
                       cancel: threading.Event | None = None, stamp_ns: int | None = None) -> FrameCompletion:
        """Complete the vehicles of one frame within `limits`, nearest first; points in and out are in the
        cloud's frame, vehicles in the output in the order of `boxes`. Vehicles not started when the time
        budget is spent, or once `cancel` is set, are skipped and counted (`time_budget`, `cancelled`).

        With `stamp_ns` given (a stream's frames in stamp order): the boxes get the track ids of `track_ids`
        (`association`); with `fusion` set, each tracked vehicle is completed from its track's fused partial
        (all of its frames so far, `fusion.TrackFusion`; with `publish_fused_points` its measured output points
        are the fused ones too); with `cache` set (reuse), a tracked vehicle's network completion runs only when
        due (`reuse.CompletionCache.decide`), the due ones most urgent first within `cache.settings.budget_s`,
        and every other one is published from its cache (a vehicle never completed and over the budget is
        skipped: `deferred`).

        Per vehicle the output holds its measured points (`include_input_points`; generated=0) and its
        completion's points (generated=1). With `measured_merge` the completion holds some of the measured
        points: those are published once, with generated=0 (left out of the completion when the measured
        points are published; without them, they keep this frame's measured coordinates, not those of the
        track's placement); with track fusion but without `publish_fused_points`, the completion's points from
        the track's earlier frames count as generated=1, as do a reused completion's measured points when the
        measured points are not published. The points kept aside that the merge keeps (`CroppedVehicle.aside`: tyres
        below the ground cut, the surround within `pool_margin`; never among the measured points published) stay in
        the completion with generated=0 (generated=1 in a reused completion). The settings are read once per frame."""
        stats = FrameStats()
        deadline = time.monotonic() + self.limits.time_budget_s
        include = self.include_input_points
        given = list(boxes)
        boxes = self._with_track_ids(given, stamp_ns)
        vehicles = self.prepare(points, boxes, stats)
        fusion = self.fusion if stamp_ns is not None else None
        if fusion is not None and stamp_ns is not None:
            fusion.expire(stamp_ns)
            vehicles = fusion.update(stamp_ns, vehicles, executor=self._pool)
        outputs = self._completions(vehicles, stamp_ns, deadline, cancel, stats, include)
        done = []
        budget = self.limits.max_output_points
        for vehicle, output in zip(vehicles, outputs):
            if output is None:
                continue
            completion, source, box_frame = output
            if not include:
                measured = np.zeros((0, 3), np.float32)
            elif fusion is not None and self.publish_fused_points:
                measured = fusion.fused_measured(vehicle)
            else:
                measured = vehicle.measured
            if len(measured) + len(completion) > budget:
                stats.skip(vehicle.box, "output_limit")
                continue
            budget -= len(measured) + len(completion)
            done.append((vehicle, measured, completion, source, box_frame))
        return self._assemble(boxes, done, stats, {id(b): g.instance_id for b, g in zip(boxes, given)})

    def _with_track_ids(self, boxes: Sequence[Box3D], stamp_ns: int | None) -> list[Box3D]:
        """`boxes` with the track ids of `track_ids` given to the boxes that will be completed (label and geometry
        usable); the others as they are. The track ids key fusion and reuse (both need stamps); the output keeps the
        given ids."""
        boxes = list(boxes)
        if self.track_ids == "message" or stamp_ns is None:
            return boxes
        usable = [i for i, box in enumerate(boxes) if box.label in self.labels and box_problem(box) is None]
        for i, box in zip(usable, track_identity(self.track_ids, [boxes[i] for i in usable], stamp_ns,
                                                 self.associator)):
            boxes[i] = box
        return boxes

    def _completions(self, vehicles: Sequence[CroppedVehicle], stamp_ns: int | None, deadline: float,
                     cancel: threading.Event | None, stats: FrameStats, include: bool
                     ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None] | None]:
        """Per vehicle, its completion (normalised), per point its `generated` flag and its refined box's frame
        vector, or None when it is skipped (counted in `stats`): the network's for the vehicles due (all of them
        without reuse), the cached one for the others."""
        stamp = stamp_ns if stamp_ns is not None else 0
        cache = self.cache if stamp_ns is not None else None   # reuse needs the stream's stamps
        decisions = self._decisions(vehicles, stamp, cache)
        due = [i for i, d in enumerate(decisions) if d.due]
        run_deadline = deadline
        if cache is not None:
            # never completed first (nearest first), then the most urgent, nearer ones first among equals
            due.sort(key=lambda i: (decisions[i].cached is not None,
                                    -decisions[i].urgency * _nearness(vehicles[i].box), i))
            run_deadline = min(deadline, time.monotonic() + cache.settings.budget_s)
        results = self._complete_all([vehicles[i].normalized for i in due], [vehicles[i].box.size for i in due],
                                     self.measured_merge, run_deadline, cancel,
                                     finish_by=cache is not None and math.isfinite(cache.settings.budget_s),
                                     asides=[vehicles[i].aside for i in due], spacing=self.even_spacing)
        ran = dict(zip(due, results))
        cancelled = cancel is not None and cancel.is_set()
        outputs: list[tuple[np.ndarray, np.ndarray, np.ndarray | None] | None] = []
        for i, (vehicle, decision) in enumerate(zip(vehicles, decisions)):
            result = ran.get(i)
            if result is not None:
                stats.completions_run += 1
                if cache is not None and vehicle.box.instance_id >= 0:
                    # measured: rows of the partial (a reuse publishes them afresh); the rows kept aside stay with the
                    # completion, published as generated=1 when reused (that frame's tyres, not this one's)
                    measured = (result[1] >= 0) & (result[1] < len(vehicle.normalized))
                    cache.store(vehicle.box.instance_id, stamp, vehicle.box.size, result[0], measured,
                                vehicle.normalized, result[2])
                outputs.append((*self._fresh_output(vehicle, result[0], result[1], include), result[2]))
            elif decision.cached is not None and not cancelled:
                stats.completions_reused += 1
                stats.completions_deferred += decision.due
                outputs.append((*self._cached_output(decision.cached, include), decision.cached.box_frame))
            else:
                reason = "cancelled" if cancelled else "time_budget" if time.monotonic() > deadline else "deferred"
                stats.skip(vehicle.box, reason)
                outputs.append(None)
        return outputs

    def _decisions(self, vehicles: Sequence[CroppedVehicle], stamp_ns: int,
                   cache: CompletionCache | None) -> list[Decision]:
        """Per vehicle: is its network completion due (always without a cache, a track id or for a repeated id)."""
        if cache is None:
            return [DUE_UNCACHED] * len(vehicles)
        cache.expire(stamp_ns)
        seen: set[int] = set()
        out = []
        for vehicle in vehicles:
            key = vehicle.box.instance_id
            if key < 0 or key in seen:
                out.append(DUE_UNCACHED)
                continue
            seen.add(key)
            current = vehicle.normalized if vehicle.current_rows is None \
                else vehicle.normalized[len(vehicle.normalized) - vehicle.current_rows:]
            out.append(cache.decide(key, stamp_ns, vehicle.box.size, current))
        return out

    def _fresh_output(self, vehicle: CroppedVehicle, completion: np.ndarray, row: np.ndarray, include: bool
                      ) -> tuple[np.ndarray, np.ndarray]:
        """A network completion as published: (points, generated flags), normalised by the vehicle's box."""
        # the rows of the partial that are this frame's measured points (all of them but with fusion: its last)
        own_from = 0 if self.publish_fused_points or vehicle.current_rows is None \
            else len(vehicle.normalized) - vehicle.current_rows
        aside = row >= len(vehicle.normalized)   # this frame's points kept aside: measured, never in `measured`
        own = (row >= own_from) & ~aside
        if include:   # published with the measured points
            completion, own, aside = completion[~own], own[~own], aside[~own]
        elif vehicle.current_source is not None and not self.publish_fused_points and own.any():
            # this frame's points where it measured them, not where its track placed them
            completion = completion.copy()
            completion[own] = normalize(vehicle.measured[vehicle.current_source[row[own] - own_from]], vehicle.box)
        return completion, np.where(own | aside, 0, 1).astype(np.uint8)

    def _cached_output(self, cached: CachedCompletion, include: bool) -> tuple[np.ndarray, np.ndarray]:
        """A cached completion as published: with the measured points published, its points that were measured
        above the ground cut when it was made are left out (this frame's measured points take their place; its kept
        points kept aside stay); else all of them; generated=1 (they are not this frame's measurements)."""
        points = cached.generated if include else cached.points
        return points, np.ones(len(points), np.uint8)

    def _assemble(self, boxes: Sequence[Box3D],
                  done: list[tuple[CroppedVehicle, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]],
                  stats: FrameStats, published_ids: dict[int, int]) -> FrameCompletion:
        """The frame's output: per vehicle (in the order of `boxes`) its measured points, then its completion placed
        by its box, and its refined box; `instance_id` from `published_ids` (by `id()` of the box: the id the caller
        gave it)."""
        order = {id(box): i for i, box in enumerate(boxes)}
        done.sort(key=lambda item: order.get(id(item[0].box), 0))
        parts: list[np.ndarray] = []
        ids: list[np.ndarray] = []
        labels: list[np.ndarray] = []
        flags: list[np.ndarray] = []
        refined: list[Box3D] = []
        for vehicle, measured, completion, source, box_frame in done:
            generated = denormalize(completion, vehicle.box).astype(np.float32)
            count = len(measured) + len(generated)
            parts += [measured, generated]
            published = replace(vehicle.box, instance_id=published_ids.get(id(vehicle.box), vehicle.box.instance_id))
            refined.append(box_from_frame(published, box_frame) if box_frame is not None else published)
            ids.append(np.full(count, published.instance_id, np.int32))
            labels.append(np.full(count, LABEL_IDS.get(vehicle.box.label, 0), np.uint8))
            flags += [np.zeros(len(measured), np.uint8), source]
        stats.completed = len(done)
        if not done:
            return FrameCompletion(np.zeros((0, 3), np.float32), np.zeros(0, np.int32),
                                   np.zeros(0, np.uint8), np.zeros(0, np.uint8), stats)
        return FrameCompletion(np.concatenate(parts).astype(np.float32, copy=False), np.concatenate(ids),
                               np.concatenate(labels), np.concatenate(flags), stats, refined)


def _nearness(box: Box3D) -> float:
    """Scheduling weight of a box: 1 at the sensor, 0.5 at 20 m (cloud frame origin)."""
    return 1.0 / (1.0 + math.hypot(box.center[0], box.center[1]) / 20.0)
