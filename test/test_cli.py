"""The `gd-completion` command line: help and the light verbs import neither torch nor rclpy."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.integration  # one Python process per case

PARSE_AND_LIST_MODULES = """
import sys
from gd_completion.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print("heavy modules:", sorted(m for m in ("torch", "rclpy") if m in sys.modules))
"""

@pytest.mark.parametrize("argv", [
    ["play", "--help"],
    ["convert", "kitti", "--help"],
    ["convert", "pandaset", "--help"],
    ["convert", "hesai", "--help"],
    ["complete", "--help"],
    ["complete-cloud", "--help"],
    ["render", "--help"],
    ["train", "--help"],
    ["evaluate", "--help"],
    ["demo", "--help"],
    ["--help"],
], ids=" ".join)
def test_help_imports_no_torch(argv):
    proc = subprocess.run([sys.executable, "-c", PARSE_AND_LIST_MODULES, *argv], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: gd-completion " + " ".join(a for a in argv if a != "--help")), proc.stdout
    assert proc.stdout.splitlines()[-1] == "heavy modules: []"


def test_unknown_verb_lists_every_verb():
    proc = subprocess.run([sys.executable, "-m", "gd_completion.cli", "frobnicate"], cwd=REPO, capture_output=True,
                          text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert "invalid choice: 'frobnicate'" in proc.stderr
    for verb in ("demo", "train", "convert", "complete", "play", "render", "evaluate"):
        assert f"'{verb}'" in proc.stderr
