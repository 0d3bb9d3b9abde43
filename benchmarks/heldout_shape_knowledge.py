"""How much of issue 32's point 3 the training meshes can give at all: the held-out meshes' published output with its
network points moved onto the nearest *training* shape instead of the true mesh.

For each held-out pair (the evaluation's, `evaluation.synthetic.load_heldout_meshes`), every one of the 12 training
meshes (`synth.meshio.load_mesh_folder` without HELDOUT_MESHES) is made into candidates the way the data set makes
its shapes: deformed (`synth.vehicles.bend_taper_lean`, each of its three amounts on the grid GRID, the data set's
range), stretched to the pair's true box (`fit_to_size`: the exact box, as the network is given it) and turned end
for end or not. The candidate whose CANDIDATE_POINTS points (area-weighted on the undeformed mesh, carried along by
the deformation) lie nearest the true mesh (CHOICE_SAMPLES points of it) on average is the pair's *oracle shape*. It
is chosen with the truth, so it is more than a network could know: an optimistic bound on completing a held-out
vehicle from knowledge of the training meshes and their deformations alone. The *input's shape* is the candidate
chosen without the truth: the one whose CANDIDATE_POINTS points lie nearest, on average, to the pair's measured
points and their mirror image (y -> -y), what a retrieval from the scan could pick.

Printed: the oracle shapes' and the input's shapes' distance to the true meshes (mean, share within 1 % and 2 % of
the length) and which training mesh each held-out mesh takes; then, as `benchmarks/heldout_oracles.py` prints them
(CD, CD(D,G) x1e4, F-score@1 % (precision / recall), share within 2 % of the true mesh):

- `published`: the shipped pipeline's output;
- `network points onto oracle shape`: each network point (the merge took it from the completion) moved onto its
  nearest of SNAP_POINTS points of the pair's oracle shape, the measured and mirrored points kept;
- `network points onto input's shape`: the same onto the input's shape;
- `network points onto true mesh`: the same onto the true mesh (`heldout_oracles.py`'s 100 % row).

`--pandaset DIR` first prints PandaSet-002's reduced protocol (`benchmarks/spacing_variants.py`'s: coverage x1e3,
overall and per input-size bucket, of the network's spaced points and of the published output), shipped and with
every network point moved onto the input's shape (chosen for the box given, exact) before the merge, the mirror +
template prior beside them: whether a shape from the training meshes helps on real vehicles too.

`--pairs seen-meshes` scores the training meshes' own pairs instead (`heldout_oracles.seen_mesh_pairs`), where the
true mesh is among the candidates (its exact deformation is not, only the grid's nearest): what is left there is the
grid's coarseness.

    python benchmarks/heldout_shape_knowledge.py [--model PT] [--meshes DIR] [--heldout N] [--pairs heldout]
        [--pandaset DIR]
"""
from __future__ import annotations

import argparse
import itertools
from collections import Counter
from collections.abc import Callable

import numpy as np
import torch
import trimesh
from heldout_oracles import SNAP_SAMPLES, network_points, score, seen_mesh_pairs
from scipy.spatial import cKDTree
from spacing_variants import by_bucket

from gd_completion.evaluation import pandaset_eval as pe
from gd_completion.evaluation.baselines import network_forward, published_outputs
from gd_completion.evaluation.nearest import nearest_sq
from gd_completion.evaluation.priors import prior_outputs
from gd_completion.evaluation.synthetic import load_heldout_meshes
from gd_completion.merge import merge_with_pool
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.network import GGDNet
from gd_completion.preprocess import with_aside
from gd_completion.spacing import SHIPPED_SPACING, even_spacing
from gd_completion.synth.meshio import HELDOUT_MESHES, Mesh, load_mesh_folder, mesh_files
from gd_completion.synth.vehicles import bend_taper_lean, fit_to_size

GRID = (-0.02, 0.0, 0.02)   # each deformation amount (perturb_mesh's deform=0.02 draws them in [-0.02, 0.02])
CANDIDATE_POINTS = 1_000    # points per candidate when choosing the oracle shape
CHOICE_SAMPLES = 50_000     # points of the true mesh the candidates are measured against when choosing
SNAP_POINTS = 200_000       # points of the chosen oracle shape the network points are moved onto


