#!/usr/bin/env bash
# Alternating A/B of two commits' code (same weights, same benchmark script: this checkout's bench_model.py with
# each commit's gd_completion first on PYTHONPATH), the model rows only:
#   bash benchmarks/ab_code.sh REV_A REV_B [ROUNDS]   (appends nothing; prints the rows to compare)
set -u
rounds=${3:-3}
cd "$(dirname "$0")/.."
root=$(pwd)
py="$root/.venv/bin/python"
tmp=$(mktemp -d)
trap 'git worktree remove --force "$tmp/a" >/dev/null 2>&1; git worktree remove --force "$tmp/b" >/dev/null 2>&1; rm -rf "$tmp"' EXIT
git worktree add --detach "$tmp/a" "$1" >/dev/null 2>&1 || { echo "!! no such revision: $1"; exit 2; }
git worktree add --detach "$tmp/b" "$2" >/dev/null 2>&1 || { echo "!! no such revision: $2"; exit 2; }
echo "# A/B of the code of $1 ($(git rev-parse --short "$1")) and $2 ($(git rev-parse --short "$2")), alternating, $rounds rounds (bench_model.py), $(date -u +%FT%TZ)"
for round in $(seq "$rounds"); do
  for side in a b; do
    rev=$([ "$side" = a ] && echo "$1" || echo "$2")
    echo "## model, $rev, round $round"
    (cd "$tmp/$side" && PYTHONPATH="$tmp/$side" "$py" "$root/benchmarks/bench_model.py" 2>&1) \
      | grep -E "^(batch|16-vehicle)" || echo "!! bench_model.py failed"
  done
done
