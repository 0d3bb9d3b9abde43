"""ament_python package set-up: `ros2 run gd_completion completer` and the `gd-completion` tool."""
import re
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "gd_completion"
# The one version string is package.xml's (ROS reads it there); the Python metadata and `__version__` follow it.
VERSION = re.search(r"<version>([^<]+)</version>", (Path(__file__).parent / "package.xml").read_text()).group(1)

setup(
    name=PACKAGE,
    version=VERSION,
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["weights/*.pt", "msg/*/*.msg", "weights/*.md"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools", "numpy", "pyyaml"],
    zip_safe=True,
    maintainer="gd_completion developers",
    description="Graph-Guided Deformation completion of lidar vehicle scans for ROS 2.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "completer = gd_completion.ros.completer_main:main",
            "gd-completion = gd_completion.cli:main",
        ],
    },
)
