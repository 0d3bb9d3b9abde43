"""Can the shipped network draw a held-out vehicle at all, given the best code, and does committing to the scan bring
it nearer? (issue 32's point 3: is the network's distance from the true surface in what its decoder and G-ResNet can
draw, or in the code its encoder gives them?)

For each held-out pair the encoder's code is given a per-pair offset, optimised with the network frozen (Adam,
learning rate LR, or with `--decay` falling to LR / 100), and the completion is then run with the fitted code (the
input's local features and kNN graph as shipped; spacing and merge as `published_outputs`). Rows:

- `encoder's code (shipped)`: the shipped output, as `heldout_oracles.py` scores it (run on the whole batch at once,
  the pipeline runs one vehicle at a time: rounding may differ);
- `P_s fitted to the truth`: the offset minimises the Chamfer distance between P_s (the tree decoder's points) and
  the pair's true surface sample (STEPS steps of the decoder alone); the decoder and the G-ResNet both take the code;
- `P_s fitted, G-ResNet's code kept`: the same code for the decoder, the encoder's for the G-ResNet;
- `P_o fitted to the truth`: the offset minimises the Chamfer distance between P_o's points but the control points
  and the truth, the whole network run each step (THROUGH_STEPS steps): what this network can draw for the vehicle
  with the best code there is (as far as the steps find it);
- `P_s fitted to the scan`: the offset minimises the mean squared distance from the measured points and their mirror
  image (y -> -y) to P_s, plus OFFSET_WEIGHT x |offset|^2, no truth used: a test-time fit, as the look-up of
  `heldout_shape_knowledge.py` chooses a shape from the scan.

The truth's rows are bounds on any encoder in front of this decoder and G-ResNet, not methods. Printed as
`heldout_oracles.py` prints them: CD, CD(D,G) x1e4, F-score@1 % (precision / recall), share within 2 % of the true
mesh; then the mean distance to the true mesh (x length) of P_s, of P_o's points but the control points as the
network gives them and after the spacing (`--spacing`, `spacing_variants.py`'s SPEC; default the shipped
5:0.3:0.3), and of the network points in the output, and how far the code moved.

    python benchmarks/heldout_code_fit.py [--model PT] [--meshes DIR] [--heldout N] [--pairs heldout] [--steps S]
        [--through-steps S] [--decay] [--spacing SPEC]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from heldout_oracles import network_points, score, seen_mesh_pairs, surface_distances
from spacing_variants import settings_of
from torch import Tensor

from gd_completion.evaluation.baselines import _resampled, _shapes, mirror_symmetry, spaced_and_merged
from gd_completion.evaluation.synthetic import HeldOut, load_heldout_meshes
from gd_completion.model.box_refiner import from_frame
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.losses import chamfer_l2, chamfer_l2_directional
from gd_completion.model.network import GGDNet

STEPS = 300          # steps of a fit of P_s (the decoder alone)
THROUGH_STEPS = 100  # steps of the fit of P_o (the whole network each step)
LR = 0.05
OFFSET_WEIGHT = 1e-4


class Frozen:
    """The shipped network split at its code: what comes before it once, the decoder and the deformation after it
    for any code."""

    def __init__(self, model: GGDNet, partial: Tensor, sizes: np.ndarray) -> None:
        self.model = model.eval()
        for p in model.parameters():
            p.requires_grad_(False)
        shape = model._shape(_shapes(sizes, len(partial)), partial)
        self.partial, shape_in_frame, self.frame = model._refine(partial, shape)
        self.order = model._order(self.partial)
        self.code, _, self.control, _, _ = model._generate(self.partial, self.order, shape_in_frame)

    def coarse(self, code: Tensor) -> Tensor:
        """P_s in the pair's normalised frame."""
        return self._back(self.model.decoder(code))

    def _back(self, points: Tensor) -> Tensor:
        return points if self.frame is None else from_frame(points, self.frame)

    def completion(self, code: Tensor, deform_code: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(P_o, its kNN graph) with this code (the G-ResNet's: `deform_code`, by default the same)."""
        p_g = torch.cat([self.control, self.model.decoder(code)], 1)
        p_o, knn = self.model.deformed(p_g, self.control.shape[1], code if deform_code is None else deform_code,
                                       self.partial, self.order)
        return self._back(p_o), knn


def fitted(frozen: Frozen, loss_of: object, steps: int, through: bool = False, decay: bool = False) -> Tensor:
    """The code plus an offset minimising `loss_of(points, offset)` (summed over pairs), the points P_s, or with
    `through` P_o's points but the control points (the whole network run with that code); `decay`: the learning rate
    falls from LR to LR / 100 (cosine) over the steps."""
    offset = torch.zeros_like(frozen.code, requires_grad=True)
    optimiser = torch.optim.Adam([offset], lr=LR)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps, eta_min=LR / 100) if decay else None
    for _ in range(steps):
        optimiser.zero_grad()
        code = frozen.code + offset
        points = frozen.completion(code)[0][:, frozen.control.shape[1]:] if through else frozen.coarse(code)
        loss = loss_of(points, offset).sum()   # type: ignore[operator]
        loss.backward()
        optimiser.step()
        if schedule is not None:
            schedule.step()
    return (frozen.code + offset).detach()


@torch.no_grad()
def published(frozen: Frozen, code: Tensor, partials: list[np.ndarray], sizes: np.ndarray,
              deform_code: Tensor | None = None, spacing: str = "5:0.3:0.3"
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(published output, P_o, the spaced P_o) with this code, as `published_outputs` with the spacing `spacing`
    (`spacing_variants.py`'s SPEC)."""
    raw, graph = (t.numpy() for t in frozen.completion(code, deform_code))
    spaced, merged = spaced_and_merged(raw, graph, partials, sizes, spacing=settings_of(spacing))
    return merged, raw, spaced


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS))
    parser.add_argument("--meshes", default="../shared/data/vehicle-meshes")
    parser.add_argument("--heldout", type=int, default=128)
    parser.add_argument("--pairs", choices=("heldout", "seen-meshes"), default="heldout")
    parser.add_argument("--steps", type=int, default=STEPS, help="steps of the fits of P_s")
    parser.add_argument("--decay", action="store_true", help="the learning rate falls to 1 %% of LR over the steps")
    parser.add_argument("--spacing", default="5:0.3:0.3", help="spacing_variants.py's SPEC (default: shipped)")
    parser.add_argument("--through-steps", type=int, default=THROUGH_STEPS, help="steps of the fit of P_o")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    pairs: HeldOut = (load_heldout_meshes if args.pairs == "heldout" else seen_mesh_pairs)(args.heldout, args.meshes)
    assert pairs.meshes is not None and pairs.sizes is not None
    partials = [np.asarray(p, np.float32) for p in pairs.partial]
    sizes = np.asarray(pairs.sizes, np.float64)
    model = load_model(args.model)
    frozen = Frozen(model, torch.from_numpy(_resampled(partials, model.config.num_input)[0]), sizes)
    truth = torch.from_numpy(np.asarray(pairs.complete, np.float32))
    scans = [torch.from_numpy(mirror_symmetry(p)) for p in partials]

    def to_truth(coarse: Tensor, offset: Tensor) -> Tensor:
        return chamfer_l2(coarse, truth)

    def to_scan(coarse: Tensor, offset: Tensor) -> Tensor:
        fit = torch.stack([chamfer_l2_directional(s[None], c[None])[0][0] for s, c in zip(scans, coarse)])
        return fit + OFFSET_WEIGHT * offset.square().sum(-1)

    truth_fit = fitted(frozen, to_truth, args.steps, decay=args.decay)
    best = fitted(frozen, to_truth, args.through_steps, through=True, decay=args.decay)
    codes = {"encoder's code (shipped)": (frozen.code, None),
             "P_s fitted to the truth": (truth_fit, None),
             "P_s fitted, G-ResNet's code kept": (truth_fit, frozen.code),
             "P_o fitted to the truth": (best, None),
             "P_s fitted to the scan": (fitted(frozen, to_scan, args.steps, decay=args.decay), None)}
    print(f"{args.pairs} pairs: {len(partials)}; {args.steps} Adam steps ({args.through_steps} through the whole "
          f"network) at {LR}{' falling to ' + str(LR / 100) if args.decay else ''} on a per-pair code offset")
    print("CD, CD(D,G) x1e4, F-score@1 % (precision / recall), on the surface (within 2 %); P_s's and the network "
          "points' mean distance to the true mesh")
    nc = model.config.num_control
    for name, (code, deform_code) in codes.items():
        output, raw, spaced = published(frozen, code, partials, sizes, deform_code, args.spacing)
        score(name, output.astype(np.float32), pairs)
        network = network_points(output, spaced, pairs.meshes)[2]
        distances = [surface_distances(c, pairs.meshes).mean()
                     for c in (frozen.coarse(code).detach().numpy(), raw[:, nc:], spaced[:, nc:])]
        moved = (code - frozen.code).norm(dim=-1).mean()
        print("  P_s {:.4f}, P_o but P_c {:.4f}, spaced {:.4f}".format(*distances)
              + f", network points {network.mean():.4f}; code moved {moved:.3f} "
              f"(code norm {frozen.code.norm(dim=-1).mean():.3f})", flush=True)


if __name__ == "__main__":
    main()
