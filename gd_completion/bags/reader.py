"""Reading rosbag2 recordings (folder, .mcap or .db3): open, iterate raw messages; errors name the bag."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gd_completion.errors import BagError

if TYPE_CHECKING:
    from rosbags.rosbag2 import Reader


@contextmanager
def open_bag(path: str | Path) -> Iterator[Reader]:
    """Open a rosbag2 (directory, .mcap or .db3) for reading; problems raise BagError naming the file."""
    from rosbags.rosbag2 import Reader

    bag = Path(path)
    if not bag.exists():
        raise BagError(f"{bag}: no such bag")
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as error:
        raise BagError(f"{bag}: cannot open bag: {error}") from error
    try:
        yield reader
    finally:
        try:
            reader.close()
        except Exception:
            pass


def iter_raw(reader: Reader, connections=None) -> Iterator[tuple[Any, int, bytes]]:
    """Messages as (connection, bag timestamp ns, raw serialized bytes); corrupt storage raises BagError."""
    try:
        yield from reader.messages(connections=connections or ())
    except BagError:
        raise
    except Exception as error:
        raise BagError(f"{reader.path}: cannot read messages (truncated or corrupt bag?): {error}") from error
