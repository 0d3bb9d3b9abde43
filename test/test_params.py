"""config/completer.yaml against the node's declarations in gd_completion/ros/params.py: every parameter, its
default (type included: a params file with `1` for a double parameter is rejected by ROS) and its description."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

pytest.importorskip("rcl_interfaces")
from gd_completion.ros.params import PARAMETERS  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "config" / "completer.yaml"


def parameter_comments(text: str) -> dict[str, str]:
    """name -> the comment lines right above it under `ros__parameters:`, joined with spaces."""
    body = text.split("ros__parameters:", 1)[1]
    comments: list[str] = []
    found: dict[str, str] = {}
    for line in body.splitlines():
        if line.strip().startswith("#"):
            comments.append(line.strip()[1:].strip())
        elif match := re.match(r"\s+(\w+):", line):
            found[match.group(1)] = " ".join(comments)
            comments = []
    return found


def test_config_file_matches_declarations():
    text = CONFIG.read_text()
    config = yaml.safe_load(text)
    assert list(config) == ["completer"] and list(config["completer"]) == ["ros__parameters"]
    values = config["completer"]["ros__parameters"]
    assert sorted(values) == sorted(PARAMETERS)
    comments = parameter_comments(text)
    assert sorted(comments) == sorted(PARAMETERS)
    for name, (default, description, _ranges) in PARAMETERS.items():
        assert values[name] == default and type(values[name]) is type(default), (name, values[name], default)
        assert comments[name] == description, name


def test_comment_parser():
    text = "n:\n  ros__parameters:\n    # First line.\n    a: 1\n    # Two\n    # lines.\n    b: [x, y]\n    c: 2\n"
    assert parameter_comments(text) == {"a": "First line.", "b": "Two lines.", "c": ""}
