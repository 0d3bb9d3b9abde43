"""atomic_path: the target holds the old content or the complete new one, never a partial file."""
from __future__ import annotations

import errno
import re

import pytest

from gd_completion.atomic import atomic_path, output_error
from gd_completion.errors import OutputError


def test_success_replaces_and_error_keeps_old_content(tmp_path):
    target = tmp_path / "sub" / "report.md"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp != target
        tmp.write_text("first")
    assert target.read_text() == "first"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("writer failed")
    assert target.read_text() == "first"
    assert sorted(p.name for p in target.parent.iterdir()) == ["report.md"]


def test_write_failures_name_the_target_and_leave_nothing(tmp_path):
    blocker = tmp_path / "notes.txt"
    blocker.write_text("a file")
    message = f"{blocker}/report.md: cannot write: {blocker} is a file, not a folder"
    with pytest.raises(OutputError, match=re.escape(message)):
        with atomic_path(blocker / "report.md") as tmp:
            tmp.write_text("never")
    target = tmp_path / "report.md"
    with pytest.raises(OutputError, match=re.escape(f"{target}: cannot write: No space left on device")):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise OSError(errno.ENOSPC, "No space left on device")  # what a write to a full disk raises
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_errors_of_other_files_pass_through(tmp_path):
    """An OSError naming another file (an input the caller reads) is not this output's failure."""
    with pytest.raises(FileNotFoundError) as raised:
        with atomic_path(tmp_path / "out.txt") as tmp:
            tmp.write_text((tmp_path / "missing_input.txt").read_text())
    assert raised.value.filename == str(tmp_path / "missing_input.txt")
    assert list(tmp_path.iterdir()) == []


def test_permission_error_names_the_refusing_folder(tmp_path):
    """What a non-root user gets from a folder without write permission (root, running the tests, is never refused):
    the system's reason, and the folder when it is one of the output's."""
    target = tmp_path / "out" / "frame.png"
    error = PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "out"))
    assert str(output_error(target, error)) == f"{target}: cannot write: Permission denied ({tmp_path / 'out'})"
