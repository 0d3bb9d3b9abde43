"""How far the CUDA path's completions are from the CPU fast path's (needs a GPU): 16 simulated scans through the
shipped weights, max |difference| per cloud with TF32 on (cuDNN's default for convolutions) and off, and the CPU
torch ops against the compiled kernels.

    .venv/bin/python benchmarks/bench_cuda_agreement.py
"""
from __future__ import annotations

import copy
import sys

import torch

from gd_completion.model.checkpoint import DEFAULT_WEIGHTS, load_model
from gd_completion.model.network import box_shape
from gd_completion.model.ops import torch_kernels
from gd_completion.synth.dataset import build_dataset


def main() -> int:
    if not torch.cuda.is_available():
        print("no CUDA device: nothing to compare")
        return 0
    model = load_model(DEFAULT_WEIGHTS)
    scans = build_dataset(16, seed=8080, n_input=model.config.num_input, n_gt=2048)
    x, shapes = torch.from_numpy(scans["partial"]), box_shape(scans["size"])
    gpu = copy.deepcopy(model).cuda()
    with torch.inference_mode():
        ref = model(x, shapes).completion
        with torch_kernels():
            torch_ops = model(x, shapes).completion
        print("cpu torch ops vs compiled kernels, max |diff|", (torch_ops - ref).abs().max().item())
        for tf32 in (True, False):
            torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = tf32
            per_cloud = (gpu(x.cuda(), shapes.cuda()).completion.cpu() - ref).abs().amax((1, 2))
            print(f"tf32 {tf32}: max |diff| {per_cloud.max().item():.3g}, per cloud "
                  + " ".join(f"{v:.2g}" for v in per_cloud.tolist()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
