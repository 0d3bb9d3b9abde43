#!/usr/bin/env bash
# Set up (.venv with every dependency) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")"
scripts/install.sh
exec .venv/bin/python -m pytest -q -p no:cacheprovider test "$@"
