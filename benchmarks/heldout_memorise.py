"""How near the true surface the network can bring its points on pairs it trains on over and over (issue 32's point
3: is the network's distance from the surface a matter of generalisation, or of what it can fit at all?).

Fine-tunes a checkpoint (default: the shipped weights) on the evaluation's `seen-meshes` pairs (the 12 training
meshes, `benchmarks/heldout_oracles.py --pairs seen-meshes`: the evaluation's seed, exact boxes), validating on the
same pairs, in stages; before and after each stage, the published output scored as `heldout_oracles.py` scores it
(CD, CD(D,G) x1e4, F-score@1 % (precision / recall), on the surface), then the mean and median distance to the true
mesh of its network points and the mean of the whole completion's before the merge (evenly spaced, x length). The
targets are the pairs' two surface samples together (4,096 points); the losses, weights and frozen refiner are the
shipped recipe's (lambda 3, gamma 3, batch 16: 8 steps an epoch); no drive. One core, about 30 s an epoch.

`--lr-final` decays the learning rate (cosine, per epoch) from `--lr` to it; each stage's schedule runs from epoch 0
to its own last epoch, so a later stage jumps back up the curve: use one stage. Capacity and loss probes: `--beta` sets
the Laplacian shape term's weight (the shipped 0.5 keeps the deformation from changing P_g's local shape), `--batch`
the pairs per step; `--gcn-blocks K`, `--gcn-width W`, `--tree-hidden H0,H1` and `--shape-basis K`
(`GGDConfig.shape_basis`) grow the network before training, so that the grown network computes exactly what the
starting one does (`grown`).

    python benchmarks/heldout_memorise.py OUTPUT [--stages 5,15,40] [--lr 1e-4] [--lr-final LR] [--batch 16]
        [--beta 0.5] [--gcn-blocks K] [--gcn-width W] [--tree-hidden H0,H1] [--shape-basis K] [--model PT] [--pairs 128]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from heldout_oracles import network_points, score, seen_mesh_pairs, surface_distances

from gd_completion.evaluation.baselines import published_outputs
from gd_completion.evaluation.synthetic import HeldOut
from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_checkpoint, load_model, save_checkpoint
from gd_completion.model.network import GGDNet
from gd_completion.preprocess import network_input
from gd_completion.train import TrainSettings, train


def measure(path: str, label: str, pairs: HeldOut) -> None:
    """Print the published output's scores and its network points' distance to the true meshes."""
    assert pairs.meshes is not None
    outputs = published_outputs(load_model(path), list(pairs.partial), np.asarray(pairs.sizes, np.float64))
    published, completion = outputs.published, outputs.completion
    gap = network_points(published, completion, pairs.meshes)[2]
    raw = surface_distances(completion, pairs.meshes)
    score(label, published, pairs)
    print(f"{label}: network points in the output: mean {gap.mean():.4f} median {np.median(gap):.4f}; "
          f"the spaced completion's: mean {raw.mean():.4f}", flush=True)


NEW_BLOCK_BIAS = 0.01   # an appended G-ResNet block's constant output at first: positive, its ReLU passes gradients


def grown(path: str, output: str, **changes: object) -> str:
    """Checkpoint `output`: the network of `path` with the config `changes` (wider decoder or G-ResNet layers, more
    G-ResNet blocks, a shape basis), computing exactly what it did; the new units train. Every old weight keeps its
    place in the leading slice of the bigger tensor; a new unit's incoming weights keep their fresh (seeded)
    initialisation and its outgoing weights (a Linear's new input columns) start at zero. Each appended G-ResNet
    block's second graph conv starts with zero weights and the bias NEW_BLOCK_BIAS, so the block maps h to
    (h + NEW_BLOCK_BIAS) x 0.5 (`GResNet`) and its ReLU is open; the output conv's weights are scaled by 2 per block and
    its bias takes the constant back out."""
    model, preprocessing = load_checkpoint(path)
    old = model.config
    torch.manual_seed(0)
    bigger = GGDNet(replace(old, **changes))
    state = bigger.state_dict()
    for name, tensor in model.state_dict().items():
        target = state[name]
        if target.dim() == 2 and target.shape[1] > tensor.shape[1]:   # a Linear's new inputs: no effect yet
            target[:, tensor.shape[1]:] = 0.0
        target[tuple(slice(0, n) for n in tensor.shape)] = tensor
    bigger.load_state_dict(state)
    with torch.no_grad():
        constant = torch.zeros(bigger.config.gcn_width)   # h after the new blocks: h x 2^-blocks + constant
        for _, g2 in list(bigger.deform.blocks)[old.gcn_blocks:]:
            g2.self_lin.weight.zero_()
            g2.nbr_lin.weight.zero_()
            g2.self_lin.bias.fill_(NEW_BLOCK_BIAS)
            constant = (constant + NEW_BLOCK_BIAS) * 0.5
        out = bigger.deform.out
        for lin in (out.self_lin, out.nbr_lin):
            lin.weight.mul_(2.0 ** (bigger.config.gcn_blocks - old.gcn_blocks))
        out.self_lin.bias.sub_((out.self_lin.weight + out.nbr_lin.weight) @ constant)   # A(constant) = constant
    return str(save_checkpoint(output, bigger.eval(), preprocessing))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", help="training folder (resumed stage by stage)")
    parser.add_argument("--stages", default="5,15,40", help="epochs after which to measure (default 5,15,40)")
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--lr-final", type=float, help="cosine decay to this over each stage's epochs (default none)")
    parser.add_argument("--batch", type=int, default=16, help="pairs per step")
    parser.add_argument("--beta", type=float, default=0.5, help="the Laplacian shape term's weight")
    parser.add_argument("--gcn-blocks", type=int, help="grow the G-ResNet to this many residual blocks first")
    parser.add_argument("--gcn-width", type=int, help="widen the G-ResNet's features to this first")
    parser.add_argument("--tree-hidden", help="widen the tree decoder's hidden layers to these first (e.g. 256,128)")
    parser.add_argument("--shape-basis", type=int, help="add a learned shape basis of this many shapes first")
    parser.add_argument("--model", default=str(DEFAULT_WEIGHTS), help="the starting checkpoint")
    parser.add_argument("--meshes", default="../shared/data/vehicle-meshes")
    parser.add_argument("--pairs", type=int, default=128)
    args = parser.parse_args()
    torch.set_num_threads(1)
    pairs = seen_mesh_pairs(args.pairs, args.meshes)
    assert pairs.surface is not None and pairs.sizes is not None
    inputs = np.stack([network_input(p, 512) for p in pairs.partial])
    data = (inputs, np.concatenate([pairs.complete, pairs.surface], 1), pairs.sizes)
    Path(args.output).mkdir(parents=True, exist_ok=True)
    changes = {k: v for k, v in (("gcn_blocks", args.gcn_blocks), ("gcn_width", args.gcn_width),
                                 ("tree_hidden", args.tree_hidden and tuple(map(int, args.tree_hidden.split(",")))),
                                 ("shape_basis", args.shape_basis))
               if v is not None}
    start = grown(args.model, f"{args.output}/grown.pt", **changes) if changes else args.model
    config = load_model(start).config
    measure(start, "start", pairs)
    for epochs in (int(v) for v in args.stages.split(",")):
        started = time.time()
        settings = TrainSettings(epochs=epochs, generation_epochs=0, lam=3.0, beta=args.beta, gamma=3.0,
                                 batch_size=args.batch, lr=args.lr, lr_final=args.lr_final, seed=0,
                                 freeze=("refiner.",))
        train(config, data, data, args.output, settings, resume=True, init_from=start)
        print(f"trained to epoch {epochs} in {time.time() - started:.0f} s", flush=True)
        measure(f"{args.output}/last.pt", f"epoch {epochs}", pairs)


if __name__ == "__main__":
    main()
