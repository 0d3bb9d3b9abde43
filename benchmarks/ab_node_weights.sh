#!/usr/bin/env bash
# Alternating A/B of two checkpoints in the live node (bench_node.py --model, 20 vehicles, measured merge on):
#   bash benchmarks/ab_node_weights.sh A.pt B.pt [ROUNDS]   (appends nothing; prints the rows to compare)
set -u
a=$(realpath "$1"); b=$(realpath "$2"); rounds=${3:-3}
cd "$(dirname "$0")/.."
py=.venv/bin/python
echo "# A/B of $a and $b in the node, alternating, $rounds rounds (bench_node.py --model), $(date -u +%FT%TZ)"
for round in $(seq "$rounds"); do
  for weights in "$a" "$b"; do
    echo "## node, 20 vehicles, $weights, round $round"
    $py benchmarks/bench_node.py --model "$weights" 2>&1 | grep -E "answered|end-to-end|processing time" \
      || echo "!! bench_node.py failed"
  done
done
