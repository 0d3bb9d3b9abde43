"""What issue 32's point 3 asks of the network: the held-out meshes' published output against oracles that fix one
thing at a time, in one run (the evaluation's held-out pairs, `evaluation.synthetic.load_heldout_meshes`):

- `published`: the shipped pipeline's output (even spacing, then the measured merge), as the report scores it;
- `network points X closer`: each of its network points (those the merge took from the completion) moved X of
  the way onto the true mesh (its nearest of SNAP_SAMPLES points sampled on it), the measured and mirrored points
  kept: a network that places its points where it does now, with its distance to the surface cut by X (100 %: as
  crisp as can be);
- `network points on own plane`: each network point moved onto the least-squares plane of its 16 nearest network
  points (`spacing.even_spacing` without pushes, all of the distance flattened; no oracle): the shell's thickness
  removed, the surface the network estimated kept;
- `crisp everything`: every published point moved onto the true mesh;
- `perfect network, same merge`: the merge given a uniform sample of the true surface (`HeldOut.surface`) in place
  of the network's completion: a network that guesses the shape exactly, through the shipped merge;
- `perfect sample` (the report's floor): a second uniform sample of the true surface.

Printed per row: CD, CD(D,G) x1e4, F-score@1 % (the pairs' mean) with its precision and recall (pooled over the
pairs), and the share of points within 2 %
of the length of the true mesh; then the share of network points in the published output and their distance to
the true mesh (to their nearest of the SNAP_SAMPLES points on it: an overstatement by at most their spacing, about
0.3 % of the length).

`--pairs seen-meshes` scores pairs of the training meshes instead (the same seed and sampling: shapes the network
was trained on, scans it was not), `--pairs procedural` the evaluation's procedural set: how far the network's
points are from a surface it has learnt, against one it has not.

    python benchmarks/heldout_oracles.py [--model PT] [--meshes DIR] [--heldout N]
        [--pairs {heldout,seen-meshes,procedural}]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from gd_completion.evaluation.baselines import published_outputs
from gd_completion.evaluation.mesh_distance import NEAR_SURFACE, distances_to_meshes
from gd_completion.evaluation.metrics import F_SCORE_THRESHOLD, nearest_sq_distance
from gd_completion.evaluation.synthetic import (
    HeldOut,
    _chamfer_row,
    load_heldout,
    load_heldout_meshes,
    load_mesh_pairs,
)
from gd_completion.merge import merge_with_pool
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.spacing import SpacingSettings, even_spacing
from gd_completion.synth.meshio import HELDOUT_MESHES, mesh_files

SNAP_SAMPLES = 400_000   # points sampled on a true mesh to snap onto
SHARES = (0.25, 0.5, 0.75, 1.0)   # how much of the network points' distance to the surface the oracles remove
OWN_PLANE = SpacingSettings(iterations=0, flatten=1.0)   # each point onto the plane of its 16 nearest


def on_surface(points: np.ndarray, mesh: tuple[np.ndarray, np.ndarray], dense: int = SNAP_SAMPLES) -> np.ndarray:
    """Each of `points` moved onto the true surface `mesh` (vertices, faces): its nearest of `dense` points sampled
    uniformly on it (seeded; their spacing, about 0.3 % of the length, is the snap's error)."""
    surface = trimesh.Trimesh(vertices=mesh[0], faces=mesh[1], process=False)
    sample = trimesh.sample.sample_surface(surface, dense, seed=0)[0].astype(np.float32)
    return sample[cKDTree(sample).query(points)[1]]


def surface_distances(clouds: np.ndarray | list[np.ndarray], meshes: list[tuple[np.ndarray, np.ndarray]]
                      ) -> np.ndarray:
    """Every point's distance to its cloud's true mesh (`on_surface`), flat."""
    return np.concatenate([np.linalg.norm(c - on_surface(c, m), axis=-1) for c, m in zip(clouds, meshes)])


def seen_mesh_pairs(n: int, mesh_dir: str) -> HeldOut:
    """`n` pairs of the meshes the network was trained on (all but HELDOUT_MESHES), drawn as the held-out pairs are."""
    return load_mesh_pairs(n, mesh_dir, [p.stem for p in mesh_files(mesh_dir) if p.stem not in HELDOUT_MESHES],
                           what="training")


def network_points(published: np.ndarray, completion: np.ndarray, meshes: list[tuple[np.ndarray, np.ndarray]]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(which published points the merge took from the completion (S, N) bool, every published point moved onto its
    true mesh (S, N, 3), those network points' distance to it (flat))."""
    network = np.stack([cKDTree(c).query(p)[0] == 0.0 for p, c in zip(published, completion)])
    targets = np.stack([on_surface(p, m) for p, m in zip(published, meshes)])
    return network, targets, np.linalg.norm(published - targets, axis=-1)[network]


def score(name: str, clouds: np.ndarray, heldout: HeldOut) -> None:
    """One printed row: CD, CD(D,G), F-score (precision, recall) and the share on the true mesh."""
    assert heldout.meshes is not None
    chamfer, to_output = _chamfer_row(clouds, heldout.complete)
    t2 = F_SCORE_THRESHOLD ** 2
    precision = float((nearest_sq_distance(clouds, heldout.complete) <= t2).float().mean())
    recall = float((to_output <= t2).float().mean())
    (distance,) = distances_to_meshes([clouds], [v for v, _ in heldout.meshes], [f for _, f in heldout.meshes])
    print(f"{name:30s} {chamfer['cd']:6.2f} {chamfer['cd_dg']:6.2f} {chamfer['f_score']:6.3f} "
          f"({precision:.3f} / {recall:.3f}) {np.mean(distance <= NEAR_SURFACE):6.3f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--meshes", default="../shared/data/vehicle-meshes")
    parser.add_argument("--heldout", type=int, default=128, help="held-out mesh pairs (as the evaluation)")
    parser.add_argument("--pairs", choices=("heldout", "seen-meshes", "procedural"), default="heldout")
    args = parser.parse_args()
    torch.set_num_threads(1)
    heldout = {"heldout": lambda: load_heldout_meshes(args.heldout, args.meshes),
               "seen-meshes": lambda: seen_mesh_pairs(args.heldout, args.meshes),
               "procedural": lambda: load_heldout(args.heldout)}[args.pairs]()
    assert heldout.meshes is not None and heldout.surface is not None and heldout.sizes is not None
    sizes = np.asarray(heldout.sizes, np.float64)
    outputs = published_outputs(load_model(args.model), list(heldout.partial), sizes)
    published, completion = outputs.published, outputs.completion
    n = published.shape[1]
    network, targets, gap = network_points(published, completion, heldout.meshes)
    perfect_merge = np.stack([merge_with_pool(s[:n] if len(s) >= n else s, p, size=z).points
                              for s, p, z in zip(heldout.surface, heldout.partial, sizes)])
    print(f"{args.pairs} pairs ({heldout.source}), {len(sizes)} pairs, {n} output points; CD, CD(D,G) x1e4, "
          f"F-score@1 % (precision / recall), on the surface (within 2 %)")
    score("published", published, heldout)
    for share in SHARES:   # the network points' distance to the surface cut by `share`
        moved = published + np.where(network[..., None], share * (targets - published), 0.0).astype(np.float32)
        score(f"network points {share:.0%} closer", moved, heldout)
    flat = published.copy()   # thickness removed, the network's own surface kept
    for i in range(len(flat)):
        flat[i, network[i]] = even_spacing(published[i, network[i]], OWN_PLANE)
    score("network points on own plane", flat, heldout)
    score("crisp everything", targets, heldout)
    score("perfect network, same merge", perfect_merge, heldout)
    score("perfect sample (the floor)", heldout.surface, heldout)
    print(f"network points: {network.mean():.3f} of the published output; their distance to the true mesh "
          f"(x length): mean {gap.mean():.4f}, median {np.median(gap):.4f}, 90th percentile "
          f"{np.percentile(gap, 90):.4f}")


if __name__ == "__main__":
    main()
