"""ROS_DOMAIN_IDs for tests: each held through an exclusive lock file for the life of the process, so that
concurrent test runs on one machine never share a domain (and never see each other's nodes and topics)."""
from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

# Fast DDS maps domain d to UDP ports from 7400 + 250 d: 232 is the highest id it accepts. Ids below 100 are
# left to the ROS graphs people start by hand.
FIRST_ID, LAST_ID = 100, 232
LOCK_DIR = Path(tempfile.gettempdir())

_held: dict[str, tuple[int, int]] = {}  # name -> (domain id, file descriptor holding its lock)


def lock_path(domain: int) -> Path:
    """The lock file of `domain`."""
    return LOCK_DIR / f"gd_completion_ros_domain_{domain}.lock"


def allocate_domain_id(name: str = "default") -> int:
    """This process's domain id for `name` (the same on every call, another for every name): the first id in
    FIRST_ID..LAST_ID whose lock file no process holds; the lock is kept until the process exits."""
    if name in _held:
        return _held[name][0]
    for domain in range(FIRST_ID, LAST_ID + 1):
        try:
            fd = os.open(lock_path(domain), os.O_RDWR | os.O_CREAT, 0o666)
        except OSError:  # e.g. another user's lock file: that user's tests may be on this domain
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # conflicts with every other open(), in any process
        except OSError:
            os.close(fd)
            continue
        _held[name] = (domain, fd)
        return domain
    raise RuntimeError(f"no free ROS domain id in {FIRST_ID}..{LAST_ID}: all locked under {LOCK_DIR}")
