#!/usr/bin/env bash
# Set up (.venv with every dependency), lint (ruff) and run the whole test suite.
# Extra arguments go to pytest, e.g. `./run_tests.sh -m "not integration"` for the fast unit subset.
set -euo pipefail
cd "$(dirname "$0")"
scripts/install.sh
.venv/bin/ruff check .
exec .venv/bin/python -m pytest -q -p no:cacheprovider test "$@"
