"""Training pairs: simulated partial scans of vehicles and their complete surfaces, normalised per box."""
from __future__ import annotations

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
from gd_completion.synth.meshio import Mesh, load_mesh_folder, sample_surface
from gd_completion.synth.vehicles import VEHICLE_KINDS, generate_vehicle, perturb_mesh, vehicle_label

__all__ = ["GENERATOR_VERSION", "DEFAULT_PATTERNS", "make_sample", "build_dataset", "save_dataset", "load_dataset",
           "sample_rng"]

GENERATOR_VERSION = "gd_completion.synth/1"
DEFAULT_PATTERNS = ("hdl64e", "pandar64", "pandar40p")
_SEED_TAG = 0x6D5A7E
_POINT_KEYS = ("partial", "complete")


def sample_rng(seed: int, index: int) -> np.random.Generator:
    """Generator of sample `index` of a dataset with `seed` (independent of how samples are split in chunks)."""
    return np.random.default_rng(np.random.SeedSequence([_SEED_TAG, int(seed), int(index)]))


def _label_for_extent(extent: np.ndarray) -> str:
    """Detection label of a mesh from its size (for meshes without a kind)."""
    length, _, height = extent
    if length > 6.5 or height > 2.7:
        return "truck"
    return "van" if height > 1.95 else "car"


def _draw_shape(rng: np.random.Generator, shape_source: str | Mesh | Sequence[Mesh] | None) -> tuple[Mesh, str, str]:
    """(mesh centred on its bbox, kind or "mesh:<i>", label)."""
    if shape_source is None or isinstance(shape_source, str):
        kind = shape_source if shape_source not in (None, "procedural") else \
            VEHICLE_KINDS[int(rng.integers(len(VEHICLE_KINDS)))]
        return generate_vehicle(rng, kind), kind, vehicle_label(kind)
    meshes = [shape_source] if isinstance(shape_source, Mesh) else list(shape_source)
    if not meshes:
        raise ValueError("make_sample: empty mesh list")
    i = int(rng.integers(len(meshes)))
    mesh = perturb_mesh(meshes[i].centered(), rng)
    return mesh, f"mesh:{i}", _label_for_extent(mesh.extent)


def _occluder(rng: np.random.Generator, dist: float, az: float) -> Mesh | None:
    """Sometimes a vehicle between the sensor and the target (partial occlusion, as in real traffic)."""
    if dist < 12 or rng.random() >= 0.2:
        return None
    occ = generate_vehicle(rng, str(rng.choice(["sedan", "hatchback", "suv"])))
    d = rng.uniform(0.3, 0.6) * dist
    a = az + rng.uniform(-1, 1) * np.arctan2(2.5, d)
    return occ.transformed(rng.uniform(-np.pi, np.pi), (d * np.cos(a), d * np.sin(a), occ.extent[2] / 2))


def network_partial(points: np.ndarray, box: Box3D, prep: Preprocessing, n_input: int
                    ) -> tuple[np.ndarray, int] | None:
    """(network input (n_input, 3), points kept) of a scan of one vehicle through the preprocessing contract,
    exactly as the node feeds it; None when fewer than `prep.min_points` points remain."""
    vehicles, _ = crop_vehicles(points, [box], prep)
    if not vehicles:
        return None
    return network_input(vehicles[0].normalized, n_input), len(vehicles[0].normalized)


