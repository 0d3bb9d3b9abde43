"""package.xml: rosdep keys that resolve, one per runtime requirement; the licence it names is the LICENSE file."""
from __future__ import annotations

import hashlib
import re
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# requirements.txt's Python libraries -> their rosdep keys, as rosdep/python.yaml of ros/rosdistro has them (checked
# at ros/rosdistro commit 8468e88c). Not keys: python3-trimesh (only python3-trimesh-pip), python3-rosbags (only
# python3-rosbags-pip); python3-pytorch-pip is a deprecated alias (migrate_eol_2025_04_30) that also installs
# torchvision, while python3-torch resolves to apt's python3-torch on Debian and Ubuntu. ray is optional
# (`complete --engine ray`) and has no key.
ROSDEP_KEYS = {
    "numpy": "python3-numpy",
    "torch": "python3-torch",
    "numba": "python3-numba",
    "scipy": "python3-scipy",
    "trimesh": "python3-trimesh-pip",
    "tqdm": "python3-tqdm",
    "pyyaml": "python3-yaml",
    "rosbags": "python3-rosbags-pip",
    "matplotlib": "python3-matplotlib",
    "pandas": "python3-pandas",
    "ray": None,
}
NOT_KEYS = ("python3-trimesh", "python3-rosbags", "python3-pytorch-pip")
# sha256 of the Apache License 2.0 text as apache.org publishes it (LICENSE-2.0.txt, 11,358 bytes)
APACHE_2_SHA256 = "cfc7749b96f63bd31c3c42b5c471bf756814053e847c10f3eb003417bc523d30"


def _package() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


def _runtime_requirements() -> list[str]:
    """Python distributions of requirements.txt before its tooling part, the ROS wheels left out."""
    text = (REPO / "requirements.txt").read_text().split("# tests and tooling")[0]
    names = [re.split(r"[<>=\[ ;#]", line.strip(), maxsplit=1)[0].lower() for line in text.splitlines()]
    return [name for name in names if name and not name.startswith("ros-")]


def test_python_keys_are_the_documented_rosdep_keys() -> None:
    package = _package()
    python_keys = {e.text for e in package.iter() if e.tag.endswith("depend") and (e.text or "").startswith("python3-")}
    assert sorted(_runtime_requirements()) == sorted(ROSDEP_KEYS)  # a new requirement needs its key here
    assert python_keys == {key for key in ROSDEP_KEYS.values() if key} | {"python3-pytest"}
    assert not python_keys & set(NOT_KEYS)
    assert [e.text for e in package.iter("test_depend")] == ["python3-pytest"]
    assert "No rosdep key" not in (REPO / "package.xml").read_text()


def test_licence_is_apache_2_everywhere() -> None:
    assert _package().findtext("license") == "Apache-2.0"
    assert hashlib.sha256((REPO / "LICENSE").read_bytes()).hexdigest() == APACHE_2_SHA256
    assert re.search(r'\blicense="Apache-2\.0"', (REPO / "setup.py").read_text())