class SurfacePoints:
    """Points sampled area-weighted on a mesh, kept as (face, barycentric weights) so that they follow any change of
    the mesh's vertices."""

    def __init__(self, mesh: Mesh, n: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        corners = mesh.vertices[mesh.faces]
        area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        self.faces = mesh.faces[rng.choice(len(area), n, p=area / area.sum())]
        r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
        self.weights = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)

    def on(self, vertices: np.ndarray) -> np.ndarray:
        """(n, 3) the points on the mesh with these vertices."""
        return np.einsum("nk,nkd->nd", self.weights, vertices[self.faces])


class Choice:
    """The published outputs with their network points moved onto one chosen shape per pair, and what was chosen."""

    def __init__(self, published: np.ndarray) -> None:
        self.output = published.copy()
        self.distance: list[np.ndarray] = []
        self.taken: Counter[tuple[str, str]] = Counter()

    def add(self, i: int, held: str, training: str, shape: np.ndarray, truth: cKDTree, network: np.ndarray) -> None:
        """Pair `i` (mesh `held`) takes `shape` (SNAP_POINTS points) made from mesh `training`."""
        self.taken[(held, training)] += 1
        self.distance.append(truth.query(shape[:: SNAP_POINTS // CANDIDATE_POINTS])[0])
        self.output[i, network] = shape[cKDTree(shape).query(self.output[i, network])[1]]


def candidates(mesh: Mesh, extent: np.ndarray) -> list[np.ndarray]:
    """Vertices of every candidate made from training `mesh` for a true box of `extent` (normalised frame)."""
    out = []
    for amounts in itertools.product(GRID, repeat=3):
        vertices = fit_to_size(bend_taper_lean(mesh, amounts), extent).vertices
        out += [vertices, vertices * np.array([-1.0, -1.0, 1.0])]   # and turned end for end
    return out


def candidate_shapes(extent: np.ndarray, training: list[Mesh], choose: list[SurfacePoints]
                     ) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(training mesh, vertices, its CANDIDATE_POINTS points) of every candidate for a true box of `extent`."""
    return [(m, vertices, points.on(vertices))
            for m, (mesh, points) in enumerate(zip(training, choose)) for vertices in candidates(mesh, extent)]


def nearest_shape(shapes: list[tuple[int, np.ndarray, np.ndarray]], cost: Callable[[np.ndarray], float]
                  ) -> tuple[int, np.ndarray]:
    """(training mesh, vertices) of the first of `shapes` whose points have the lowest `cost`."""
    m, vertices, _ = min(shapes, key=lambda shape: cost(shape[2]))
    return m, vertices


def oracle_shape(truth: cKDTree, shapes: list[tuple[int, np.ndarray, np.ndarray]]) -> tuple[int, np.ndarray]:
    """The candidate whose points lie nearest, on average, to the true mesh (points of it in `truth`)."""
    return nearest_shape(shapes, lambda points: float(truth.query(points)[0].mean()))


def input_shape(measured: np.ndarray, shapes: list[tuple[int, np.ndarray, np.ndarray]]) -> tuple[int, np.ndarray]:
    """The candidate whose points lie nearest, on average, to `measured` and their mirror (no truth used)."""
    measured = np.concatenate([measured, measured * np.array([1.0, -1.0, 1.0])])
    return nearest_shape(shapes, lambda points: float(cKDTree(points).query(measured)[0].mean()))


def print_pandaset(model: GGDNet, root: str, training: list[Mesh], choose: list[SurfacePoints],
                   snap: list[SurfacePoints]) -> None:
    """PandaSet-002's reduced protocol (`benchmarks/spacing_variants.py`): coverage x1e3 overall and per bucket of the
    network's spaced points and of the published output, shipped and with the network's points moved onto the
    input's shape before the merge; the prior beside them."""
    observations = pe.reduced_observations(root)
    sizes = np.array([o[1] for o in observations])
    _, raw, graph = network_forward(model, [o[0] for o in observations], sizes)
    spaced = even_spacing(raw, SHIPPED_SPACING, graph=graph)
    moved = spaced.copy()
    for i, (partial, size, _, _) in enumerate(observations):
        extent = np.array([1.0, size[1] / size[0], size[2] / size[0]])
        m, candidate = input_shape(partial, candidate_shapes(extent, training, choose))
        shape = snap[m].on(candidate)
        moved[i] = shape[cKDTree(shape).query(spaced[i])[1]]
    bins = [name for name, *_ in pe.SIZE_BINS]
    where = np.array([pe.size_bin(len(o[0])) for o in observations])
    print(f"PandaSet reduced protocol, {len(observations)} observations: coverage x1e3 all / {' / '.join(bins)}")
    prior = [prior_outputs(with_aside(p, b), s, raw.shape[1])["mirror_template"] for p, s, _, b in observations]
    prior_coverage = [nearest_sq(o[2], q).mean() * 1e3 for o, q in zip(observations, prior)]
    print(f"  {'mirror + template':34s} {by_bucket(prior_coverage, where, bins)}")
    for name, points in (("shipped", spaced), ("onto the input's shape", moved)):
        network = [nearest_sq(o[2], c).mean() * 1e3 for o, c in zip(observations, points)]
        merged = [merge_with_pool(c, p, aside=b, size=s).points for c, (p, s, _, b) in zip(points, observations)]
        published = [nearest_sq(o[2], q).mean() * 1e3 for o, q in zip(observations, merged)]
        print(f"  {name + ', network alone':34s} {by_bucket(network, where, bins)}")
        print(f"  {name + ', published':34s} {by_bucket(published, where, bins)}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--meshes", default="../shared/data/vehicle-meshes")
    parser.add_argument("--heldout", type=int, default=128, help="held-out mesh pairs (as the evaluation)")
    parser.add_argument("--pairs", choices=("heldout", "seen-meshes"), default="heldout")
    parser.add_argument("--pandaset", help="also PandaSet-002's reduced protocol with the input's shape (its folder)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    heldout = (load_heldout_meshes if args.pairs == "heldout" else seen_mesh_pairs)(args.heldout, args.meshes)
    assert heldout.meshes is not None and heldout.sizes is not None and heldout.mesh_names is not None
    training = load_mesh_folder(args.meshes, exclude=HELDOUT_MESHES)
    names = [p.stem for p in mesh_files(args.meshes) if p.stem not in HELDOUT_MESHES]
    choose = [SurfacePoints(m, CANDIDATE_POINTS) for m in training]
    snap = [SurfacePoints(m, SNAP_POINTS, seed=1) for m in training]
    model = load_model(args.model)
    if args.pandaset:
        print_pandaset(model, args.pandaset, training, choose, snap)
    outputs = published_outputs(model, list(heldout.partial), np.asarray(heldout.sizes, np.float64))
    published = outputs.published
    network, on_truth, _ = network_points(published, outputs.completion, heldout.meshes)
    chosen = {"oracle shape": Choice(published), "input's shape": Choice(published)}
    for i, (vertices, faces) in enumerate(heldout.meshes):
        true_surface = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        coarse_truth = cKDTree(trimesh.sample.sample_surface(true_surface, CHOICE_SAMPLES, seed=0)[0])
        truth = cKDTree(trimesh.sample.sample_surface(true_surface, SNAP_SAMPLES, seed=0)[0])
        extent = vertices.max(0) - vertices.min(0)   # the exact box the network is given, normalised
        assert np.allclose(extent, heldout.sizes[i] / heldout.sizes[i][0], atol=1e-4)
        shapes = candidate_shapes(extent, training, choose)
        best = {"oracle shape": oracle_shape(coarse_truth, shapes),
                "input's shape": input_shape(heldout.partial[i], shapes)}
        for name, (m, candidate) in best.items():
            chosen[name].add(i, heldout.mesh_names[i], names[m], snap[m].on(candidate), truth, network[i])
    for name, choice in chosen.items():
        distance = np.concatenate(choice.distance)
        print(f"{args.pairs} pairs: {len(published)}; the {name}s' distance to the true meshes (x length): mean "
              f"{distance.mean():.4f}, within 1 % {np.mean(distance <= 0.01):.3f}, within 2 % "
              f"{np.mean(distance <= 0.02):.3f}")
        for (held, train), count in sorted(choice.taken.items()):
            print(f"  {held:22s} <- {train:22s} {count:3d} pairs")
    print("CD, CD(D,G) x1e4, F-score@1 % (precision / recall), on the surface (within 2 %)")
    score("published", published, heldout)
    for name, choice in chosen.items():
        score(f"network points onto {name}", choice.output.astype(np.float32), heldout)
    score("network points onto true mesh", np.where(network[..., None], on_truth, published).astype(np.float32),
          heldout)


if __name__ == "__main__":
    main()
