"""Writing rosbag2 recordings atomically (temporary name, rename on success) and adding their connections."""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from functools import lru_cache, wraps
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from gd_completion.atomic import make_folder, output_error, refuse_existing
from gd_completion.bags.typestore import require_type, typestore
from gd_completion.errors import BagError

if TYPE_CHECKING:
    from rosbags.rosbag2 import Writer

STORAGES = ("mcap", "sqlite3")
BAG_VERSION: Literal[9] = 9


def storage_plugin(storage: str):
    """rosbags StoragePlugin for 'mcap' or 'sqlite3'."""
    from rosbags.rosbag2 import StoragePlugin

    try:
        return {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    except KeyError:
        raise BagError(f"unknown storage {storage!r}; expected one of {', '.join(STORAGES)}") from None


@lru_cache(maxsize=1)
def _writer_class() -> type[Writer]:
    """rosbags' Writer whose storage failures (an OSError such as a full disk, a sqlite3 error) raise OutputError
    naming the bag's final path, `final`; errors of the caller's own code pass through unchanged."""
    import sqlite3

    from rosbags.rosbag2 import Writer

    def guarded(method: Callable[..., Any]) -> Callable[..., Any]:
        @wraps(method)
        def call(self: Any, *args: Any, **kwargs: Any) -> Any:
            try:
                return method(self, *args, **kwargs)
            except (OSError, sqlite3.Error) as error:
                raise output_error(self.final, error) from error
        return call

    methods = ("open", "add_connection", "write", "close")
    return type("OutputWriter", (Writer,), {"final": Path(), **{m: guarded(getattr(Writer, m)) for m in methods}})


@contextmanager
def atomic_bag_writer(path: str | Path, *, storage: str = "mcap", overwrite: bool = False) -> Iterator[Writer]:
    """Open a rosbag2 writer under a temporary name beside `path`; rename to `path` only on success.

    On any exception the temporary bag is deleted and nothing appears under `path`. Failures to write (a file
    where a folder should be, no permission, a full disk) raise OutputError naming `path` and the cause.
    """
    from rosbags.rosbag2 import WriterError

    final = Path(path)
    plugin = storage_plugin(storage)
    refuse_existing(final, overwrite)
    parent = make_folder(final.parent, final)
    try:
        scratch = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=parent))
    except OSError as error:
        raise output_error(final, error) from error
    tmp_bag = scratch / final.name
    writer = _writer_class()(tmp_bag, version=BAG_VERSION, storage_plugin=plugin)
    writer.final = final  # type: ignore[attr-defined]  # read by the _writer_class subclass's error wrapper
    try:
        writer.open()
        yield writer
        writer.close()
        # rosbags names the storage file after the directory; keep that name (same stem as the final bag).
        try:
            if final.exists():
                shutil.rmtree(final) if final.is_dir() else final.unlink()
            os.replace(tmp_bag, final)
        except OSError as error:
            raise output_error(final, error) from error
    except BaseException as error:
        with suppress(Exception):  # a full disk can fail the abort's own flush as well
            writer.abort()
        if isinstance(error, WriterError):
            raise BagError(f"{final}: cannot write bag: {error}") from error
        raise
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def add_connection(writer: Writer, topic: str, msgtype: str, *, latched: bool = False):
    """Register `topic` with the definition from the typestore (transient-local QoS when latched)."""
    require_type(msgtype)
    qos = (latched_qos(),) if latched else ()
    return writer.add_connection(topic, msgtype, typestore=typestore(), offered_qos_profiles=qos)


def has_definition(conn: Any) -> bool:
    """Whether a connection of an input bag can be copied: its definition and hash are stored in the bag (rosbag2
    v8 and later), or its type is in the typestore."""
    return bool(conn.msgdef.data and conn.digest) or conn.msgtype in typestore().types


def copy_connection(writer: Writer, conn: Any, src: str | Path) -> Any:
    """Add `conn` (topic, type, definition, hash, QoS) of an input bag to `writer` unchanged."""
    msgdef, digest = conn.msgdef.data, conn.digest
    if not msgdef or not digest:  # bags older than rosbag2 v8 store no definitions
        if not has_definition(conn):
            raise BagError(f"{src}: topic {conn.topic} has unknown type {conn.msgtype} and no stored definition, "
                           "so it cannot be copied (--skip-unknown-types leaves such topics out)")
        msgdef, _ = typestore().generate_msgdef(conn.msgtype, ros_version=2)
        digest = typestore().hash_rihs01(conn.msgtype)
    return writer.add_connection(conn.topic, conn.msgtype, msgdef=msgdef, rihs01=digest,
                                 serialization_format=conn.ext.serialization_format,
                                 offered_qos_profiles=conn.ext.offered_qos_profiles)


def latched_qos() -> Any:
    """Reliable, transient-local, keep-last-1 QoS (what /tf_static publishers offer)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL, deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)
