#!/usr/bin/env bash
# Alternating A/B of the node's fresh_frame_age (bench_node.py --fresh-frame-age, 20 vehicles at 10 Hz):
# holding a stale frame for the next one (the default, 0.05 s) against completing the newest pending frame
# whatever its age (0).   bash benchmarks/ab_fresh_frame_age.sh [ROUNDS]
set -u
rounds=${1:-3}
cd "$(dirname "$0")/.."
py=.venv/bin/python
echo "# A/B of fresh_frame_age 0.05 (default) and 0 in the node, alternating, $rounds rounds, $(git rev-parse --short HEAD), $(date -u +%FT%TZ)"
for round in $(seq "$rounds"); do
  for age in 0.05 0; do
    echo "## node, 20 vehicles, fresh_frame_age $age, round $round"
    $py benchmarks/bench_node.py --fresh-frame-age "$age" 2>&1 | grep -E "answered|end-to-end|processing time|accounting" \
      || echo "!! bench_node.py failed"
  done
done
