"""BagWriter: write contract bags (rosbag2, MCAP storage by default, sqlite3 on request).

The bag is written into a hidden temporary directory beside the target and renamed to the
final name only when it is closed without error, so a crash never leaves a half-written bag
under the final name. Writing goes through rosbags (no rclpy).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from maglev_ros.contract import (SENSORBLOCK_TYPE, STRING_TYPE, TOPIC_METADATA, Metadata,
                                 metadata_from_dict)
from maglev_ros.errors import UserError
from maglev_ros.outputs import fsync_dir
from maglev_ros.sensor_block import Block, block_to_msg, msgtype_name, string_msg, typestore

__all__ = ["BagWriter", "STORAGES"]

STORAGES = ("mcap", "sqlite3")


class BagWriter:
    """Context manager writing one contract bag.

    ``BagWriter(path, metadata, storage="mcap", overwrite=False, metadata_stamp_ns=None)``

    - ``metadata``: the metadata JSON document (dict or :class:`Metadata`); validated against
      the contract (ContractError on a problem) unless ``validate=False``.
    - The metadata is the first message of the bag, on ``/testline/metadata``
      (std_msgs/msg/String). Its stamp is ``metadata_stamp_ns`` or, when None, the stamp of the
      first message written (so it is written lazily, just before that message).
    - ``write_block(topic, block, log_time_ns=None)``: one SensorBlock; the bag's receive time
      is ``log_time_ns`` (default: the block's header stamp).
    - ``write_message(topic, msgtype, msg_or_cdr, stamp_ns)``: any registered type (our
      maglev_msgs types or ROS 2 built-ins), a rosbags message object or raw CDR bytes.
    """

    def __init__(self, path: str | os.PathLike, metadata: Mapping[str, Any] | Metadata,
                 storage: str = "mcap", overwrite: bool = False,
                 metadata_stamp_ns: int | None = None, validate: bool = True) -> None:
        self.path = Path(path)
        if storage not in STORAGES:
            raise UserError(f"{self.path}: storage must be one of {', '.join(STORAGES)}, got {storage!r}")
        self.storage = storage
        self.overwrite = overwrite
        raw = metadata.raw if isinstance(metadata, Metadata) else metadata
        if validate:
            metadata_from_dict(raw, f"{self.path} (metadata to write)")
        self.metadata_json = json.dumps(raw)
        self.metadata_stamp_ns = metadata_stamp_ns
        self._meta_written = False
        self._writer = None
        self._tmpdir: Path | None = None
        self._connections: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self._store = typestore()
        self.counts: dict[str, int] = {}

    # -------------------------------------------------------------------------- lifecycle
    def open(self) -> "BagWriter":
        from rosbags.rosbag2 import StoragePlugin, Writer

        if self._writer is not None:
            raise UserError(f"{self.path}: BagWriter already open")
        if (self.path.exists() or self.path.is_symlink()) and not self.overwrite:
            raise UserError(f"{self.path}: already exists; refusing to overwrite "
                            "(pass overwrite=True / --overwrite)")
        parent = self.path.parent if str(self.path.parent) else Path(".")
        if not parent.is_dir():
            raise UserError(f"{self.path}: parent directory {parent} does not exist")
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.partial-", dir=parent))
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self._tmpdir / self.path.name, version=9, storage_plugin=plugin)
        self._writer.open()
        if self.metadata_stamp_ns is not None:
            self._write_metadata(self.metadata_stamp_ns)
        return self

    def close(self) -> Path:
        """Finish the bag, fsync it and move it to its final name; returns the final path.

        On any failure the partial bag is removed and what was at the final path stays; an
        OSError becomes a one-line UserError naming the bag and the OS reason."""
        if self._writer is None:
            raise UserError(f"{self.path}: BagWriter is not open")
        writer = self._writer
        try:
            if not self._meta_written:
                self._write_metadata(0)
            writer.close()
            self._writer = None
            tmp_bag = self._tmpdir / self.path.name
            _fsync_tree(tmp_bag)
            old = None
            if self.path.exists() or self.path.is_symlink():
                # moved aside, not deleted, until the new bag is in place
                old = self._tmpdir / ".replaced"
                os.replace(self.path, old)
            try:
                os.replace(tmp_bag, self.path)
            except OSError:
                if old is not None:
                    os.replace(old, self.path)
                raise
            fsync_dir(self.path.parent)
        except OSError as exc:
            self.abort()
            raise UserError(f"{self.path}: cannot write the bag ({exc.strerror or exc})") from None
        except BaseException:
            self.abort()
            raise
        shutil.rmtree(self._tmpdir, ignore_errors=True)
        self._tmpdir = None
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; the final path is left untouched."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.storage.abort() if writer.storage is not None else None
            except Exception:  # noqa: BLE001 - best effort cleanup of a failed write
                pass
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False

    # ---------------------------------------------------------------------------- writing
    def _connection(self, topic: str, msgtype: str):
        conn = self._connections.get(topic)
        if conn is None:
            if msgtype not in self._store.types:
                raise UserError(f"{self.path}: unknown message type {msgtype!r} for topic {topic}")
            conn = self._writer.add_connection(topic, msgtype, typestore=self._store)
            self._connections[topic] = conn
            self._types[topic] = msgtype
            self.counts[topic] = 0
        elif self._types[topic] != msgtype:
            raise UserError(f"{self.path}: topic {topic} already has type {self._types[topic]}, "
                            f"cannot write {msgtype}")
        return conn

    def _write_metadata(self, stamp_ns: int) -> None:
        self._meta_written = True
        self._raw_write(TOPIC_METADATA, STRING_TYPE,
                        self._store.serialize_cdr(string_msg(self.metadata_json, self._store),
                                                  STRING_TYPE), int(stamp_ns))

    def _raw_write(self, topic: str, msgtype: str, cdr, log_ns: int) -> None:
        conn = self._connection(topic, msgtype)
        self._writer.write(conn, int(log_ns), cdr)
        self.counts[topic] += 1

    def _check_open(self, stamp_ns: int) -> None:
        if self._writer is None:
            raise UserError(f"{self.path}: BagWriter is not open (use it as a context manager)")
        if not self._meta_written:
            self._write_metadata(stamp_ns)

    def write_block(self, topic: str, block: Block, log_time_ns: int | None = None) -> None:
        """Write one SensorBlock on ``topic``."""
        if topic == TOPIC_METADATA:
            raise UserError(f"{self.path}: {TOPIC_METADATA} is written by BagWriter itself")
        if not isinstance(block, Block):
            raise UserError(f"{self.path}: write_block({topic}) needs a Block, got {type(block).__name__}")
        if block.data.ndim != 2 or block.data.shape[1] != len(block.channels) \
                or len(block.units) != len(block.channels):
            raise UserError(f"{self.path}: {topic}: block data {block.data.shape} does not match "
                            f"{len(block.channels)} channels / {len(block.units)} units")
        log_ns = block.stamp_ns if log_time_ns is None else int(log_time_ns)
        self._check_open(min(log_ns, block.stamp_ns))
        cdr = self._store.serialize_cdr(block_to_msg(block, self._store), SENSORBLOCK_TYPE)
        self._raw_write(topic, SENSORBLOCK_TYPE, cdr, log_ns)

    def write_message(self, topic: str, msgtype: str, msg_or_cdr, stamp_ns: int) -> None:
        """Write any registered message type (object or raw CDR bytes) with receive time stamp_ns."""
        if topic == TOPIC_METADATA:
            raise UserError(f"{self.path}: {TOPIC_METADATA} is written by BagWriter itself")
        msgtype = msgtype_name(msgtype)
        self._check_open(int(stamp_ns))
        if isinstance(msg_or_cdr, (bytes, bytearray, memoryview)):
            cdr = msg_or_cdr
        else:
            try:
                cdr = self._store.serialize_cdr(msg_or_cdr, msgtype)
            except Exception as exc:  # rosbags raises assorted errors for a wrong object
                raise UserError(f"{self.path}: {topic}: cannot serialise message as {msgtype}: "
                                f"{exc}") from None
        self._raw_write(topic, msgtype, cdr, int(stamp_ns))

    def write_arrays(self, topic: str, stamp_ns: int, sample_rate_hz: float, channels, units,
                     data: np.ndarray, frame_id: str = "", log_time_ns: int | None = None) -> None:
        """Convenience: build a Block from arrays and write it."""
        self.write_block(topic, Block.from_arrays(stamp_ns, sample_rate_hz, channels, units,
                                                  data, frame_id), log_time_ns)


def _fsync_tree(path: Path) -> None:
    """fsync the files of a finished bag and its directory, so its rename publishes data on disk."""
    for f in sorted(path.rglob("*")):
        if f.is_file() and not f.is_symlink():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
    fsync_dir(path)
