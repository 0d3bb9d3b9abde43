"""ROS domain ids of the tests (test/ros_domain.py): concurrent test processes never share one."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from ros_domain import FIRST_ID, LAST_ID, allocate_domain_id

HOLD_ONE = """
import sys
sys.path.insert(0, sys.argv[1])
from ros_domain import allocate_domain_id
print(allocate_domain_id(), flush=True)
sys.stdin.read()  # hold the id until the test closes our stdin
"""


def test_one_id_per_name_in_a_process():
    a, b = allocate_domain_id("test_a"), allocate_domain_id("test_b")
    assert a != b and FIRST_ID <= min(a, b) and max(a, b) <= LAST_ID
    assert allocate_domain_id("test_a") == a


@pytest.mark.integration
def test_concurrent_processes_get_different_ids():
    mine = allocate_domain_id("test_parent")
    procs = [subprocess.Popen([sys.executable, "-c", HOLD_ONE, str(Path(__file__).parent)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True) for _ in range(2)]
    try:
        ids = [int(p.stdout.readline()) for p in procs]  # both alive and holding their ids
    finally:
        for p in procs:
            p.stdin.close()
            p.wait(timeout=30)
            p.stdout.close()
    assert len({mine, *ids}) == 3 and all(FIRST_ID <= i <= LAST_ID for i in ids)
    assert [p.returncode for p in procs] == [0, 0]
