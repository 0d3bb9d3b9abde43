"""What made a bag: package version, model checksum and parameters, kept in rosbag2 metadata `custom_data`.

rosbag2 stores `custom_data` in the bag folder's metadata.yaml (what `ros2 bag info` reads) and, for MCAP,
in the file's rosbag2 metadata record as well.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from gd_completion import __version__
from gd_completion.errors import BagError

if TYPE_CHECKING:
    from rosbags.rosbag2 import Writer

PREFIX = "gd_completion."


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def completer_parameters(completer: Any) -> dict[str, Any]:
    """The settings of a VehicleCompleter that decide its output (not its thread count: that does not)."""
    return {"labels": sorted(completer.labels), "include_input_points": completer.include_input_points,
            "measured_merge": completer.measured_merge, "even_spacing": completer.even_spacing,
            "num_input_points": completer.num_input, "num_output_points": completer.num_output,
            "device": str(completer.device), "preprocessing": completer.preprocessing.to_dict()}


def provenance(command: str, model: str | Path, parameters: dict[str, Any]) -> dict[str, str]:
    """custom_data entries: package version, the command, the model file and its SHA-256, parameters as JSON."""
    return {f"{PREFIX}version": __version__, f"{PREFIX}command": command, f"{PREFIX}model": str(model),
            f"{PREFIX}model_sha256": file_sha256(model),
            f"{PREFIX}parameters": json.dumps(parameters, sort_keys=True)}


def set_provenance(writer: Writer, entries: dict[str, str]) -> None:
    """Store `entries` in the custom_data of a bag being written (before it is closed)."""
    for key, value in entries.items():
        writer.set_custom_data(key, value)


def read_provenance(bag: str | Path) -> dict[str, str]:
    """The gd_completion entries of a bag folder's custom_data (empty when it has none)."""
    metadata = Path(bag) / "metadata.yaml"
    try:
        info = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as error:
        raise BagError(f"{metadata}: cannot read rosbag2 metadata: {error}") from error
    custom = info.get("custom_data") or {}
    return {k: str(v) for k, v in custom.items() if k.startswith(PREFIX)}
