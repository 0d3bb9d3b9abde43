"""Graph-Guided Deformation completion of lidar vehicle scans for ROS 2."""

from typing import Any

__all__ = ["__version__", "complete_cloud"]


def __getattr__(name: str) -> Any:
    """PEP 562, so that `import gd_completion` loads nothing (the `completer` executable installs its signal handlers
    right after it): `complete_cloud` (numpy, torch) and `__version__` (package.xml's, through the installed
    metadata; "unknown" in a source tree never installed) on first use."""
    if name == "complete_cloud":
        from gd_completion.single_cloud import complete_cloud
        return complete_cloud
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version
        try:
            return version("gd_completion")
        except PackageNotFoundError:
            return "unknown"
    raise AttributeError(f"module 'gd_completion' has no attribute {name!r}")
