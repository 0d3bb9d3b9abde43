"""Outputs that cannot be written (a file where a folder should be, a full disk, a file size limit) end every
writing verb with one error line naming the output and the cause, exit code 2, and nothing left behind."""
from __future__ import annotations

import errno
import subprocess
import sys
from pathlib import Path

import pytest

from gd_completion.cli import main

KITTI = "kitti-object-sample/training"
HESAI_BAG = "hesai-nebula/40p/1673400149412331409"
HESAI_CALIBRATION = "hesai-nebula/calibration/Pandar40P.csv"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def kitti_bag(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first two frames of the KITTI sample as an MCAP bag."""
    out = tmp_path_factory.mktemp("bags") / "kitti"
    assert main(["convert", "kitti", str(shared_data / KITTI), str(out), "--frames", "2", "--quiet"]) == 0
    return out


def _files(folder: Path) -> list[str]:
    """Every file and folder under `folder`, hidden ones included."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _error_line(capsys: pytest.CaptureFixture, verb: str) -> str:
    """The one line on stderr, which must be `verb`'s error line (no traceback)."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gd-completion {verb}: error: "), lines
    return lines[0]


VERBS = {
    "convert kitti": lambda data, bag, out: ["convert", "kitti", str(data / KITTI), str(out), "--frames", "1"],
    "convert pandaset": lambda data, bag, out: ["convert", "pandaset", str(data / "pandaset-002"), str(out),
                                                "--frames", "1", "--sensors", "0"],
    "convert hesai": lambda data, bag, out: ["convert", "hesai", str(data / HESAI_BAG), str(out),
                                             "--calibration", str(data / HESAI_CALIBRATION)],
    "complete": lambda data, bag, out: ["complete", str(bag), str(out), "--threads", "1"],
    "render": lambda data, bag, out: ["render", str(bag), str(out), "--frame", "1"],
    "demo": lambda data, bag, out: ["demo", "--output", str(out), "--frames", "1", "--vehicles", "1"],
    "train": lambda data, bag, out: ["train", "--output", str(out), "--samples", "4", "--val-samples", "2"],
    "evaluate": lambda data, bag, out: ["evaluate", "--output", str(out), "--synthetic-samples", "0",
                                        "--no-pandaset"],
}


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_output_under_a_regular_file(verb: str, shared_data: Path, kitti_bag: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture) -> None:
    """Root ignores folder permissions, so the unwritable place is a path through a regular file."""
    blocker = tmp_path / "notes.txt"
    blocker.write_text("a file, not a folder\n")
    out = blocker / "sub" / ("frame.png" if verb == "render" else "out")
    code = main(VERBS[verb](shared_data, kitti_bag, out))
    line = _error_line(capsys, verb.split()[0])
    assert code == 2
    assert line.endswith(f": error: {out}: cannot write: {blocker} is a file, not a folder"), line
    assert _files(tmp_path) == ["notes.txt"] and blocker.read_text() == "a file, not a folder\n"


class _FillingFile:
    """A file object on a disk that fills up after `room` bytes: the bytes that fit are written, then ENOSPC."""

    def __init__(self, stream, room: int) -> None:
        self.stream, self.room = stream, room

    def write(self, data) -> int:
        if len(data) > self.room:
            self.stream.write(bytes(data[: self.room]))
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.stream.write(data)

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_disk_full_while_completing(storage: str, kitti_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture) -> None:
    """The disk fills up after the first cloud: MCAP's file write fails with ENOSPC; sqlite3 reaches its page limit
    (SQLITE_FULL, what a full disk gives it)."""
    from rosbags.rosbag2 import storage_mcap, storage_sqlite3

    if storage == "mcap":
        opened = storage_mcap.McapWriter.__init__

        def small_disk(self, *args) -> None:
            opened(self, *args)
            self.bio = _FillingFile(self.bio, 2_500_000)  # one 1.9 MB KITTI cloud fits, the second does not

        monkeypatch.setattr(storage_mcap.McapWriter, "__init__", small_disk)
        cause = "No space left on device"
    else:
        opened = storage_sqlite3.Sqlite3Writer.__init__

        def small_disk(self, *args) -> None:
            opened(self, *args)
            self.conn.execute("PRAGMA max_page_count = 600")  # 600 pages of 4 kB

        monkeypatch.setattr(storage_sqlite3.Sqlite3Writer, "__init__", small_disk)
        cause = "database or disk is full"
    out = tmp_path / "completed"
    code = main(["complete", str(kitti_bag), str(out), "--storage", storage, "--threads", "1", "--quiet"])
    line = _error_line(capsys, "complete")
    assert code == 2 and line.endswith(f": error: {out}: cannot write: {cause}"), line
    assert _files(tmp_path) == []  # neither the output nor its temporary


FILE_SIZE_LIMIT = """
import resource, sys
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))
from gd_completion.cli import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.integration
@pytest.mark.parametrize("case", ["mcap", "sqlite3", "png"])
def test_file_size_limit(case: str, shared_data: Path, kitti_bag: Path, tmp_path: Path) -> None:
    """The kernel refuses the writes beyond a file size limit (RLIMIT_FSIZE, like a full disk or a quota), in a
    process of its own: one error line, exit 2, no output and no temporary."""
    out = tmp_path / ("frame.png" if case == "png" else "out")
    if case == "png":
        limit, argv = 20_000, ["render", str(kitti_bag), str(out)]
    else:
        limit, argv = 3_000_000, ["convert", "kitti", str(shared_data / KITTI), str(out), "--storage", case,
                                  "--quiet"]
    proc = subprocess.run([sys.executable, "-c", FILE_SIZE_LIMIT, str(limit), *argv], cwd=REPO, capture_output=True,
                          text=True, timeout=300, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    verb = argv[0]
    cause = "disk I/O error" if case == "sqlite3" else "File too large"
    assert lines[0] == f"gd-completion {verb}: error: {out}: cannot write: {cause}"
    assert _files(tmp_path) == []


def test_render_refuses_to_overwrite(kitti_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """As `complete` and `convert`: an existing output is replaced only with --overwrite, checked before any work."""
    frame, vehicles = tmp_path / "frame.png", tmp_path / "vehicles.png"
    vehicles.write_bytes(b"an older render")
    code = main(["render", str(kitti_bag), str(frame), "--vehicles", str(vehicles)])
    line = _error_line(capsys, "render")
    assert code == 2 and line.endswith(f"error: {vehicles}: output exists already (use --overwrite to replace it)")
    assert _files(tmp_path) == ["vehicles.png"] and vehicles.read_bytes() == b"an older render"

    frame.write_bytes(b"an older render")
    assert main(["render", str(kitti_bag), str(frame), "--frame", "1"]) == 2
    assert "output exists already" in _error_line(capsys, "render") and frame.read_bytes() == b"an older render"
    assert main(["render", str(kitti_bag), str(frame), "--frame", "1", "--overwrite"]) == 0
    assert frame.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and _files(tmp_path) == ["frame.png", "vehicles.png"]


def test_checkpoint_save_on_a_full_disk_is_an_output_error(tmp_path, monkeypatch):
    import torch
    from test_model import TINY

    from gd_completion.errors import OutputError
    from gd_completion.model import GGDNet, save_checkpoint

    def full_disk(obj, f, *args, **kwargs):
        with open(f, "wb") as handle:
            handle.write(b"PK")                # a partial write, then the zip writer's error
        raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")
    monkeypatch.setattr(torch, "save", full_disk)
    target = tmp_path / "ckpt" / "last.pt"
    with pytest.raises(OutputError, match="last.pt: cannot write: PytorchStreamWriter failed"):
        save_checkpoint(target, GGDNet(TINY))
    assert not target.exists() and list(target.parent.iterdir()) == []
