"""Graph-Guided Deformation completion of lidar vehicle scans for ROS 2."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gd_completion")   # package.xml's, through setup.py
except PackageNotFoundError:   # run from a source tree that was never installed
    __version__ = "unknown"

__all__ = ["complete_cloud"]


def __getattr__(name: str) -> object:
    """PEP 562: `complete_cloud` is imported on first use, so `import gd_completion` loads neither numpy nor torch."""
    if name == "complete_cloud":
        from gd_completion.single_cloud import complete_cloud
        return complete_cloud
    raise AttributeError(f"module 'gd_completion' has no attribute {name!r}")
