"""colcon build of the repo in a temporary workspace, the installed `completer` executable, vision_msgs bindings."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from interfaces import (
    DETECTION3DARRAY_TYPE_HASH,
    REPO,
    import_vision_msgs,
    ros_test_domain_id,
    roundtrip_detection_array,
    vision_msgs_type_hash,
)

pytestmark = pytest.mark.integration  # processes, ROS nodes, builds or bags: the slow part of the suite

VENV_BIN = Path(sys.executable).parent
COLCON = VENV_BIN / "colcon"
PY = f"python{sys.version_info.major}.{sys.version_info.minor}"
COPY_IGNORE = shutil.ignore_patterns(
    ".venv", ".git", "build", "install", "log", "__pycache__", "*.egg-info", ".pytest_cache", "out"
)
EXPECTED_SHARE = ("package.xml", "config/completer.yaml", "launch/completer.launch.py")
STARTUP_TIMEOUT_S = 60.0  # a ceiling, not a speed check: the wait ends at readiness (25 s was missed under load)
STOP_TIMEOUT_S = 10.0


def _clean_env(**extra: str) -> dict[str, str]:
    """This process's environment with the venv as the only ROS prefix (no colcon user defaults)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("COLCON_")}
    env["AMENT_PREFIX_PATH"] = sys.prefix  # the wheels install their ament index into the venv
    env.pop("CMAKE_PREFIX_PATH", None)
    env["PATH"] = f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}"
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory) -> Path:
    """`colcon build` of a copy of the repository; returns the workspace's install/ folder."""
    if not COLCON.exists():
        pytest.fail(f"colcon not found at {COLCON}: run scripts/install.sh (colcon-common-extensions, colcon-ros)")
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(REPO, ws / "src" / "gd_completion", ignore=COPY_IGNORE)
    env = _clean_env(COLCON_HOME=str(ws / ".colcon"), PYTHONDONTWRITEBYTECODE="1")
    proc = subprocess.run(
        [str(COLCON), "build", "--base-paths", "src", "--executor", "sequential", "--event-handlers",
         "console_cohesion+", "status-"],
        cwd=ws, env=env, capture_output=True, text=True, timeout=300, check=False,
    )
    assert proc.returncode == 0, f"colcon build failed in {ws}:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    assert "gd_completion" in proc.stdout, f"colcon did not build gd_completion:\n{proc.stdout[-2000:]}"
    return ws / "install"


def test_colcon_installs_executable_and_ament_index(colcon_install: Path) -> None:
    prefix = colcon_install / "gd_completion"
    exe = prefix / "lib" / "gd_completion" / "completer"
    assert exe.is_file(), f"{exe} not installed (setup.cfg [install] install_scripts=$base/lib/gd_completion)"
    assert os.access(exe, os.X_OK), f"{exe} is not executable"
    shebang = exe.read_text().splitlines()[0]
    assert shebang.startswith(f"#!{VENV_BIN}{os.sep}python"), f"{exe} does not run the venv's python: {shebang}"
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / "gd_completion"
    assert marker.is_file(), f"ament index marker {marker} missing"
    assert (prefix / "lib" / PY / "site-packages" / "gd_completion" / "__init__.py").is_file()


def test_colcon_installs_share_files(colcon_install: Path) -> None:
    share = colcon_install / "gd_completion" / "share" / "gd_completion"
    missing = [name for name in EXPECTED_SHARE if not (share / name).is_file()]
    not_in_repo = [name for name in missing if not (REPO / name).is_file()]
    assert not missing, (
        f"not installed under {share}: {missing}"
        + (f" (absent from the repository too: {not_in_repo})" if not_in_repo else " (present in the repository)")
    )
    for pattern in ("config/*.yaml", "launch/*.launch.py"):
        for src in REPO.glob(pattern):
            assert (share / src.relative_to(REPO)).is_file(), f"{src.relative_to(REPO)} not installed under {share}"


class _Output:
    """Collects a subprocess's merged stdout/stderr lines on a thread."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:  # type: ignore[union-attr]
            self.lines.append(line.rstrip("\n"))

    def has(self, text: str) -> bool:
        return any(text in line for line in self.lines)

    def tail(self, n: int = 40) -> str:
        self._thread.join(timeout=1.0)
        return "\n".join(self.lines[-n:])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_installed_completer_runs_and_stops_cleanly(colcon_install: Path, monkeypatch, sig: signal.Signals) -> None:
    import rclpy

    prefix = colcon_install / "gd_completion"
    domain = ros_test_domain_id(f"colcon_{sig.name}")  # the two runs must not see each other's node
    site = prefix / "lib" / PY / "site-packages"
    env = _clean_env(
        PYTHONPATH=os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH", "")) if p),
        AMENT_PREFIX_PATH=os.pathsep.join((str(prefix), sys.prefix)),
        ROS_DOMAIN_ID=str(domain),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        PYTHONUNBUFFERED="1",
        RCUTILS_LOGGING_BUFFERED_STREAM="1",
        RCUTILS_COLORIZED_OUTPUT="0",
    )
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    exe = prefix / "lib" / "gd_completion" / "completer"
    proc = subprocess.Popen([str(exe)], env=env, cwd=colcon_install.parent, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    out = _Output(proc)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    try:
        probe = rclpy.create_node("gd_test_graph_probe", context=ctx)
        in_graph = False
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline and proc.poll() is None:
            in_graph = in_graph or "completer" in probe.get_node_names()
            if in_graph and out.has("completer ready"):
                break
            time.sleep(0.2)
        probe.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    try:
        assert proc.poll() is None, f"{exe} exited early with {proc.returncode}:\n{out.tail()}"
        assert in_graph, (
            f"node 'completer' not in the ROS graph (domain {domain}) after {STARTUP_TIMEOUT_S} s:\n{out.tail()}"
        )
        assert out.has("completer ready"), f"no 'completer ready' log line after {STARTUP_TIMEOUT_S} s:\n{out.tail()}"
        proc.send_signal(sig)
        try:
            rc = proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{exe} still running {STOP_TIMEOUT_S} s after {sig.name}:\n{out.tail()}")
        assert rc == 0, f"{exe} exited with {rc} on {sig.name}:\n{out.tail()}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_vision_msgs_bindings_round_trip() -> None:
    """The locally built vision_msgs: import in-process, publisher + subscription, one message over loopback."""
    msgs = import_vision_msgs()
    assert [f for f in msgs.Detection3D.get_fields_and_field_types()] == ["header", "results", "bbox", "id"]
    assert msgs.ObjectHypothesis.get_fields_and_field_types() == {"class_id": "string", "score": "double"}
    assert vision_msgs_type_hash("Detection3DArray") == DETECTION3DARRAY_TYPE_HASH
    sent, received = roundtrip_detection_array()
    assert received == sent
    assert received.detections[1].results[0].hypothesis.class_id == "car"
    assert received.detections[0].bbox.size.x == 4.5
