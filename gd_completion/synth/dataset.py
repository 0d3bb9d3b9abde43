"""Training pairs: simulated partial scans of vehicles and their complete surfaces, normalised per box."""
from __future__ import annotations

import dataclasses
import json
import multiprocessing
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gd_completion.atomic import atomic_path
from gd_completion.errors import DataFormatError
from gd_completion.geometry import Box3D, normalize
from gd_completion.preprocess import Preprocessing, crop_vehicles, network_input
from gd_completion.synth.lidar import BeamPattern, scan_meshes
from gd_completion.synth.meshio import HELDOUT_MESHES, Mesh, load_mesh_folder, sample_surface
from gd_completion.synth.vehicles import (
    BASE_KINDS,
    VEHICLE_KINDS,
    WIDE_SIZE_SPREAD,
    generate_vehicle,
    perturb_mesh,
    vehicle_label,
)

__all__ = ["GENERATOR_VERSION", "DEFAULT_PATTERNS", "SampleOptions", "V1_SAMPLING", "V2_SAMPLING", "make_sample",
           "build_dataset", "save_dataset", "load_dataset", "sample_rng"]

#: Version 2: mesh-backed data sets leave out meshio.HELDOUT_MESHES by default and SampleOptions exists;
#: procedural samples with the default options (V1_SAMPLING) are those of version 1, bit for bit.
GENERATOR_VERSION = "gd_completion.synth/2"
DEFAULT_PATTERNS = ("hdl64e", "pandar64", "pandar40p")
_SEED_TAG = 0x6D5A7E
_POINT_KEYS = ("partial", "complete")
_MESH_KEYS = ("mesh_vertices", "mesh_faces")   # build_dataset(surface_mesh=True): lists, never saved


