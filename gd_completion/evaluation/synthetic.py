"""Held-out synthetic benchmark: every baseline against complete ground truth, and the control-point ablation."""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from torch import Tensor

from gd_completion.errors import DataFormatError, EvaluationError
from gd_completion.model.checkpoint import load_model
from gd_completion.model.network import GGDNet
from gd_completion.synth.dataset import build_dataset, load_dataset

from .baselines import BASELINE_NAMES, mirror_symmetry, network_outputs, published_outputs
from .mesh_distance import distances_to_meshes, surface_shares
from .metrics import (
    CD_SCALE,
    FIDELITY_SCALE,
    f_score_of,
    fidelity,
    nearest_sq_distance,
    observed_mask,
    region_means,
)
from .priors import box_fill, template_points, thinned_union

# Seeds from EVAL_SEED up are reserved for evaluation; training sets must use seeds below it.
EVAL_SEED = 9_000_000
SYNTHETIC_METRICS: tuple[str, ...] = ("cd", "cd_dg", "cd_gd", "f_score", "fidelity", "cd_gd_observed",
                                      "cd_gd_unobserved", "on_surface", "far")


@dataclass
class SyntheticResult:
    """Mean metrics per baseline (CD, CD(D,G), CD(G,D) x1e4; fidelity x1e3) on `n_samples` held-out pairs;
    CD(G,D) also split into observed / unobserved ground truth (`completeness_by_region`); on_surface and far:
    shares of output points within `NEAR_SURFACE` of the true mesh and beyond `FAR_FROM_SURFACE` (NaN without
    the meshes)."""

    n_samples: int
    seed: int | None
    source: str
    metrics: dict[str, dict[str, float]]
    seconds: float
    examples: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    points: dict[str, int] = field(default_factory=dict)  # output points per baseline
    n_gt: int = 0
    observed_fraction: float = float("nan")
    floor: dict[str, float] | None = None   # CD of the resampled true surface: what a perfect completion scores


class HeldOut(NamedTuple):
    """Held-out pairs; `surface` is a second uniform sample of each true surface (None when not available);
    `sizes` (S, 3) the boxes' (length, width, height) in metres, which normalised each pair; `meshes` each
    pair's true surface, (vertices (V, 3), faces (F, 3)) in its normalised frame (None when not available);
    `mesh_names` each pair's mesh (its file stem; None when the shapes are not meshes of a folder)."""

    partial: np.ndarray
    complete: np.ndarray
    source: str
    surface: np.ndarray | None = None
    sizes: np.ndarray | None = None
    meshes: list[tuple[np.ndarray, np.ndarray]] | None = None
    mesh_names: tuple[str, ...] | None = None


@dataclass
class AblationRow:
    """Control-point ablation entry: one checkpoint's N_c and directional Chamfer (x1e4) of its completion."""

    checkpoint: str
    num_control: int
    cd_dg: float
    cd_gd: float
    cd_generation: float = float("nan")   # CD x1e4 of the same checkpoint's generation-only branch

    @property
    def cd(self) -> float:
        return self.cd_dg + self.cd_gd


def _pairs(data: dict[str, Any], where: str) -> tuple[np.ndarray, np.ndarray]:
    """(partial (S,N,3), complete (S,M,3)) float32 of a synth dataset dict, shapes checked."""
    partial, complete = np.asarray(data["partial"], np.float32), np.asarray(data["complete"], np.float32)
    if partial.ndim != 3 or complete.ndim != 3 or partial.shape[-1] != 3 or complete.shape[-1] != 3 \
            or len(partial) != len(complete):
        raise EvaluationError(f"{where}: partial {partial.shape} and complete {complete.shape} are not "
                              f"matching (S, N, 3) arrays")
    return partial, complete


def _sizes(data: dict[str, Any], count: int, where: str) -> np.ndarray:
    """The per-sample box sizes (S, 3) of a synth dataset dict (its `size` array); never guessed."""
    if "size" not in data:
        raise EvaluationError(f"{where}: no per-sample box sizes ('size'): box-conditioned models and the box "
                              "priors need them; rebuild the set with gd_completion.synth")
    sizes = np.asarray(data["size"], np.float64).reshape(-1, 3)
    if len(sizes) < count:
        raise EvaluationError(f"{where}: {len(sizes)} box sizes for {count} pairs")
    return sizes[:count]


