#!/usr/bin/env bash
# Every benchmark whose figures the README quotes, one after the other (run on an otherwise idle machine).
# Usage: benchmarks/run_all.sh [output file]   (default: benchmarks/results.txt)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-benchmarks/results.txt}
py=.venv/bin/python
{
  echo "# $(date -u +%FT%TZ) $(nproc) cores, $(uname -m), code $(git rev-parse --short HEAD)$(git diff --quiet HEAD || echo ' (with uncommitted changes)'), load before: $(cut -d' ' -f1-3 /proc/loadavg)"
  echo "## model: torch path vs fast path (bench_model.py --stages --train)"; $py benchmarks/bench_model.py --stages --train || echo "!! bench_model.py failed"
  echo "## core (bench_core.py)"; $py benchmarks/bench_core.py || echo "!! bench_core.py failed"
  echo "## track fusion (bench_fusion.py)"; $py benchmarks/bench_fusion.py || echo "!! bench_fusion.py failed"
  echo "## node, 20 vehicles (bench_node.py)"; $py benchmarks/bench_node.py || echo "!! bench_node.py failed"
  echo "## node, PandaSet frame 0 (bench_node.py --pandaset 0)"; $py benchmarks/bench_node.py --pandaset 0 || echo "!! bench_node.py failed"
  echo "## PandaSet-002 live at 10 Hz, reuse on/off alternating, without and with one busy core (bench_live_sequence.py)"; $py benchmarks/bench_live_sequence.py || echo "!! bench_live_sequence.py failed"
  echo "## offline complete --track-fusion with and without --reuse (bench_offline_reuse.py)"; $py benchmarks/bench_offline_reuse.py || echo "!! bench_offline_reuse.py failed"
  echo "## start-up (start_up.py)"; $py benchmarks/start_up.py || echo "!! start_up.py failed"
  echo "## offline tools (bench_tools.py --complete-frames 10)"; $py benchmarks/bench_tools.py --complete-frames 10 || echo "!! bench_tools.py failed"
  echo "## hesai (bench_hesai.py)"; $py benchmarks/bench_hesai.py || echo "!! bench_hesai.py failed"
  echo "## synthetic data (bench_synth.py)"; $py benchmarks/bench_synth.py || echo "!! bench_synth.py failed"
  echo
  echo "# Node with and without the measured merge, alternating (bench_node.py [--no-measured-merge]), same commit"
  for round in 1 2 3; do
    echo "## node, 20 vehicles, measured merge on (bench_node.py), round $round"
    $py benchmarks/bench_node.py || echo "!! bench_node.py failed"
    echo "## node, 20 vehicles, measured merge off (bench_node.py --no-measured-merge), round $round"
    $py benchmarks/bench_node.py --no-measured-merge || echo "!! bench_node.py failed"
  done
} 2>&1 | tee "$out"