@dataclasses.dataclass(frozen=True)
class SampleOptions:
    """What shapes a training pair beyond its size (see `make_sample`); defaults reproduce version 1 exactly.

    kinds: procedural kinds drawn (uniformly) when a shape is procedural. patterns: beam patterns drawn
    (uniformly) per sample. size_spread: widening of the kinds' size ranges (`vehicles.size_range`) and of
    the per-axis scale of mesh shapes (0.9-1.1 without spread).
    box_noise_prob: probability that the box used to crop and normalise is perturbed like a detector's:
    centre N(0, box_center_sigma) in x and y and N(0, box_z_sigma) in z (m), each size axis times
    1 + N(0, box_size_sigma), yaw + N(0, box_yaw_sigma_deg) degrees; the complete surface is normalised by
    the same noisy box and `size` is the noisy box's size (the network completes in the frame it is given).

    Sensor effects (all off by default):
    mixed_pixel_prob: probability that a return at a depth discontinuity lands between the foreground and
    background ranges (`lidar.scan_meshes`). glass_dropout: per sample a fraction drawn in [0, glass_dropout]
    of the returns of the greenhouse band (a belt line drawn at 50-70 % of the height up to 93 %; cars, vans,
    buses and mesh shapes that are not trucks) hit glass: a share glass_passthrough of them comes back from
    0.2-1.5 m behind it (the cabin), the rest is lost. patch_dropout: mean number (Poisson) of dark or
    specular panels per vehicle, discs of 0.3-0.8 m radius around a return whose returns are lost with a
    probability drawn in [0.7, 1]. range_dropout: loss probability at 50 m, growing with the square of the
    range and scaled by a per-sample darkness in [0.5, 1.5] (capped at 0.95). ground_roughness: standard
    deviation (m) of the ground returns' heights (uneven road; with a noisy box, ground returns leak into the
    crop above the ground cut). tilt_deg: standard deviation of the sensor's roll and pitch (the scene turns
    about the sensor, ground plane included; the box stays yaw-only, as a detector's).

    crop_margin_max: when above the preprocessing's crop_margin, each sample is cropped with a margin drawn
    uniformly between the two (the node's wider `crop_margin` for detector boxes: the data then holds the ends a
    noisy box cuts off and the clutter a wider crop lets in); otherwise the contract's margin, drawing nothing.
    """

    kinds: tuple[str, ...] = BASE_KINDS
    patterns: tuple[str, ...] = DEFAULT_PATTERNS
    size_spread: float = 0.0
    box_noise_prob: float = 0.0
    box_center_sigma: float = 0.15
    box_z_sigma: float = 0.05
    box_size_sigma: float = 0.05
    box_yaw_sigma_deg: float = 4.0
    mixed_pixel_prob: float = 0.0
    glass_dropout: float = 0.0
    glass_passthrough: float = 0.5
    patch_dropout: float = 0.0
    range_dropout: float = 0.0
    ground_roughness: float = 0.0
    tilt_deg: float = 0.0
    crop_margin_max: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "kinds", tuple(self.kinds))
        object.__setattr__(self, "patterns", tuple(self.patterns))
        if not self.kinds or any(k not in VEHICLE_KINDS for k in self.kinds):
            raise ValueError(f"SampleOptions.kinds: expected a non-empty subset of {VEHICLE_KINDS}, got {self.kinds}")
        if not self.patterns:
            raise ValueError("SampleOptions.patterns: need at least one beam pattern")
        for name in self.patterns:
            BeamPattern.named(name)  # fail early on a bad name
        if not 0.0 <= self.box_noise_prob <= 1.0:
            raise ValueError(f"SampleOptions.box_noise_prob must be in [0, 1], got {self.box_noise_prob}")
        if not 0.0 <= self.size_spread < 1.0:
            raise ValueError(f"SampleOptions.size_spread must be in [0, 1), got {self.size_spread}")
        for name in ("mixed_pixel_prob", "glass_dropout", "glass_passthrough", "range_dropout"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"SampleOptions.{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("patch_dropout", "ground_roughness", "tilt_deg", "box_center_sigma", "box_z_sigma",
                     "box_size_sigma", "box_yaw_sigma_deg"):
            if not 0.0 <= getattr(self, name) < 100.0:
                raise ValueError(f"SampleOptions.{name} must be non-negative, got {getattr(self, name)}")
        if not (np.isfinite(self.crop_margin_max) and 0.0 <= self.crop_margin_max <= 5.0):
            raise ValueError(f"SampleOptions.crop_margin_max must be in [0, 5] metres, got {self.crop_margin_max}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples as lists); `from_dict` reads it back. crop_margin_max is left out when off, so data
        sets made before it existed keep their cache keys."""
        data = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}
        if not data["crop_margin_max"]:
            del data["crop_margin_max"]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SampleOptions:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"SampleOptions: unknown fields {sorted(unknown)}")
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**values)


#: Generator version 1's sampling (the defaults).
V1_SAMPLING = SampleOptions()
#: Training preset of model v2: every kind, wider sizes, the evaluation's sensor families (Pandar64, PandarGT,
#: HDL-64E, 32-beam, Pandar40P), detector-box noise and every sensor effect.
V2_SAMPLING = SampleOptions(kinds=VEHICLE_KINDS,
                            patterns=("hdl64e", "pandar64", "pandar40p", "pandargt", "hdl32e", "vlp32c"),
                            size_spread=WIDE_SIZE_SPREAD, box_noise_prob=0.7, mixed_pixel_prob=0.5,
                            glass_dropout=0.6, glass_passthrough=0.5, patch_dropout=1.0, range_dropout=0.15,
                            ground_roughness=0.03, tilt_deg=1.0)


def sample_rng(seed: int, index: int) -> np.random.Generator:
    """Generator of sample `index` of a dataset with `seed` (independent of how samples are split in chunks)."""
    return np.random.default_rng(np.random.SeedSequence([_SEED_TAG, int(seed), int(index)]))


def _label_for_extent(extent: np.ndarray) -> str:
    """Detection label of a mesh from its size (for meshes without a kind)."""
    length, _, height = extent
    if length > 6.5 or height > 2.7:
        return "truck"
    return "van" if height > 1.95 else "car"


def _draw_shape(rng: np.random.Generator, shape_source: str | Mesh | Sequence[Mesh] | None,
                opts: SampleOptions) -> tuple[Mesh, str, str]:
    """(mesh centred on its bbox, kind or "mesh:<i>", label)."""
    if shape_source is None or isinstance(shape_source, str):
        kind = shape_source if shape_source not in (None, "procedural") else \
            opts.kinds[int(rng.integers(len(opts.kinds)))]
        return generate_vehicle(rng, kind, size_spread=opts.size_spread), kind, vehicle_label(kind)
    meshes = [shape_source] if isinstance(shape_source, Mesh) else list(shape_source)
    if not meshes:
        raise ValueError("make_sample: empty mesh list")
    i = int(rng.integers(len(meshes)))
    spread = opts.size_spread  # the mesh's random per-axis scale widens as the kinds' size ranges do
    mesh = perturb_mesh(meshes[i].centered(), rng, scale=(0.9 - spread, 1.1 + spread))
    return mesh, f"mesh:{i}", _label_for_extent(mesh.extent)


def _occluder(rng: np.random.Generator, dist: float, az: float) -> Mesh | None:
    """Sometimes a vehicle between the sensor and the target (partial occlusion, as in real traffic)."""
    if dist < 12 or rng.random() >= 0.2:
        return None
    occ = generate_vehicle(rng, str(rng.choice(["sedan", "hatchback", "suv"])))
    d = rng.uniform(0.3, 0.6) * dist
    a = az + rng.uniform(-1, 1) * np.arctan2(2.5, d)
    return occ.transformed(rng.uniform(-np.pi, np.pi), (d * np.cos(a), d * np.sin(a), occ.extent[2] / 2))


def _box_noise(rng: np.random.Generator, opts: SampleOptions) -> np.ndarray:
    """(7,) detector-like box error: centre offset (x, y, z; m), size factors (l, w, h), yaw offset (rad);
    identity (zeros, ones, zero) when the draw says no noise. Draws nothing with box_noise_prob 0."""
    noise = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0])
    if opts.box_noise_prob > 0 and rng.random() < opts.box_noise_prob:
        sig = np.array([opts.box_center_sigma, opts.box_center_sigma, opts.box_z_sigma])
        noise[:3] = rng.normal(0.0, 1.0, 3) * sig
        noise[3:6] = np.clip(1.0 + rng.normal(0.0, opts.box_size_sigma, 3), 0.7, 1.3)
        noise[6] = rng.normal(0.0, np.radians(opts.box_yaw_sigma_deg))
    return noise


def _tilt(rng: np.random.Generator, opts: SampleOptions) -> tuple[np.ndarray, np.ndarray]:
    """(3x3 rotation, (roll, pitch) in degrees) of a sensor rolled and pitched by N(0, tilt_deg) each."""
    angles = rng.normal(0.0, opts.tilt_deg, 2)
    roll, pitch = np.radians(angles)
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    return np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]]) @ \
        np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]]), angles


def _has_glass(kind: str, label: str) -> bool:
    return label in ("car", "van") or kind == "bus"


def _sensor_effects(points: np.ndarray, obj: np.ndarray, sensor: np.ndarray, centre: np.ndarray, height: float,
                    glass: bool, rng: np.random.Generator, opts: SampleOptions) -> np.ndarray:
    """Returns after ground roughness, glass, dark-patch and range-dependent losses (see SampleOptions); the
    target is object 0, the ground -1. Draws nothing for effects that are off."""
    pts = points.astype(np.float64)
    keep = np.ones(len(pts), bool)
    if opts.ground_roughness > 0:
        ground = obj < 0
        pts[ground, 2] += rng.normal(0.0, opts.ground_roughness, int(ground.sum()))
    target = obj == 0
    if opts.glass_dropout > 0 and glass:
        frac = rng.uniform(0.0, opts.glass_dropout)
        belt = rng.uniform(0.5, 0.7)
        h = (pts[:, 2] - (centre[2] - height / 2)) / height
        hit = target & (h > belt) & (h < 0.93) & (rng.random(len(pts)) < frac)
        through = hit & (rng.random(len(pts)) < opts.glass_passthrough)
        ray = pts[through] - sensor
        rng_ = np.linalg.norm(ray, axis=1, keepdims=True)
        pts[through] = sensor + ray * (1.0 + rng.uniform(0.2, 1.5, (len(ray), 1)) / np.maximum(rng_, 1e-9))
        keep &= ~(hit & ~through)
    if opts.patch_dropout > 0:
        tgt = np.flatnonzero(target)
        for _ in range(int(rng.poisson(opts.patch_dropout))):
            if not len(tgt):
                break
            c = pts[tgt[int(rng.integers(len(tgt)))]]
            radius, prob = rng.uniform(0.3, 0.8), rng.uniform(0.7, 1.0)
            near = target & (((pts - c) ** 2).sum(1) < radius ** 2)
            keep &= ~(near & (rng.random(len(pts)) < prob))
    if opts.range_dropout > 0:
        dark = rng.uniform(0.5, 1.5)
        r = np.linalg.norm(pts - sensor, axis=1)
        p = np.minimum(opts.range_dropout * (r / 50.0) ** 2 * np.where(target, dark, 1.0), 0.95)
        keep &= rng.random(len(pts)) >= p
    return pts[keep].astype(np.float32)


def network_partial(points: np.ndarray, box: Box3D, prep: Preprocessing, n_input: int
                    ) -> tuple[np.ndarray, int] | None:
    """(network input (n_input, 3), points kept) of a scan of one vehicle through the preprocessing contract,
    exactly as the node feeds it; None when fewer than `prep.min_points` points remain."""
    vehicles, _ = crop_vehicles(points, [box], prep)
    if not vehicles:
        return None
    return network_input(vehicles[0].normalized, n_input), len(vehicles[0].normalized)


def make_sample(rng: np.random.Generator, shape_source: str | Mesh | Sequence[Mesh] | None = None, *,
                pattern: BeamPattern | str | Sequence[str] | None = None, n_input: int = 1024,
                n_gt: int = 2048, preprocessing: Preprocessing | None = None, max_attempts: int = 60,
                surface_resample: bool = False, options: SampleOptions | None = None, surface_mesh: bool = False
                ) -> tuple[np.ndarray, np.ndarray, dict]:
    """One training pair: (partial (n_input,3), complete (n_gt,3)) float32 normalised by the vehicle's box.

    `shape_source`: None or "procedural" (random kind of `options.kinds`), a kind name, a Mesh, or a list of
    meshes (one is drawn, randomly scaled and deformed). `pattern`: a pattern, a name or names to draw from
    (default `options.patterns`). `options` (default V1_SAMPLING, generator version 1) sets the sampling and
    the sensor effects (see SampleOptions). The vehicle stands on the ground 5-50 m from a sensor 1.7-2.0 m
    high, at any azimuth and heading; the scan goes through the node's preprocessing (`gd_completion.preprocess`
    with `preprocessing`, default the contract's defaults) with the box, perturbed when the options say so.
    Poses giving fewer than its `min_points` points are re-drawn (the shape too, every 10 attempts).
    `surface_resample` adds meta["surface_resample"]: a second, independent uniform sample of the same surface
    (drawn last, so the pair is the same with or without it), whose Chamfer distance to `complete` is the
    metric's floor. `surface_mesh` adds meta["mesh_vertices"] (V,3) float32 and meta["mesh_faces"] (F,3) int32:
    the vehicle's mesh in the pair's normalised frame (no random draw: the pair is the same with or without it).
    meta["size"] is the size of the box used (noisy or not), meta["true_size"] the vehicle's,
    meta["box_noise"] the (7,) error (centre offset, size factors, yaw offset; see `_box_noise`) of the box
    against the vehicle's (centre meta["true_center"], heading meta["yaw"]); meta["tilt"] the sensor's
    (roll, pitch) in degrees; meta["sensor_heading"] the heading (deg) of a forward-facing pattern, which is
    turned towards the vehicle give or take half its field of view (so vehicles near the edge are cut);
    meta["crop_margin"] the margin the scan was cropped with (see SampleOptions.crop_margin_max).
    """
    opts = options or V1_SAMPLING
    if pattern is None:
        pattern = opts.patterns
    if isinstance(pattern, BeamPattern):
        patterns = [pattern]
    else:
        names = [pattern] if isinstance(pattern, str) else list(pattern)
        patterns = [BeamPattern.named(names[int(rng.integers(len(names)))])]
    pat = patterns[0]
    prep = preprocessing or Preprocessing()
    if opts.crop_margin_max > prep.crop_margin:
        prep = dataclasses.replace(prep, crop_margin=float(rng.uniform(prep.crop_margin, opts.crop_margin_max)))
    margin = prep.crop_margin
    for attempt in range(max_attempts):
        if attempt % 10 == 0:
            mesh, kind, label = _draw_shape(rng, shape_source, opts)
            size = mesh.extent
        dist, az, yaw = rng.uniform(5.0, 50.0), rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        sensor_h = rng.uniform(1.7, 2.0)
        centre = np.array([dist * np.cos(az), dist * np.sin(az), size[2] / 2])
        world = mesh.transformed(yaw, centre)
        occluder = _occluder(rng, dist, az)
        noise = _box_noise(rng, opts)
        box_size = size * noise[3:6]
        reach = np.linalg.norm(np.maximum(size, box_size)[:2]) / 2 + np.linalg.norm(noise[:2])
        half = np.degrees(np.arctan2(reach + margin + 0.5, dist)) if dist > 8 else 180.0
        window = (np.degrees(az) - half, np.degrees(az) + half)
        sensor = np.array([0.0, 0.0, sensor_h])
        heading = np.degrees(az) + rng.uniform(-0.5, 0.5) * pat.fov_deg if pat.fov_deg < 360 else 0.0
        scene = [world] + ([occluder] if occluder is not None else [])
        ground: dict[str, Any] = {"ground_z": 0.0}
        tilt_angles = np.zeros(2)
        if opts.tilt_deg > 0:  # the sensor rolls and pitches: the scene turns about it, the ground too
            tilt, tilt_angles = _tilt(rng, opts)
            scene = [Mesh(sensor + (m.vertices - sensor) @ tilt.T, m.faces) for m in scene]
            world = scene[0]
            centre = sensor + tilt @ (centre - sensor)
            ground = {"ground_plane": (tilt[:, 2], float(tilt[:, 2] @ sensor) - sensor_h)}
        scan = scan_meshes(scene, sensor, pat, rng, azimuth_range=window, sensor_heading_deg=heading,
                           mixed_pixel_prob=opts.mixed_pixel_prob, **ground)
        points = scan.points
        if opts.ground_roughness > 0 or opts.glass_dropout > 0 or opts.patch_dropout > 0 or opts.range_dropout > 0:
            points = _sensor_effects(points, scan.object_index, sensor, centre, float(size[2]),
                                     _has_glass(kind, label), rng, opts)
        box = Box3D(center=tuple(float(c) for c in centre + noise[:3]), size=tuple(float(s) for s in box_size),
                    yaw=float(yaw + noise[6]), label=label, instance_id=0)
        found = network_partial(points, box, prep, n_input)
        if found is not None:
            partial, n_points = found
            break
    else:
        raise RuntimeError(f"make_sample: no pose gave {prep.min_points} points in {max_attempts} attempts")
    gt = normalize(sample_surface(world, n_gt, rng), box).astype(np.float32)
    meta = {"kind": kind, "label": label, "pattern": pat.name, "n_points": n_points, "distance": float(dist),
            "azimuth": float(az), "yaw": float(yaw), "sensor_height": float(sensor_h),
            "size": box_size.astype(np.float32), "true_size": size.astype(np.float32),
            "box_noise": noise.astype(np.float32), "occluded": occluder is not None, "attempts": attempt + 1,
            "sensor_heading": float(heading), "tilt": tilt_angles.astype(np.float32),
            "true_center": centre.astype(np.float32), "crop_margin": margin}
    if surface_resample:
        meta["surface_resample"] = normalize(sample_surface(world, n_gt, rng), box).astype(np.float32)
    if surface_mesh:
        meta["mesh_vertices"] = normalize(world.vertices, box).astype(np.float32)
        meta["mesh_faces"] = world.faces.astype(np.int32)
    return partial, gt, meta


_WORKER_MESHES: dict[tuple, list[Mesh]] = {}


def _meshes(meshes_dir: str | None, exclude: tuple[str, ...] = (), only: tuple[str, ...] | None = None
            ) -> list[Mesh] | None:
    if meshes_dir is None:
        return None
    key = (meshes_dir, exclude, only)
    if key not in _WORKER_MESHES:
        meshes = load_mesh_folder(meshes_dir, exclude=exclude, only=only)
        if not meshes:
            raise DataFormatError(f"{meshes_dir}: no meshes left (exclude {list(exclude)}, only {only})")
        _WORKER_MESHES[key] = meshes
    return _WORKER_MESHES[key]


def _make_range(args: tuple) -> list[tuple[np.ndarray, np.ndarray, dict]]:
    start, stop, seed, mesh_key, n_input, n_gt, mesh_fraction, resample, prep, options, with_mesh = args
    try:  # one thread per worker: FPS runs in torch
        import torch
        torch.set_num_threads(1)
    except ImportError:
        pass
    meshes = _meshes(*mesh_key)
    opts = SampleOptions.from_dict(options)
    out = []
    for i in range(start, stop):
        rng = sample_rng(seed, i)
        source = meshes if meshes and rng.random() < mesh_fraction else None
        out.append(make_sample(rng, source, n_input=n_input, n_gt=n_gt, preprocessing=Preprocessing.from_dict(prep),
                               surface_resample=resample, options=opts, surface_mesh=with_mesh))
    return out


def build_dataset(n_samples: int, seed: int, *, meshes_dir: str | Path | None = None,
                  patterns: Sequence[str] | None = None, workers: int = 1, n_input: int = 1024,
                  n_gt: int = 2048, mesh_fraction: float = 0.3, surface_resample: bool = False,
                  preprocessing: Preprocessing | None = None, options: SampleOptions | None = None,
                  exclude_meshes: Sequence[str] | None = None, only_meshes: Sequence[str] | None = None,
                  surface_mesh: bool = False) -> dict[str, Any]:
    """`n_samples` pairs, deterministic for `seed` whatever `workers` is (sample i uses `sample_rng(seed, i)`).

    `options` (default V1_SAMPLING: generator version 1's pairs; V2_SAMPLING for training) sets the kinds,
    patterns, size spread, box noise and sensor effects; `patterns`, when given, replaces its patterns.
    With `meshes_dir`, a fraction `mesh_fraction` of the shapes come from that folder's meshes, the rest
    are procedural. The folder's meshes named (file stem) in `exclude_meshes` are left out: by default
    `meshio.HELDOUT_MESHES` (never train on the evaluation's shapes), or nothing when `only_meshes` is given
    (`only_meshes=HELDOUT_MESHES` with `mesh_fraction=1` draws every shape from the held-out meshes: the
    evaluation's held-out mesh set, `evaluation.synthetic.load_heldout_meshes`). Returns arrays `partial` (S,n_input,3),
    `complete` (S,n_gt,3) float32, `n_points`, `size` (S,3) (of the box used, noisy or not), `true_size`
    (S,3), `box_noise` (S,7), `distance`, `yaw`, `label`, `kind`, `pattern`, and a `metadata` dict holding
    everything that shaped the data (metadata["sample_options"] is `options.to_dict()`); with
    `surface_resample`, also `surface_resample` (S,n_gt,3) (see `make_sample`; the other arrays are unchanged);
    with `surface_mesh`, also lists `mesh_vertices` and `mesh_faces` of each pair's mesh in its normalised frame
    (sizes differ: lists, not arrays; `save_dataset` refuses them).
    `preprocessing` (default: the contract's defaults) is recorded in metadata["preprocessing"].
    """
    prep = preprocessing or Preprocessing()
    opts = options or V1_SAMPLING
    if patterns is not None:
        opts = dataclasses.replace(opts, patterns=tuple(patterns))
    mdir = str(meshes_dir) if meshes_dir is not None else None
    only = tuple(only_meshes) if only_meshes is not None else None
    exclude = tuple(exclude_meshes) if exclude_meshes is not None else (() if only is not None else HELDOUT_MESHES)
    mesh_key = (mdir, exclude, only)
    if mdir is not None:
        _meshes(*mesh_key)  # fail early on a bad folder
    workers = max(1, min(int(workers), n_samples or 1))
    step = max(1, -(-n_samples // (workers * 4)))
    jobs = [(s, min(s + step, n_samples), int(seed), mesh_key, n_input, n_gt, mesh_fraction,
             bool(surface_resample), prep.to_dict(), opts.to_dict(), bool(surface_mesh))
            for s in range(0, n_samples, step)]
    if workers == 1:
        chunks = [_make_range(j) for j in jobs]
    else:
        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            chunks = pool.map(_make_range, jobs)
    samples = [s for c in chunks for s in c]
    metas = [m for _, _, m in samples]
    data: dict[str, Any] = {
        "partial": np.stack([p for p, _, _ in samples]) if samples else np.zeros((0, n_input, 3), np.float32),
        "complete": np.stack([g for _, g, _ in samples]) if samples else np.zeros((0, n_gt, 3), np.float32),
        "n_points": np.array([m["n_points"] for m in metas], np.int32),
        "size": np.array([m["size"] for m in metas], np.float32).reshape(-1, 3),
        "true_size": np.array([m["true_size"] for m in metas], np.float32).reshape(-1, 3),
        "box_noise": np.array([m["box_noise"] for m in metas], np.float32).reshape(-1, 7),
        "distance": np.array([m["distance"] for m in metas], np.float32),
        "yaw": np.array([m["yaw"] for m in metas], np.float32),
        "label": np.array([m["label"] for m in metas], dtype="<U8"),
        "kind": np.array([m["kind"] for m in metas], dtype="<U16"),
        "pattern": np.array([m["pattern"] for m in metas], dtype="<U16"),
    }
    if surface_resample:
        data["surface_resample"] = (np.stack([m["surface_resample"] for m in metas]) if samples
                                    else np.zeros((0, n_gt, 3), np.float32))
    if surface_mesh:
        data["mesh_vertices"] = [m["mesh_vertices"] for m in metas]
        data["mesh_faces"] = [m["mesh_faces"] for m in metas]
    labels, counts = np.unique(data["label"], return_counts=True)
    data["metadata"] = {
        "generator_version": GENERATOR_VERSION, "seed": int(seed), "n_samples": int(n_samples),
        "n_input": int(n_input), "n_gt": int(n_gt), "patterns": list(opts.patterns),
        "meshes_dir": mdir, "mesh_fraction": float(mesh_fraction) if mdir else 0.0,
        "exclude_meshes": list(exclude) if mdir else [], "only_meshes": list(only) if mdir and only else None,
        "sample_options": opts.to_dict(),
        "label_counts": {str(k): int(v) for k, v in zip(labels, counts)},
        "normalization": "gd_completion.geometry.normalize (centre, rotate by -yaw, divide by length) by the "
                         "box used (noisy when box_noise is not the identity)",
        "preprocessing": prep.to_dict(),
    }
    return data


def save_dataset(path: str | Path, data: dict[str, Any]) -> Path:
    """Write `data` (from build_dataset) as a compressed .npz; points stored as float16, metadata as JSON."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    for key, value in data.items():
        if key == "metadata":
            continue
        if key in _MESH_KEYS:
            raise ValueError(f"save_dataset: {key!r} holds per-sample meshes, which are not stored; build the "
                             "data set without surface_mesh to save it")
        arr = np.asarray(value)
        if arr.dtype == object:
            raise ValueError(f"save_dataset: {key!r} is an object array")
        arrays[key] = arr.astype(np.float16) if key in _POINT_KEYS else arr
    meta = dict(data.get("metadata", {}))
    meta["stored_float16"] = [k for k in _POINT_KEYS if k in arrays]
    arrays["metadata_json"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as allow_pickle
    return path


def load_dataset(path: str | Path) -> dict[str, Any]:
    """Read a dataset written by save_dataset; points come back as float32, `metadata` as a dict."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            data: dict[str, Any] = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DataFormatError(f"{path}: cannot read synthetic dataset ({exc})") from exc
    if "partial" not in data or "complete" not in data or "metadata_json" not in data:
        raise DataFormatError(f"{path}: not a synthetic dataset (needs partial, complete, metadata_json)")
    try:
        data["metadata"] = json.loads(data.pop("metadata_json").tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataFormatError(f"{path}: garbled dataset metadata ({exc})") from exc
    for key in _POINT_KEYS:
        data[key] = data[key].astype(np.float32)
    return data