def make_sample(rng: np.random.Generator, shape_source: str | Mesh | Sequence[Mesh] | None = None, *,
                pattern: BeamPattern | str | Sequence[str] = DEFAULT_PATTERNS, n_input: int = 1024,
                n_gt: int = 2048, preprocessing: Preprocessing | None = None, max_attempts: int = 60,
                surface_resample: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
    """One training pair: (partial (n_input,3), complete (n_gt,3)) float32 normalised by the vehicle's box.

    `shape_source`: None or "procedural" (random kind), a kind name, a Mesh, or a list of meshes (one is
    drawn, randomly scaled and deformed). The vehicle stands on the ground 5-50 m from a sensor 1.7-2.0 m
    high, at any azimuth and heading; the scan goes through the node's preprocessing (`gd_completion.preprocess`
    with `preprocessing`, default the contract's defaults). Poses giving fewer than its `min_points` points
    are re-drawn (the shape too, every 10 attempts). `surface_resample` adds
    meta["surface_resample"]: a second, independent uniform sample of the same surface (drawn last, so the
    pair is the same with or without it), whose Chamfer distance to `complete` is the metric's floor.
    """
    if isinstance(pattern, BeamPattern):
        patterns = [pattern]
    else:
        names = [pattern] if isinstance(pattern, str) else list(pattern)
        patterns = [BeamPattern.named(names[int(rng.integers(len(names)))])]
    pat = patterns[0]
    prep = preprocessing or Preprocessing()
    margin = prep.crop_margin
    for attempt in range(max_attempts):
        if attempt % 10 == 0:
            mesh, kind, label = _draw_shape(rng, shape_source)
            size = mesh.extent
        dist, az, yaw = rng.uniform(5.0, 50.0), rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        sensor_h = rng.uniform(1.7, 2.0)
        centre = np.array([dist * np.cos(az), dist * np.sin(az), size[2] / 2])
        world = mesh.transformed(yaw, centre)
        occluder = _occluder(rng, dist, az)
        half = np.degrees(np.arctan2(np.linalg.norm(size[:2]) / 2 + margin + 0.5, dist)) if dist > 8 else 180.0
        window = (np.degrees(az) - half, np.degrees(az) + half)
        scan = scan_meshes([world] + ([occluder] if occluder is not None else []), (0.0, 0.0, sensor_h), pat, rng,
                           azimuth_range=window, ground_z=0.0)
        box = Box3D(center=tuple(float(c) for c in centre), size=tuple(float(s) for s in size),
                    yaw=float(yaw), label=label, instance_id=0)
        found = network_partial(scan.points, box, prep, n_input)
        if found is not None:
            partial, n_points = found
            break
    else:
        raise RuntimeError(f"make_sample: no pose gave {prep.min_points} points in {max_attempts} attempts")
    gt = normalize(sample_surface(world, n_gt, rng), box).astype(np.float32)
    meta = {"kind": kind, "label": label, "pattern": pat.name, "n_points": n_points, "distance": float(dist),
            "azimuth": float(az), "yaw": float(yaw), "sensor_height": float(sensor_h), "size": size.astype(np.float32),
            "occluded": occluder is not None, "attempts": attempt + 1}
    if surface_resample:
        meta["surface_resample"] = normalize(sample_surface(world, n_gt, rng), box).astype(np.float32)
    return partial, gt, meta


_WORKER_MESHES: dict[str, list[Mesh]] = {}


def _meshes(meshes_dir: str | None) -> list[Mesh] | None:
    if meshes_dir is None:
        return None
    if meshes_dir not in _WORKER_MESHES:
        _WORKER_MESHES[meshes_dir] = load_mesh_folder(meshes_dir)
    return _WORKER_MESHES[meshes_dir]


def _make_range(args: tuple) -> list[tuple[np.ndarray, np.ndarray, dict]]:
    start, stop, seed, meshes_dir, patterns, n_input, n_gt, mesh_fraction, resample, prep = args
    try:  # one thread per worker: FPS runs in torch
        import torch
        torch.set_num_threads(1)
    except ImportError:
        pass
    meshes = _meshes(meshes_dir)
    out = []
    for i in range(start, stop):
        rng = sample_rng(seed, i)
        source = meshes if meshes and rng.random() < mesh_fraction else None
        out.append(make_sample(rng, source, pattern=patterns, n_input=n_input, n_gt=n_gt,
                               preprocessing=Preprocessing.from_dict(prep), surface_resample=resample))
    return out


def build_dataset(n_samples: int, seed: int, *, meshes_dir: str | Path | None = None,
                  patterns: Sequence[str] = DEFAULT_PATTERNS, workers: int = 1, n_input: int = 1024,
                  n_gt: int = 2048, mesh_fraction: float = 0.3, surface_resample: bool = False,
                  preprocessing: Preprocessing | None = None) -> dict[str, Any]:
    """`n_samples` pairs, deterministic for `seed` whatever `workers` is (sample i uses `sample_rng(seed, i)`).

    With `meshes_dir`, a fraction `mesh_fraction` of the shapes come from that folder's meshes, the rest
    are procedural. Returns arrays `partial` (S,n_input,3), `complete` (S,n_gt,3) float32, `n_points`,
    `size` (S,3), `distance`, `yaw`, `label`, `kind`, `pattern`, and a `metadata` dict; with
    `surface_resample`, also `surface_resample` (S,n_gt,3) (see `make_sample`; the other arrays are unchanged).
    `preprocessing` (default: the contract's defaults) is recorded in metadata["preprocessing"].
    """
    prep = preprocessing or Preprocessing()
    patterns = tuple(patterns)
    for name in patterns:
        BeamPattern.named(name)  # fail early on a bad name
    mdir = str(meshes_dir) if meshes_dir is not None else None
    if mdir is not None:
        _meshes(mdir)  # fail early on a bad folder
    workers = max(1, min(int(workers), n_samples or 1))
    step = max(1, -(-n_samples // (workers * 4)))
    jobs = [(s, min(s + step, n_samples), int(seed), mdir, patterns, n_input, n_gt, mesh_fraction,
             bool(surface_resample), prep.to_dict()) for s in range(0, n_samples, step)]
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
        "distance": np.array([m["distance"] for m in metas], np.float32),
        "yaw": np.array([m["yaw"] for m in metas], np.float32),
        "label": np.array([m["label"] for m in metas], dtype="<U8"),
        "kind": np.array([m["kind"] for m in metas], dtype="<U16"),
        "pattern": np.array([m["pattern"] for m in metas], dtype="<U16"),
    }
    if surface_resample:
        data["surface_resample"] = (np.stack([m["surface_resample"] for m in metas]) if samples
                                    else np.zeros((0, n_gt, 3), np.float32))
    labels, counts = np.unique(data["label"], return_counts=True)
    data["metadata"] = {
        "generator_version": GENERATOR_VERSION, "seed": int(seed), "n_samples": int(n_samples),
        "n_input": int(n_input), "n_gt": int(n_gt), "patterns": list(patterns),
        "meshes_dir": mdir, "mesh_fraction": float(mesh_fraction) if mdir else 0.0,
        "label_counts": {str(k): int(v) for k, v in zip(labels, counts)},
        "normalization": "gd_completion.geometry.normalize (centre, rotate by -yaw, divide by length)",
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
        arr = np.asarray(value)
        if arr.dtype == object:
            raise ValueError(f"save_dataset: {key!r} is an object array")
        arrays[key] = arr.astype(np.float16) if key in _POINT_KEYS else arr
    meta = dict(data.get("metadata", {}))
    meta["stored_float16"] = [k for k in _POINT_KEYS if k in arrays]
    arrays["metadata_json"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
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
