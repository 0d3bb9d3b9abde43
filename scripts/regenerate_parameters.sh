#!/usr/bin/env bash
# Regenerate the README's parameters table and config/completer.yaml from the settings tables
# (gd_completion/settings.py and gd_completion/ros/params.py); test/test_params.py fails when they differ.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$repo"
.venv/bin/python -c 'from pathlib import Path; from gd_completion.ros.params import write_parameter_docs as w; w(Path("README.md"), Path("config/completer.yaml"))'
git --no-pager diff --stat README.md config/completer.yaml
