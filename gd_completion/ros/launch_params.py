"""What launch/completer.launch.py computes without launch: the checked parameters file (also under a namespace)
and the topic remappings."""
from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

from gd_completion.errors import GDCompletionError

NODE_NAME = "completer"
# launch argument -> the node's topic name it remaps (the default of the node's parameter of the same name)
TOPIC_ARGUMENTS = {"cloud_topic": "points", "boxes_topic": "detections", "output_topic": "completed_vehicles"}


class LaunchParamsError(GDCompletionError):
    """A launch argument that cannot work: a parameters file that is missing or is no YAML mapping."""


def checked_params_file(path: str | Path) -> Path:
    """`path` when it is a file; else LaunchParamsError (at launch time, before the node would start on defaults)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise LaunchParamsError(f"params_file {path}: {'not a file' if path.exists() else 'no such file'}")
    return path


def params_file_for_namespace(path: str | Path, namespace: str, node_name: str = NODE_NAME) -> Path:
    """The parameters file to give the node in `namespace`: `path` itself, or, when the file keys the node's
    section by its bare name (`completer:`, which rcl applies only to `/completer`), a copy (in the temporary
    folder) with that section keyed `/<namespace>/completer`. Wildcard sections (`/**`) and sections naming the
    namespaced node already are left as they are."""
    import yaml

    path = Path(path)
    namespace = namespace.strip("/")
    if not namespace:
        return path
    try:
        sections = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise LaunchParamsError(f"params_file {path}: {exc}") from exc
    if not isinstance(sections, Mapping):
        raise LaunchParamsError(f"params_file {path}: not a YAML mapping of node names to ros__parameters")
    full_name = f"/{namespace}/{node_name}"
    keys = [str(key).strip("/") for key in sections]
    if full_name.strip("/") in keys or node_name not in keys:
        return path
    renamed = {(full_name if str(key).strip("/") == node_name else key): value for key, value in sections.items()}
    fd, copy = tempfile.mkstemp(prefix=f"{node_name}_params_", suffix=".yaml")
    with os.fdopen(fd, "w") as out:
        yaml.safe_dump(renamed, out, sort_keys=False)
    return Path(copy)


def topic_remappings(values: Mapping[str, str]) -> list[tuple[str, str]]:
    """(node's topic name, launch argument's value) for every topic argument of `values` that changes its name."""
    return [(topic, values[argument]) for argument, topic in TOPIC_ARGUMENTS.items()
            if values.get(argument, topic) not in ("", topic)]
