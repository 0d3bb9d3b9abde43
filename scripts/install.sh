#!/usr/bin/env bash
# Create .venv inside the repository and install everything the project needs (idempotent, offline-safe re-runs).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
stamp=.venv/.gd_completion-installed
want=$(cat requirements.txt setup.py | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -r requirements.txt
  .venv/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
  echo "$want" > "$stamp"
fi
# Compile the CPU kernels now (numba caches them beside the sources, and recompiles after a source change), not on
# the first `completer` start; seconds when the cache is current.
.venv/bin/python -m gd_completion.warmup
