"""`gd-completion play` stops on SIGINT or SIGTERM (Ctrl-C, `ros2 launch`, `kill`): while it publishes a --loop and
while it waits for subscribers, exit code 0, the one summary line, no traceback, no RCLError."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from interfaces import REPO, ros_test_domain_id

from gd_completion.bags.messages import pointcloud2_msg
from gd_completion.bags.typestore import POINTCLOUD2, serialize
from gd_completion.bags.writer import add_connection, atomic_bag_writer
from gd_completion.pointcloud2 import write_points

pytestmark = pytest.mark.integration  # processes and ROS nodes

TOPIC = "/points"
MESSAGES = 5          # per pass, 0.1 s apart: a pass of --loop takes 0.4 s
START_TIMEOUT_S = 60.0   # hang guards only, not speed checks
EXIT_TIMEOUT_S = 20.0


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("play_stop") / "small"
    cloud = np.zeros(10, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    with atomic_bag_writer(path) as writer:
        conn = add_connection(writer, TOPIC, POINTCLOUD2)
        for k in range(MESSAGES):
            ns = 1_000_000_000 + k * 100_000_000
            writer.write(conn, ns, serialize(pointcloud2_msg(write_points(cloud), "lidar", ns), POINTCLOUD2))
    return path


def _start_player(bag: Path, tmp_path: Path, domain: int, *args: str) -> subprocess.Popen:
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": str(tmp_path / "roslog"), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "gd_completion.cli", "play", str(bag), "--topics", TOPIC, *args],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@contextmanager
def _ros_and_player() -> Iterator[tuple[int, object, list[subprocess.Popen]]]:
    """(a test ROS domain, an rclpy context on it, a list to put the player in); on leaving, a player still running
    is killed and the context shut down."""
    import rclpy

    domain = ros_test_domain_id()
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    players: list[subprocess.Popen] = []
    try:
        yield domain, context, players
    finally:
        for player in players:
            if player.poll() is None:
                player.kill()
                player.communicate()
        rclpy.shutdown(context=context)


def _stop(player: subprocess.Popen, sig: signal.Signals) -> tuple[str, str]:
    player.send_signal(sig)
    try:
        out, err = player.communicate(timeout=EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        player.kill()
        out, err = player.communicate()
        pytest.fail(f"play did not stop within {EXIT_TIMEOUT_S} s of {sig.name}:\n{err[-2000:]}")
    return out, err


def _assert_clean_stop(player: subprocess.Popen, out: str, err: str, sig: signal.Signals) -> None:
    assert player.returncode == 0, err[-2000:]
    assert "Traceback" not in err and "RCLError" not in err and "KeyboardInterrupt" not in err, err[-2000:]
    assert out.splitlines()[-1:] == [out.strip()] and out.strip().endswith(f"; stopped by {sig.name}"), out


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_signal_stops_a_loop_cleanly(small_bag: Path, tmp_path: Path, sig: signal.Signals) -> None:
    """The player publishes a --loop (a subscriber has received more than one pass) when the signal comes."""
    pytest.importorskip("rclpy")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    with _ros_and_player() as (domain, context, players):
        node = rclpy.create_node("gd_completion_play_stop_test", context=context)
        got: list[bytes] = []
        node.create_subscription(PointCloud2, TOPIC, got.append, QoSProfile(depth=100,
                                 reliability=ReliabilityPolicy.RELIABLE), raw=True)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        player = _start_player(small_bag, tmp_path, domain, "--loop", "--wait-subscribers", "60", "--delay", "0.2")
        players.append(player)
        deadline = time.monotonic() + START_TIMEOUT_S
        while len(got) <= MESSAGES and player.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert len(got) > MESSAGES and player.poll() is None, player.stderr.read() if player.stderr else ""
        out, err = _stop(player, sig)
        _assert_clean_stop(player, out, err, sig)
        published = int(out.split(f"{TOPIC} ")[1].split(";")[0])
        assert published >= len(got) > MESSAGES
        executor.shutdown()
        node.destroy_node()


def test_sigint_while_waiting_for_subscribers(small_bag: Path, tmp_path: Path) -> None:
    """Nobody subscribes: the player is up (its publisher is in the graph), waiting up to 120 s; Ctrl-C ends the
    wait at once, nothing published."""
    pytest.importorskip("rclpy")
    import rclpy

    with _ros_and_player() as (domain, context, players):
        node = rclpy.create_node("gd_completion_play_stop_watcher", context=context)
        player = _start_player(small_bag, tmp_path, domain, "--loop", "--wait-subscribers", "120")
        players.append(player)
        deadline = time.monotonic() + START_TIMEOUT_S
        while node.count_publishers(TOPIC) == 0 and player.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert node.count_publishers(TOPIC) == 1 and player.poll() is None
        out, err = _stop(player, signal.SIGINT)
        _assert_clean_stop(player, out, err, signal.SIGINT)
        assert out.strip() == "published: nothing; stopped by SIGINT"
        node.destroy_node()
