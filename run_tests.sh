#!/usr/bin/env bash
# Set up (.venv with every dependency), lint (ruff), type-check the core (mypy) and run the whole test suite.
# Extra arguments go to pytest, e.g. `./run_tests.sh -m "not integration"` for the fast unit subset.
set -euo pipefail
cd "$(dirname "$0")"
scripts/install.sh
.venv/bin/ruff check .
.venv/bin/mypy   # the core's types (files and settings: pyproject.toml)
exec .venv/bin/python -m pytest -q -p no:cacheprovider test "$@"
