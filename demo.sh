#!/usr/bin/env bash
# Set up (.venv with every dependency) and run the main job on the built-in synthetic drive.
# Extra arguments go to `gd-completion demo` (e.g. --frames 20 --output out/demo).
set -euo pipefail
cd "$(dirname "$0")"
scripts/install.sh
exec .venv/bin/gd-completion demo "$@"
