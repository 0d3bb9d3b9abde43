"""The Fast DDS large-message profile shipped in config/: where it is, and using it in this process."""
from __future__ import annotations

import os
import sys
from collections.abc import Iterator, MutableMapping
from pathlib import Path

PACKAGE = "gd_completion"
PROFILE_NAME = "fastdds_large_messages.xml"
# Fast DDS 2.x (ROS 2 Jazzy) reads the first; 3.x the second. Either one set by the user is left alone.
PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
SOURCE_CONFIG = Path(__file__).resolve().parents[1] / "config"  # when running from the source tree


def large_message_profile() -> Path | None:
    """The profile: the source tree's config/ when running from it, else the installed share/gd_completion/config
    (through ament_index_python when it is importable, else under this Python's prefix); None when absent."""
    return next((folder / PROFILE_NAME for folder in _config_folders() if (folder / PROFILE_NAME).is_file()), None)


def _config_folders() -> Iterator[Path]:
    yield SOURCE_CONFIG
    try:
        from ament_index_python.packages import get_package_share_directory

        share = get_package_share_directory(PACKAGE)
    except (ImportError, LookupError, OSError, ValueError):  # no ament; no AMENT_PREFIX_PATH; not installed there
        pass
    else:
        yield Path(share) / "config"
    yield Path(sys.prefix) / "share" / PACKAGE / "config"


def use_large_message_profile(environ: MutableMapping[str, str] = os.environ) -> str | None:
    """Point FASTRTPS_DEFAULT_PROFILES_FILE at the large-message profile unless a profile file is set already.

    Fast DDS reads the variable once, when the process creates its first participant: call this before
    `rclpy.init`. Returns the profile file in effect (None when none is set and the profile is not found).
    """
    chosen = next((environ[name] for name in PROFILE_VARIABLES if environ.get(name)), None)
    if chosen is None and (profile := large_message_profile()) is not None:
        chosen = environ[PROFILE_VARIABLES[0]] = str(profile)
    return chosen
