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


def _package_xml_version() -> str:
    import re

    found = re.search(r"<version>([^<]+)</version>", (REPO / "package.xml").read_text())
    assert found
    return found.group(1)


def test_version_is_package_xml_and_imports_nothing_heavy():
    """`gd-completion --version` prints `gd_completion <package.xml's version>` (through the installed metadata, as
    `gd_completion.__version__`), exit 0, without importing torch or rclpy; also after a verb's name is known."""
    from gd_completion import __version__

    assert __version__ == _package_xml_version()
    proc = subprocess.run([sys.executable, "-c", PARSE_AND_LIST_MODULES, "--version"], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [f"gd_completion {__version__}", "heavy modules: []"]
    script = Path(sys.executable).parent / "gd-completion"
    if script.is_file():  # the installed console script
        done = subprocess.run([str(script), "--version"], capture_output=True, text=True, timeout=120, check=False)
        assert (done.returncode, done.stdout, done.stderr) == (0, f"gd_completion {__version__}\n", "")