def _pair_meshes(data: dict[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each pair's (vertices, faces) of a `build_dataset(surface_mesh=True)` dict."""
    return list(zip(data["mesh_vertices"], data["mesh_faces"]))


def load_heldout(n_samples: int, *, seed: int = EVAL_SEED, mesh_dir: str | Path | None = None,
                 path: str | Path | None = None) -> HeldOut:
    """Held-out pairs: `load_dataset(path)` when `path` is given (no meshes), else `build_dataset(n_samples,
    seed, surface_resample=True, surface_mesh=True)` on a seed reserved for evaluation (with the mesh folder
    `mesh_dir`)."""
    if path is not None:
        data = load_dataset(Path(path))
        partial, complete = _pairs(data, str(path))
        surface = data.get("surface_resample")
        n = min(n_samples, len(partial))
        return HeldOut(partial[:n], complete[:n], f"{path} (first {n})",
                       None if surface is None else np.asarray(surface, np.float32)[:n], _sizes(data, n, str(path)))
    if mesh_dir is not None and not Path(mesh_dir).is_dir():
        raise EvaluationError(f"held-out mesh folder {mesh_dir}: not a directory")
    data = build_dataset(n_samples, seed, meshes_dir=mesh_dir, surface_resample=True, surface_mesh=True)
    partial, complete = _pairs(data, "build_dataset")
    where = f"build_dataset(seed={seed}" + (f", meshes {mesh_dir})" if mesh_dir else ", generated shapes)")
    return HeldOut(partial, complete, where, np.asarray(data["surface_resample"], np.float32),
                   _sizes(data, len(partial), where), _pair_meshes(data))


def load_heldout_meshes(n_samples: int, mesh_dir: str | Path, *, seed: int = EVAL_SEED) -> HeldOut:
    """Pairs made from the held-out meshes only (`synth.meshio.HELDOUT_MESHES` of `mesh_dir`, never trained
    on): `build_dataset` with every shape drawn from those meshes."""
    from gd_completion.synth.meshio import HELDOUT_MESHES

    return load_mesh_pairs(n_samples, mesh_dir, HELDOUT_MESHES, seed=seed, what="held-out")


def load_mesh_pairs(n_samples: int, mesh_dir: str | Path, names: Sequence[str], *, seed: int = EVAL_SEED,
                    what: str = "named") -> HeldOut:
    """Pairs made from the meshes `names` (file stems) of `mesh_dir` only, every one of them found there:
    `build_dataset` with every shape drawn from those meshes (`what` names them in errors and in the source)."""
    from gd_completion.synth.meshio import mesh_files

    names = tuple(names)
    if not Path(mesh_dir).is_dir():
        raise EvaluationError(f"mesh folder {mesh_dir}: not a directory")
    try:   # counted by file name: build_dataset reads them (once)
        found = sum(path.stem in names for path in mesh_files(mesh_dir))
        if found != len(names):
            raise EvaluationError(f"{mesh_dir}: {found} of the {len(names)} {what} meshes found")
        if n_samples < 1:
            raise EvaluationError(f"no {what} mesh samples requested")
        data = build_dataset(n_samples, seed, meshes_dir=mesh_dir, mesh_fraction=1.0, only_meshes=names,
                             surface_resample=True, surface_mesh=True)
    except DataFormatError as exc:   # an unreadable mesh
        raise EvaluationError(f"{what} meshes: {exc}") from exc
    partial, complete = _pairs(data, "build_dataset")
    where = f"the {found} {what} meshes of {Path(mesh_dir).name} ({', '.join(names)}), seed {seed}"
    stems = [path.stem for path in mesh_files(mesh_dir) if path.stem in names]   # kind "mesh:<i>": the i-th
    mesh_names = tuple(stems[int(kind.removeprefix("mesh:"))] for kind in data["kind"])
    return HeldOut(partial, complete, where, np.asarray(data["surface_resample"], np.float32),
                   _sizes(data, len(partial), where), _pair_meshes(data), mesh_names)


def _chamfer_row(output: np.ndarray, complete: np.ndarray) -> tuple[dict[str, float], Tensor]:
    """{cd, cd_dg, cd_gd} x1e4 and F-score@1% averaged over the pairs, and the per-point ground truth -> output
    distances."""
    to_truth, to_output = nearest_sq_distance(output, complete), nearest_sq_distance(complete, output)
    dg, gd = to_truth.mean(-1), to_output.mean(-1)
    return {"cd": float((dg + gd).mean()) * CD_SCALE, "cd_dg": float(dg.mean()) * CD_SCALE,
            "cd_gd": float(gd.mean()) * CD_SCALE,
            "f_score": float(f_score_of(to_truth, to_output).mean())}, to_output


def _mesh_shares(clouds: dict[str, np.ndarray], meshes: Sequence[tuple[np.ndarray, np.ndarray]] | None,
                 count: int) -> dict[str, dict[str, float]]:
    """{name: {on_surface, far}} of each cloud set (S, N, 3) against the pairs' meshes (NaN without them)."""
    if meshes is None:
        return {name: {"on_surface": float("nan"), "far": float("nan")} for name in clouds}
    if len(meshes) != count:
        raise EvaluationError(f"{len(meshes)} true meshes for {count} pairs")
    names = list(clouds)
    distances = distances_to_meshes([clouds[n] for n in names], [v for v, _ in meshes], [f for _, f in meshes])
    return {n: dict(zip(("on_surface", "far"), surface_shares(d))) for n, d in zip(names, distances)}


def evaluate_synthetic(model: GGDNet, partial: np.ndarray, complete: np.ndarray, sizes: np.ndarray, *,
                       seed: int | None = None, source: str = "", max_batch: int = 32, n_examples: int = 4,
                       surface: np.ndarray | None = None,
                       meshes: Sequence[tuple[np.ndarray, np.ndarray]] | None = None) -> SyntheticResult:
    """CD, CD(D,G), CD(G,D) (x1e4) and Fidelity (x1e3) of every method, averaged over the pairs; `sizes`
    (S, 3): each pair's box (length, width, height), given to the network and the box priors. With `surface`
    (a second sample of each true surface), also the metric floor `SyntheticResult.floor`. With `meshes` (each
    pair's true mesh, (vertices, faces) in its normalised frame), the shares of output points on the surface
    and far from it (`mesh_distance.surface_shares`; the raw input's are its points'), else NaN."""
    t0 = time.perf_counter()
    partial = np.asarray(partial, np.float32)
    complete = np.asarray(complete, np.float32)
    sizes = np.asarray(sizes, np.float64).reshape(-1, 3)
    networks = published_outputs(model, list(partial), sizes, max_batch=max_batch)
    completion = networks.completion
    n_out = model.config.num_output
    mirror, template = mirror_symmetry(partial), template_points(sizes, n_out)
    outputs = {"input": partial, "mirror": mirror, "box_fill": box_fill(sizes, n_out), "template": template,
               "mirror_template": np.stack([thinned_union([m, t], n_out) for m, t in zip(mirror, template)])
               if len(partial) else np.zeros((0, n_out, 3), np.float32),
               "generation": networks.generated, "ggd_raw": networks.raw, "ggd": completion,
               "ggd_merge": networks.published}
    result: dict[str, dict[str, float]] = {}
    observed = observed_mask(complete, partial)
    observed_fraction = float("nan")
    for name in BASELINE_NAMES:
        out = outputs[name]
        row, gt_to_output = _chamfer_row(out, complete)
        seen, unseen, observed_fraction = region_means(gt_to_output, observed)
        result[name] = {**row, "fidelity": float(fidelity(partial, out).mean()) * FIDELITY_SCALE,
                        "cd_gd_observed": seen * CD_SCALE, "cd_gd_unobserved": unseen * CD_SCALE}
    clouds = {name: outputs[name] for name in BASELINE_NAMES}
    if surface is not None:
        clouds["(floor)"] = np.asarray(surface, np.float32)
    shares = _mesh_shares(clouds, meshes, len(partial))
    for name in BASELINE_NAMES:
        result[name].update(shares[name])
    floor = {**_chamfer_row(clouds["(floor)"], complete)[0], **shares["(floor)"]} if surface is not None else None
    examples = [(f"synthetic #{i}", partial[i], completion[i], complete[i])
                for i in range(min(n_examples, len(partial)))]
    return SyntheticResult(len(partial), seed, source, result, time.perf_counter() - t0, examples,
                           {name: int(out.shape[1]) for name, out in outputs.items()}, int(complete.shape[1]),
                           observed_fraction, floor)


def control_point_ablation(checkpoints: Sequence[str | Path], partial: np.ndarray, complete: np.ndarray,
                           sizes: np.ndarray, *, max_batch: int = 32) -> list[AblationRow]:
    """CD(D,G) and CD(G,D) (x1e4) of the GGD-Net completion of each checkpoint (e.g. N_c = 128, 256, 512),
    and the CD of its generation-only branch."""
    rows = []
    for path in checkpoints:
        model = load_model(path)
        generated, completion = network_outputs(model, partial, sizes, max_batch=max_batch)
        ggd = _chamfer_row(completion, np.asarray(complete, np.float32))[0]
        gen = _chamfer_row(generated, np.asarray(complete, np.float32))[0]
        rows.append(AblationRow(str(path), model.config.num_control, ggd["cd_dg"], ggd["cd_gd"], gen["cd"]))
    return sorted(rows, key=lambda r: r.num_control)
