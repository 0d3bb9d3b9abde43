"""Generated data sets cached on disk, keyed by everything that shapes them (`build_dataset`'s arguments, the
generator version and the meshes' contents): a run that asks for the same data set loads it."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from gd_completion.errors import DataFormatError
from gd_completion.preprocess import Preprocessing
from gd_completion.synth.dataset import (
    GENERATOR_VERSION,
    V1_SAMPLING,
    SampleOptions,
    build_dataset,
    load_dataset,
    save_dataset,
)
from gd_completion.synth.meshio import mesh_folder_digest

MESH_FRACTION = 0.3  # share of the shapes drawn from the meshes folder (the rest are procedural)


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
    """Everything that determines a generated data set (the arguments of `build_dataset` that shape it)."""

    n_samples: int
    seed: int
    n_input: int
    n_gt: int
    meshes_dir: Path | None = None
    mesh_fraction: float = MESH_FRACTION
    preprocessing: Preprocessing = Preprocessing()
    options: SampleOptions = V1_SAMPLING

    def key(self) -> dict[str, Any]:
        """JSON-ready cache key: the generator version, the settings and a digest of the meshes' files."""
        return {"generator_version": GENERATOR_VERSION, "n_samples": self.n_samples, "seed": self.seed,
                "n_input": self.n_input, "n_gt": self.n_gt, "options": self.options.to_dict(),
                "mesh_fraction": self.mesh_fraction if self.meshes_dir else 0.0,
                "meshes_digest": mesh_folder_digest(self.meshes_dir) if self.meshes_dir else None,
                "preprocessing": self.preprocessing.to_dict()}

    def build(self, workers: int) -> dict[str, Any]:
        """Generate the data set (meshes of `meshio.HELDOUT_MESHES` are never drawn)."""
        return build_dataset(self.n_samples, self.seed, meshes_dir=self.meshes_dir, workers=workers,
                             n_input=self.n_input, n_gt=self.n_gt, mesh_fraction=self.mesh_fraction,
                             preprocessing=self.preprocessing, options=self.options)


def cached_dataset(cache_dir: Path, prefix: str, spec: DatasetSpec, workers: int) -> dict[str, Any]:
    """The data set of `spec`: loaded from `cache_dir` when a file there holds the same key, else generated and
    saved as `<prefix>_<n>_s<seed>_<digest of the key>.npz` with the key in its metadata."""
    key = spec.key()
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    path = cache_dir / f"{prefix}_{spec.n_samples}_s{spec.seed}_{digest}.npz"
    if path.is_file():
        try:
            data = load_dataset(path)
        except DataFormatError as error:
            logging.warning("regenerating the data set: %s", error)
        else:
            if data["metadata"].get("cache_key") == key:
                logging.info("loaded %d cached samples from %s", spec.n_samples, path)
                return data
            logging.warning("regenerating %s: it was made with other settings", path)
    started = time.perf_counter()
    data = spec.build(workers)
    elapsed = time.perf_counter() - started
    logging.info("generated %d samples in %.0f s (%.1f samples/s)", spec.n_samples, elapsed,
                 spec.n_samples / max(elapsed, 1e-9))
    data["metadata"]["cache_key"] = key
    save_dataset(path, data)
    return data
