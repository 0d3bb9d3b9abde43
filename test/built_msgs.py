"""In-process import of any message package that scripts/build_interfaces.sh builds (vision_msgs, tf2_msgs,
autoware_perception_msgs), the way `interfaces.import_vision_msgs` imports vision_msgs."""
from __future__ import annotations

import ctypes
import importlib
import json
import threading
from pathlib import Path
from types import ModuleType

from interfaces import _PRELOAD_ORDER, build_interfaces, import_vision_msgs

BUILT_PACKAGES = ("vision_msgs", "tf2_msgs", "autoware_perception_msgs")
_lock = threading.Lock()
_preloaded: dict[str, list[ctypes.CDLL]] = {}


def import_built_msgs(package: str) -> ModuleType:
    """`<package>.msg` from the local build (built on demand); raises ImportError when it is not from there or its
    type support does not load.

    `import_vision_msgs` builds all packages into the one install prefix and puts its site-packages on sys.path
    and AMENT_PREFIX_PATH; the package's own libraries are then preloaded by absolute path (RTLD_GLOBAL) for the
    same reason as vision_msgs': LD_LIBRARY_PATH is read at process start only.
    """
    if package not in BUILT_PACKAGES:
        raise ValueError(f"{package} is not built by scripts/build_interfaces.sh (one of {BUILT_PACKAGES})")
    vision = import_vision_msgs()
    site = Path(vision.__file__).resolve().parents[2]  # <prefix>/lib/python3.X/site-packages
    lib = site.parents[1]
    with _lock:
        if package not in _preloaded:
            paths = [lib / f"lib{package}__{kind}.so" for kind in _PRELOAD_ORDER]
            _preloaded[package] = [ctypes.CDLL(str(p), mode=ctypes.RTLD_GLOBAL) for p in paths if p.exists()]
    msgs = importlib.import_module(f"{package}.msg")
    if Path(msgs.__file__).resolve().parents[2] != site:
        raise ImportError(f"{package} imported from {msgs.__file__}, expected the build in {site}")
    first = next(v for v in vars(msgs).values() if isinstance(v, type))
    first.__class__.__import_type_support__()
    if first._TYPE_SUPPORT is None:  # type: ignore[attr-defined]
        raise ImportError(f"{package} type support from {site} could not be loaded")
    return msgs


def built_type_hash(package: str, name: str) -> str:
    """The RIHS01 type hash of `<package>/msg/<name>` from the generated type description (builds on demand)."""
    desc = build_interfaces() / "share" / package / "msg" / f"{name}.json"
    hashes = json.loads(desc.read_text())["type_hashes"]
    return next(h["hash_string"] for h in hashes if h["type_name"] == f"{package}/msg/{name}")
