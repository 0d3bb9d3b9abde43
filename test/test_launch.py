"""launch/completer.launch.py: its arguments (read from the file's syntax tree: launch and launch_ros are not
installed here) and what it computes through gd_completion.ros.launch_params (the params file checked at launch
time, its section applied under a namespace, the topic remappings)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest
import yaml
from interfaces import ros_test_domain_id

from gd_completion.ros.launch_params import (
    NODE_NAME,
    TOPIC_ARGUMENTS,
    LaunchParamsError,
    checked_params_file,
    params_file_for_namespace,
    topic_remappings,
)

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / "launch" / "completer.launch.py"
SHIPPED_PARAMS = REPO / "config" / "completer.yaml"
ARGUMENTS = {"namespace", "use_sim_time", "params_file", "cloud_topic", "boxes_topic", "output_topic", "log_level"}


def _calls(name: str) -> list[ast.Call]:
    tree = ast.parse(LAUNCH_FILE.read_text())
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == name]


def _declared() -> dict[str, dict[str, ast.expr]]:
    """Launch argument name -> its DeclareLaunchArgument keywords."""
    out = {}
    for call in _calls("DeclareLaunchArgument"):
        assert isinstance(call.args[0], ast.Constant)
        out[call.args[0].value] = {k.arg: k.value for k in call.keywords if k.arg}
    return out


def test_declared_arguments() -> None:
    declared = _declared()
    assert set(declared) == ARGUMENTS
    assert all("description" in keywords and "default_value" in keywords for keywords in declared.values())
    literal = {name: ast.literal_eval(kw["default_value"]) for name, kw in declared.items()
               if isinstance(kw["default_value"], ast.Constant)}
    assert literal["namespace"] == "" and literal["use_sim_time"] == "false" and literal["log_level"] == "info"
    assert ast.literal_eval(declared["use_sim_time"]["choices"]) == ["true", "false"]
    # the topic arguments default to the node's topic names, which are its parameters' defaults
    node_defaults = yaml.safe_load(SHIPPED_PARAMS.read_text())[NODE_NAME]["ros__parameters"]
    for argument, topic in TOPIC_ARGUMENTS.items():
        assert literal[argument] == topic == node_defaults[argument]
    assert "completer.yaml" in ast.unparse(declared["params_file"]["default_value"])


def test_node_gets_namespace_parameters_remappings_and_profile() -> None:
    """One Node, built at launch time (OpaqueFunction) from the checked params file."""
    (node,) = _calls("Node")
    keywords = {k.arg: k.value for k in node.keywords}
    assert {"namespace", "name", "parameters", "remappings", "additional_env", "arguments"} <= set(keywords)
    parameters = ast.unparse(keywords["parameters"])
    assert "params_file" in parameters and "use_sim_time" in parameters
    assert "topic_remappings" in ast.unparse(keywords["remappings"])
    assert [ast.unparse(c.keywords[0].value) for c in _calls("OpaqueFunction")] == ["_completer"]
    called = {getattr(c.func, "id", None) for c in ast.walk(ast.parse(LAUNCH_FILE.read_text()))
              if isinstance(c, ast.Call)}
    assert {"checked_params_file", "params_file_for_namespace"} <= called
    assert "PROFILE_VARIABLES" in LAUNCH_FILE.read_text()   # the Fast DDS profile unless one is set


def test_missing_params_file_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(LaunchParamsError, match=rf"params_file {tmp_path / 'nope.yaml'}: no such file"):
        checked_params_file(tmp_path / "nope.yaml")
    with pytest.raises(LaunchParamsError, match="not a file"):
        checked_params_file(tmp_path)
    assert checked_params_file(SHIPPED_PARAMS) == SHIPPED_PARAMS


def test_params_file_under_a_namespace(tmp_path: Path) -> None:
    """rcl applies a `completer:` section to /completer only: under a namespace the node gets a copy keyed by its
    full name, with the same parameters; files that name it already (or /**) are given as they are."""
    assert params_file_for_namespace(SHIPPED_PARAMS, "") == SHIPPED_PARAMS
    assert params_file_for_namespace(SHIPPED_PARAMS, "/") == SHIPPED_PARAMS
    shipped = yaml.safe_load(SHIPPED_PARAMS.read_text())
    for namespace, key in (("robot", "/robot/completer"), ("/fleet/robot_2/", "/fleet/robot_2/completer")):
        copy = params_file_for_namespace(SHIPPED_PARAMS, namespace)
        assert copy != SHIPPED_PARAMS
        assert yaml.safe_load(copy.read_text()) == {key: shipped[NODE_NAME]}
        copy.unlink()
    for keyed in ("/**", "/robot/completer", "robot/completer", "other_node"):
        path = tmp_path / "p.yaml"
        path.write_text(yaml.safe_dump({keyed: {"ros__parameters": {"min_points": 5}}}))
        assert params_file_for_namespace(path, "robot") == path
    path.write_text("- a list\n")
    with pytest.raises(LaunchParamsError, match="not a YAML mapping"):
        params_file_for_namespace(path, "robot")


@pytest.mark.integration  # a ROS node
def test_namespaced_copy_applies_to_the_namespaced_node(tmp_path: Path) -> None:
    """What rcl does with either file for a node `completer` in /robot."""
    rclpy = pytest.importorskip("rclpy")
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({NODE_NAME: {"ros__parameters": {"cloud_topic": "lidar/points"}}}))
    copy = params_file_for_namespace(path, "robot")
    seen = {}
    try:
        for name, params in (("as written", path), ("copy", copy)):
            context = rclpy.Context()
            rclpy.init(context=context, domain_id=ros_test_domain_id(),
                       args=["--ros-args", "-r", "__ns:=/robot", "--params-file", str(params)])
            try:
                node = rclpy.create_node(NODE_NAME, context=context)
                seen[name] = node.declare_parameter("cloud_topic", "points").value
                node.destroy_node()
            finally:
                rclpy.shutdown(context=context)
    finally:
        copy.unlink()
    assert seen == {"as written": "points", "copy": "lidar/points"}


def test_topic_remappings() -> None:
    assert topic_remappings(TOPIC_ARGUMENTS) == []
    assert topic_remappings({**TOPIC_ARGUMENTS, "cloud_topic": "/lidar/points", "output_topic": "vehicles"}) == [
        ("points", "/lidar/points"), ("completed_vehicles", "vehicles")]
    assert topic_remappings({"boxes_topic": ""}) == []
