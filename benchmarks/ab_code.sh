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
case $mode in node) what="bench_node.py, 20 vehicles" ;; frame) what="bench_node.py --offline 20" ;; *) what="bench_model.py" ;; esac
echo "# A/B of the code of $1 ($(git rev-parse --short "$1")) and $2 ($(git rev-parse --short "$2")), alternating, $rounds rounds ($what), $(date -u +%FT%TZ)"
for round in $(seq "$rounds"); do
  for side in a b; do
    rev=$([ "$side" = a ] && echo "$1" || echo "$2")
    case $mode in
      node)
        echo "## node, 20 vehicles, $rev, round $round"
        (cd "$tmp/$side" && PYTHONPATH="$tmp/$side${PYTHONPATH:+:$PYTHONPATH}" "$py" benchmarks/bench_node.py 2>&1) \
          | grep -E "answered|end-to-end|processing time" || echo "!! bench_node.py failed" ;;
      frame)
        echo "## node core, 20-vehicle frame, $rev, round $round"
        (cd "$tmp/$side" && PYTHONPATH="$tmp/$side${PYTHONPATH:+:$PYTHONPATH}" "$py" "$root/benchmarks/bench_node.py" --offline 20 2>&1) \
          | grep -E "^frame" || echo "!! bench_node.py --offline failed" ;;
      *)
        echo "## model, $rev, round $round"
        (cd "$tmp/$side" && PYTHONPATH="$tmp/$side${PYTHONPATH:+:$PYTHONPATH}" "$py" "$root/benchmarks/bench_model.py" 2>&1) \
          | grep -E "^(batch|16-vehicle)" || echo "!! bench_model.py failed" ;;
    esac
  done
done
