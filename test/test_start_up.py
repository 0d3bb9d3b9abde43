"""The `completer` executable's start-up: a SIGINT or SIGTERM at any moment of it (torch importing, the model
loading, the kernels warming up, after ready) ends the process with exit code 0 and no traceback."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_live import REPO, ros_env

pytestmark = pytest.mark.integration
HANG_GUARD_S = 20.0   # a hang fails the test; the exit times themselves are measured by benchmarks/start_up.py


def _start(tmp: Path) -> tuple[subprocess.Popen, Path]:
    err = tmp / f"completer_{time.monotonic_ns()}.stderr"
    env = {**os.environ, **ros_env(tmp), "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "gd_completion.ros.completer_main", "--ros-args", "-p",
                             "boxes_type:=marker"], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=err.open("w"))
    return proc, err


def _handlers_installed(pid: int) -> bool:
    """True once the process catches SIGTERM (Python itself catches only SIGINT): `completer_main` has installed its
    handlers, the first thing it does after the interpreter has started."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
    return bool(caught & (1 << (signal.SIGTERM - 1)))


@pytest.mark.parametrize(("sig", "delay"), [(signal.SIGINT, 0.0), (signal.SIGTERM, 0.3), (signal.SIGINT, 1.0),
                                            (signal.SIGTERM, 2.0)])
def test_signal_during_start_up_exits_0_without_traceback(tmp_path, sig, delay) -> None:
    """`delay` seconds after the handlers are in place (before that the interpreter itself is starting: tens of
    milliseconds, in which Python's default handling applies)."""
    proc, err = _start(tmp_path)
    end = time.monotonic() + HANG_GUARD_S
    while not _handlers_installed(proc.pid):
        assert proc.poll() is None and time.monotonic() < end, err.read_text()[-2000:]
        time.sleep(0.002)
    time.sleep(delay)
    proc.send_signal(sig)
    assert proc.wait(HANG_GUARD_S) == 0, err.read_text()[-2000:]
    assert "Traceback" not in err.read_text()


def test_signal_after_ready_exits_0(tmp_path) -> None:
    proc, err = _start(tmp_path)
    end = time.monotonic() + 120
    while "completer ready" not in err.read_text():
        assert proc.poll() is None and time.monotonic() < end, err.read_text()[-2000:]
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(HANG_GUARD_S) == 0
    assert "Traceback" not in err.read_text()


def test_help_imports_neither_torch_nor_rclpy_and_survives_a_closed_pipe(tmp_path) -> None:
    env = {**os.environ, **ros_env(tmp_path), "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "gd_completion.ros.completer_main", "--help"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "track_ids (default 'associate'" in done.stdout
    imported = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if line.startswith("import time")}
    assert "gd_completion.ros.params" in imported
    assert not {"torch", "rclpy", "gd_completion.pipeline"} & imported
    piped = subprocess.run(f"{sys.executable} -m gd_completion.ros.completer_main --help | head -1", shell=True,
                           cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert piped.stdout.startswith("usage: completer") and "Traceback" not in piped.stderr


def test_version_imports_neither_torch_nor_rclpy(tmp_path) -> None:
    """`completer --version` prints `gd_completion <package.xml's version>` and exits 0 at once."""
    import re

    from gd_completion import __version__

    found = re.search(r"<version>([^<]+)</version>", (REPO / "package.xml").read_text())
    assert found and __version__ == found.group(1)
    env = {**os.environ, **ros_env(tmp_path), "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "gd_completion.ros.completer_main", "--version"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout) == (0, f"gd_completion {__version__}\n")
    imported = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if line.startswith("import time")}
    assert not {"torch", "rclpy", "gd_completion.ros.params", "gd_completion.pipeline"} & imported
    script = Path(sys.executable).parent / "completer"
    if script.is_file():  # the installed console script
        done = subprocess.run([str(script), "--version"], env=env, capture_output=True, text=True, timeout=60)
        assert (done.returncode, done.stdout, done.stderr) == (0, f"gd_completion {__version__}\n", "")
