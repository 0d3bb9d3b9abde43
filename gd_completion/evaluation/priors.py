"""Box-only completion priors (no learning), in the normalised box frame (centre, -yaw, divided by the length).

- `box_fill`: points uniform in the box volume (no input at all);
- `template_points`: a fixed procedural sedan fitted to the box size, sampled on its surface (no input);
- `mirror_template`: the mirror baseline together with the template, thinned to the output count by farthest
  point sampling (`thinned_union`, `preprocess.resample_indices`: deterministic, no seed).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from gd_completion.sampling import resample_indices

PRIOR_POINTS = 2048
BOX_FILL_SEED = 1
TEMPLATE_SEED = 0          # generate_vehicle(default_rng(TEMPLATE_SEED), TEMPLATE_KIND)
TEMPLATE_SAMPLE_SEED = 1   # surface sampling of the fitted template
TEMPLATE_KIND = "sedan"


def _sizes(sizes: np.ndarray) -> np.ndarray:
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    if np.any(~np.isfinite(sizes)) or np.any(sizes <= 0):
        raise ValueError("box sizes (length, width, height) must be finite and positive")
    return sizes


def box_fill(sizes: np.ndarray, n: int = PRIOR_POINTS, seed: int = BOX_FILL_SEED) -> np.ndarray:
    """(B, n, 3) float32: `n` points uniform in each box (sizes (B, 3) = length, width, height in metres),
    normalised by its length; the same unit draw (seeded) scaled to every box."""
    sizes = _sizes(sizes)
    unit = np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 3))
    return (unit[None] * (sizes / sizes[:, :1])[:, None, :]).astype(np.float32)


@lru_cache(maxsize=1)
def _template_mesh():
    from gd_completion.synth.vehicles import generate_vehicle

    return generate_vehicle(np.random.default_rng(TEMPLATE_SEED), TEMPLATE_KIND).centered()


@lru_cache(maxsize=4096)
def _template_cached(size: tuple[float, float, float], n: int, seed: int) -> np.ndarray:
    from gd_completion.synth.meshio import sample_surface
    from gd_completion.synth.vehicles import fit_to_size

    mesh = fit_to_size(_template_mesh(), np.array(size))
    points = sample_surface(mesh, n, np.random.default_rng(seed))
    return (points / size[0]).astype(np.float32)


def template_points(sizes: np.ndarray, n: int = PRIOR_POINTS, seed: int = TEMPLATE_SAMPLE_SEED) -> np.ndarray:
    """(B, n, 3) float32: the fixed procedural sedan (`generate_vehicle(default_rng(TEMPLATE_SEED), "sedan")`)
    fitted to each box size (`fit_to_size`, centred on the box), `n` surface points sampled with `seed`,
    normalised by the length."""
    sizes = _sizes(sizes)
    if len(sizes) == 0:
        return np.zeros((0, n, 3), np.float32)
    return np.stack([_template_cached(tuple(float(v) for v in s), n, seed) for s in sizes])


def thinned_union(clouds: list[np.ndarray], n: int = PRIOR_POINTS) -> np.ndarray:
    """(n, 3) float32: the union of `clouds` thinned to `n` points by farthest point sampling (deterministic;
    repeated cyclically when the union has fewer than `n` points)."""
    union = np.concatenate([np.asarray(c, np.float32).reshape(-1, 3) for c in clouds])
    return union[resample_indices(len(union), union, n)]


def mirror_template(partial: np.ndarray, size: np.ndarray, n: int = PRIOR_POINTS,
                    template: np.ndarray | None = None) -> np.ndarray:
    """(n, 3): the "mirror + template" prior of one vehicle, its normalised `partial` (M, 3) and its mirror image
    with the template fitted to its box `size` (3,) (`template`: that template's points, when already sampled),
    thinned to `n` points."""
    from .baselines import mirror_symmetry

    template = template_points(size, n)[0] if template is None else template
    return thinned_union([mirror_symmetry(partial), template], n)


def prior_outputs(partial: np.ndarray, size: np.ndarray, n: int = PRIOR_POINTS) -> dict[str, np.ndarray]:
    """The three box-only priors of one vehicle: its normalised `partial` (M, 3), its box `size` (3,)."""
    fill, template = box_fill(size, n)[0], template_points(size, n)[0]
    return {"box_fill": fill, "template": template, "mirror_template": mirror_template(partial, size, n, template)}
