#!/usr/bin/env bash
# Control-point ablation (paper Sec. IV, N_c = 128, 256, 512): three GGD-Nets warm-started from the v1
# weights (docs/evaluation/ablation/ggd_v1.pt) with the same budget. The tree decoder's levels after the first split depend on N_s = N_o - N_c,
# so those levels start fresh for every N_c (256 included, for a fair comparison); then 2 epochs with
# lambda = 3 (no generation-only epoch: everything but those levels is already trained, and a lambda = 0
# epoch lets the deformation collapse to zero offsets) on the 2400-sample training set of the shipped run.
# About 13 minutes per model on 2 CPU cores. Output: runs/ablation/nc{128,256,512}/best.pt; evaluate with
#   gd-completion evaluate --ablation-checkpoints runs/ablation/nc128/best.pt runs/ablation/nc256/best.pt \
#       runs/ablation/nc512/best.pt
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-runs/ablation}
SKIP=()
for level in 1 2 3; do
  SKIP+=(--init-skip "decoder.node_in.$level" --init-skip "decoder.code_in.$level" --init-skip "decoder.rest.$level")
done
for nc in 128 256 512; do
  "$PY" -m gd_completion.cli train --output "$OUT/nc$nc" --cache "${CACHE:-runs/data}" --samples 2400 \
    --val-samples 120 --epochs 2 --generation-epochs 0 --batch-size 16 --lr 1e-3 --num-control "$nc" \
    --init-from docs/evaluation/ablation/ggd_v1.pt "${SKIP[@]}" --resume
done
