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


def test_unknown_parameters_and_params_file_sections(tmp_path):
    from gd_completion.ros.params import params_file_problems, unknown_parameters

    assert unknown_parameters(["min_points", "use_sim_time", "qos_overrides./points.subscription.depth"]) == []
    assert unknown_parameters(["min_point", "zzz"]) == [
        "unknown parameter 'min_point' is ignored (did you mean 'min_points'?)", "unknown parameter 'zzz' is ignored"]
    good, wrong = tmp_path / "good.yaml", tmp_path / "wrong.yaml"
    good.write_text("/completer:\n  ros__parameters:\n    min_points: 5\n")
    wrong.write_text("other_node:\n  ros__parameters:\n    min_points: 5\n")
    args = ["--ros-args", "--params-file", str(good), "--params-file", str(wrong)]
    problems = params_file_problems(args, ("completer",))
    assert len(problems) == 1 and str(wrong) in problems[0] and "other_node" in problems[0]
    assert params_file_problems(["--ros-args", "--params-file", str(wrong)], ("other_node",)) == []


def test_live_and_read_only_parameters():
    from gd_completion.ros.params import LIVE_PARAMETERS, PARAMETERS
    from gd_completion.settings import LIMIT_SETTINGS

    assert LIVE_PARAMETERS <= set(PARAMETERS) and set(LIMIT_SETTINGS) <= LIVE_PARAMETERS
    assert {"cloud_topic", "model_path", "device", "num_threads", "queue_size"}.isdisjoint(LIVE_PARAMETERS)


def test_device_and_checkpoint_errors_are_clear(tmp_path):
    import torch

    from gd_completion.errors import CheckpointError, DeviceError
    from gd_completion.model.checkpoint import read_checkpoint
    from gd_completion.pipeline import check_device

    check_device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="no CUDA device"):
            check_device("cuda")
    with pytest.raises(DeviceError, match="only cpu and cuda"):
        check_device("mps")
    with pytest.raises(DeviceError, match="not a torch device"):
        check_device("gpu0")
    junk = tmp_path / "junk.pt"
    torch.save({"f": print}, junk)          # a pickle of a Python object: refused without running it
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(junk)
    assert "weights_only=False" not in str(info.value) and "junk.pt" in str(info.value)


def test_readme_parameters_table_is_the_node_table():
    """README.md's parameters table is `parameters_markdown()` (regenerate it from gd_completion/ros/params.py)."""
    from gd_completion.ros.params import parameters_markdown

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    start = readme.index("| parameter | default | meaning |")
    assert readme[start:readme.index("\n\n", start)] == parameters_markdown()
