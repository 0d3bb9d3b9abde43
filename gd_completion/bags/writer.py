"""Writing rosbag2 recordings atomically (temporary name, rename on success) and adding their connections."""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gd_completion.bags.typestore import require_type, typestore
from gd_completion.errors import BagError

if TYPE_CHECKING:
    from rosbags.rosbag2 import Writer

STORAGES = ("mcap", "sqlite3")
BAG_VERSION = 9


def storage_plugin(storage: str):
    """rosbags StoragePlugin for 'mcap' or 'sqlite3'."""
    from rosbags.rosbag2 import StoragePlugin

    try:
        return {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    except KeyError:
        raise BagError(f"unknown storage {storage!r}; expected one of {', '.join(STORAGES)}") from None


@contextmanager
def atomic_bag_writer(path: str | Path, *, storage: str = "mcap", overwrite: bool = False) -> Iterator[Writer]:
    """Open a rosbag2 writer under a temporary name beside `path`; rename to `path` only on success.

    On any exception the temporary bag is deleted and nothing appears under `path`.
    """
    from rosbags.rosbag2 import Writer, WriterError

    final = Path(path)
    if final.exists() and not overwrite:
        raise BagError(f"{final}: output exists already (use --overwrite to replace it)")
    parent = final.parent if str(final.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=parent))
    tmp_bag = scratch / final.name
    writer = Writer(tmp_bag, version=BAG_VERSION, storage_plugin=storage_plugin(storage))
    try:
        writer.open()
        yield writer
        writer.close()
        # rosbags names the storage file after the directory; keep that name (same stem as the final bag).
        if final.exists():
            shutil.rmtree(final) if final.is_dir() else final.unlink()
        os.replace(tmp_bag, final)
    except BaseException as error:
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


def copy_connection(writer: Writer, conn: Any, src: str | Path) -> Any:
    """Add `conn` (topic, type, definition, hash, QoS) of an input bag to `writer` unchanged."""
    msgdef, digest = conn.msgdef.data, conn.digest
    if not msgdef or not digest:  # bags older than rosbag2 v8 store no definitions
        if conn.msgtype not in typestore().types:
            raise BagError(f"{src}: topic {conn.topic} has unknown type {conn.msgtype} and no definition")
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
