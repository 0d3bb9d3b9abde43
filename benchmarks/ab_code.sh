#!/usr/bin/env bash
# Alternating A/B of two commits' code, same weights; each commit checked out in a temporary git worktree:
#   bash benchmarks/ab_code.sh [--node|--frame] REV_A REV_B [ROUNDS]   (appends nothing; prints the rows to compare)
# Default: this checkout's bench_model.py with each commit's gd_completion first on PYTHONPATH (the model rows).
# --frame: the same with this checkout's `bench_node.py --offline 20` (the node's core on its 20-vehicle frame,
#          in one process, without ROS).
# --node: each commit's own bench_node.py (its node runs that commit's code; 20 vehicles, measured merge on).
set -u
mode=model
case "${1:-}" in --node) mode=node; shift ;; --frame) mode=frame; shift ;; esac
[ $# -ge 2 ] || { echo "usage: bash benchmarks/ab_code.sh [--node|--frame] REV_A REV_B [ROUNDS]"; exit 2; }
rounds=${3:-3}
cd "$(dirname "$0")/.."
root=$(pwd)
py="$root/.venv/bin/python"
tmp=$(mktemp -d) || exit 2
[ -e ../shared ] && ln -s "$(realpath ../shared)" "$tmp/shared"   # the worktrees find ../shared as this checkout does
trap 'git worktree remove --force "$tmp/a" >/dev/null 2>&1; git worktree remove --force "$tmp/b" >/dev/null 2>&1; rm -rf "$tmp"' EXIT
git worktree add --detach "$tmp/a" "$1" >/dev/null 2>&1 || { echo "!! no such revision: $1"; exit 2; }
git worktree add --detach "$tmp/b" "$2" >/dev/null 2>&1 || { echo "!! no such revision: $2"; exit 2; }
# per mode: what it runs, the script (node: each commit's own; else this checkout's), its rows, the row title
case $mode in
  node) what="bench_node.py, 20 vehicles"; script=benchmarks/bench_node.py; args=""
        rows="answered|end-to-end|processing time"; title="node, 20 vehicles" ;;
  frame) what="bench_node.py --offline 20"; script="$root/benchmarks/bench_node.py"; args="--offline 20"
         rows="^frame"; title="node core, 20-vehicle frame" ;;
  *) what="bench_model.py"; script="$root/benchmarks/bench_model.py"; args=""
     rows="^(batch|16-vehicle)"; title="model" ;;
esac
echo "# A/B of the code of $1 ($(git rev-parse --short "$1")) and $2 ($(git rev-parse --short "$2")), alternating, $rounds rounds ($what), $(date -u +%FT%TZ)"
for round in $(seq "$rounds"); do
  for side in a b; do
    rev=$([ "$side" = a ] && echo "$1" || echo "$2")
    echo "## $title, $rev, round $round"
    # shellcheck disable=SC2086  # args: words on purpose
    (cd "$tmp/$side" && PYTHONPATH="$tmp/$side${PYTHONPATH:+:$PYTHONPATH}" "$py" "$script" $args 2>&1) \
      | grep -E "$rows" || echo "!! $what failed"
  done
done
