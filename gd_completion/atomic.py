"""Atomic file writes: write to a hidden partial file beside the target, rename on success; write failures raise
OutputError naming the target and the cause."""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from gd_completion.errors import OutputError


def output_error(path: str | os.PathLike, error: BaseException, *, folder: bool = False) -> OutputError:
    """OutputError naming `path` (a `folder` or a file) and why it cannot be written: a file where a folder should
    be, the system's reason ('No space left on device', 'Permission denied') or the storage library's message."""
    path = Path(path)
    folders = [path, *path.parents] if folder else path.parents
    blocker = next((p for p in folders if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        reason = f"{blocker} is a file, not a folder"
    elif isinstance(error, OSError) and error.strerror:
        where = Path(error.filename) if error.filename else None
        reason = error.strerror + (f" ({where})" if where in path.parents else "")
    else:
        reason = str(error) or type(error).__name__
    return OutputError(f"{path}: cannot write: {reason}")


def refuse_existing(path: str | os.PathLike, overwrite: bool) -> None:
    """OutputError when `path` exists and `overwrite` is not set: every verb replaces an output only when asked."""
    if not overwrite and Path(path).exists():
        raise OutputError(f"{path}: output exists already (use --overwrite to replace it)")


def make_folder(path: str | os.PathLike, output: str | os.PathLike | None = None) -> Path:
    """Create the folder `path` and its parents; when that is impossible, OutputError naming `output` (the file
    to be written in it) or else the folder."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise output_error(output or path, error, folder=output is None) from error
    return path


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path` (parent folders created) to write to; on success it replaces
    `path`, on an error it is removed, so `path` never holds a half-written file. An OSError of the write itself
    (no file name, or the temporary's) or of the rename becomes an OutputError naming `path`."""
    path = Path(path)
    make_folder(path.parent, path)
    tmp = path.with_name(f".{path.name}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as error:
        if error.filename is not None and str(error.filename) not in (str(tmp), str(path)):
            raise  # a file the caller read, not this output
        raise output_error(path, error) from error
    finally:
        with suppress(OSError):
            tmp.unlink(missing_ok=True)
