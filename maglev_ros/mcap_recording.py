"""An MCAP file of ROS 2 messages as they arrive (``ros2`` profile, ``cdr`` messages, ``ros2msg``
schemas, zstd chunks): what the recorder node writes; no rclpy.

The file grows under a partial name beside the target (``.<name>.<pid>.partial``) and gets the
target name only when :meth:`McapRecording.close` has written its summary and index and synced it,
so a file under the target name is always complete. A crash (SIGKILL, power) leaves the partial
file: its chunks, flushed every ``flush_period_s``, are readable by a streaming MCAP reader
(``mcap.stream_reader.StreamReader``, ``mcap recover``), and :func:`recover` makes a complete file
of them. Schemas come from :mod:`maglev_ros.msg_definitions`; one channel per topic, registered with
its first message. Log time is the receive time the caller gives, publish time the header stamp
for types that start with a ``std_msgs/Header`` (the receive time otherwise).
"""
from __future__ import annotations

import os
import struct
import time
from pathlib import Path

from maglev_ros.errors import UserError
from maglev_ros.outputs import check_file, fsync_dir

__all__ = ["McapRecording", "header_stamp_ns", "partial_path", "recover", "PROFILE", "LIBRARY"]

PROFILE = "ros2"
LIBRARY = "maglev_ros recorder"
_STAMP = {1: struct.Struct("<iI"), 0: struct.Struct(">iI")}   # CDR encapsulation: 1 LE, 0 BE


def header_stamp_ns(cdr: bytes) -> int | None:
    """The header stamp [ns] of a CDR message whose first field is a std_msgs/Header (right after
    the 4-byte encapsulation), or None when the bytes are too short or the stamp is negative."""
    if len(cdr) < 12 or cdr[0] != 0 or cdr[1] not in _STAMP:
        return None
    sec, nsec = _STAMP[cdr[1]].unpack_from(cdr, 4)
    if sec < 0 or nsec >= 1_000_000_000:
        return None
    return sec * 1_000_000_000 + nsec


def partial_path(target: Path) -> Path:
    """Where a recording to ``target`` grows until it is closed."""
    return target.with_name(f".{target.name}.{os.getpid()}.partial")


class McapRecording:
    """``McapRecording(path, metadata=None, flush_period_s=5.0)``; ``open()``, ``write(...)``,
    ``close()`` (or a context manager; leaving it with an error keeps the partial file).

    ``metadata``: string key/values stored as an MCAP metadata record named ``maglev_ros``.
    ``counts``: messages written per topic.
    """

    def __init__(self, path, metadata: dict | None = None, flush_period_s: float = 5.0,
                 option: str | None = None) -> None:
        self.path = Path(path)
        self.option = option
        self.metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self.flush_period_s = float(flush_period_s)
        self.partial: Path | None = None
        self.counts: dict[str, int] = {}
        self._writer = None
        self._file = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, bool]] = {}     # topic -> (channel id, has header)
        self._types: dict[str, str] = {}
        self._last_flush = time.monotonic()
        self._dirty = False

    # ------------------------------------------------------------------------ lifecycle
    def open(self) -> "McapRecording":
        from mcap.writer import CompressionType, Writer

        check_file(self.path, self.option)
        self.partial = partial_path(self.path)
        try:
            fd = os.open(self.partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), 0o666)
            self._file = os.fdopen(fd, "wb")
        except OSError as exc:
            raise UserError(f"{self._label()}: cannot write {self.partial} ({exc.strerror or exc})") from None
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        if self.metadata:
            self._writer.add_metadata("maglev_ros", self.metadata)
        return self

    def __enter__(self) -> "McapRecording":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abandon()
        return False

    def _label(self) -> str:
        return f"{self.option} {self.path}" if self.option else str(self.path)

    @property
    def is_open(self) -> bool:
        return self._writer is not None

    # ------------------------------------------------------------------------- writing
    def _channel(self, topic: str, msgtype: str) -> tuple[int, bool]:
        from maglev_ros.msg_definitions import has_header, message_definition
        ch = self._channels.get(topic)
        if ch is not None:
            if self._types[topic] != msgtype:
                raise UserError(f"{self._label()}: topic {topic} has type {self._types[topic]}, "
                                f"got a message of type {msgtype}")
            return ch
        sid = self._schemas.get(msgtype)
        if sid is None:
            sid = self._writer.register_schema(msgtype, "ros2msg", message_definition(msgtype).encode())
            self._schemas[msgtype] = sid
        cid = self._writer.register_channel(topic, "cdr", sid)
        self._channels[topic] = ch = (cid, has_header(msgtype))
        self._types[topic] = msgtype
        self.counts[topic] = 0
        return ch

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Register ``topic`` now (readers list it even if no message follows)."""
        self._channel(topic, msgtype)

    def write(self, topic: str, msgtype: str, cdr: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """One serialized message (``pkg/msg/Type``, CDR bytes) received at ``log_time_ns``;
        publish time ``publish_time_ns`` or, when None, the header stamp (else the receive time)."""
        cid, stamped = self._channel(topic, msgtype)
        publish = publish_time_ns
        if publish is None and stamped:
            publish = header_stamp_ns(cdr)
        seq = self.counts[topic]
        self._writer.add_message(cid, log_time=int(log_time_ns), data=bytes(cdr),
                                 publish_time=int(log_time_ns if publish is None else publish),
                                 sequence=seq & 0xFFFFFFFF)
        self.counts[topic] = seq + 1
        self._dirty = True

    def flush_if_due(self) -> bool:
        """End the open chunk and push it to the file when ``flush_period_s`` has passed since the
        last flush (a crash then loses at most that much); True when it flushed."""
        if not self._dirty or time.monotonic() - self._last_flush < self.flush_period_s:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """End the open chunk and push what was written to the file (not fsynced)."""
        self._writer.flush()
        self._last_flush = time.monotonic()
        self._dirty = False

    def close(self) -> Path:
        """Write the summary and index, sync, rename to the target; returns the target path."""
        if self._writer is None:
            raise UserError(f"{self._label()}: recording is not open")
        writer, self._writer = self._writer, None
        try:
            writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self.partial, self.path)
            fsync_dir(self.path.parent)
        except OSError as exc:
            raise UserError(f"{self._label()}: cannot finish the recording ({exc.strerror or exc}); "
                            f"what was written so far is in {self.partial}") from None
        return self.path

    def abandon(self) -> Path | None:
        """Stop without a summary: flush what was written and keep the partial file (for
        :func:`recover`); returns its path."""
        if self._writer is None:
            return None
        writer, self._writer = self._writer, None
        try:
            writer.flush()
            self._file.close()
        except OSError:
            pass
        return self.partial


def recover(partial, target) -> dict[str, int]:
    """A complete MCAP at ``target`` from the readable records of a partial recording (a crashed
    recorder's ``.partial`` file): every whole chunk is kept, a torn last one is dropped.
    Returns the messages kept per topic."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    partial, target = Path(partial), Path(target)
    schemas, channels, kept = {}, {}, {}
    rec = McapRecording(target)
    with open(partial, "rb") as f:
        rec.open()
        try:
            records = StreamReader(f, skip_magic=False).records
            while True:
                try:
                    r = next(records)
                except StopIteration:
                    break
                except (McapError, EOFError, ValueError, struct.error):
                    break                      # the torn end of a crashed recording
                if isinstance(r, Schema):
                    schemas[r.id] = r.name
                elif isinstance(r, Channel):
                    channels[r.id] = (r.topic, schemas.get(r.schema_id, ""))
                elif isinstance(r, Metadata) and r.name == "maglev_ros":
                    rec._writer.add_metadata(r.name, dict(r.metadata))
                elif isinstance(r, Message) and r.channel_id in channels:
                    topic, msgtype = channels[r.channel_id]
                    rec.write(topic, msgtype, r.data, r.log_time, r.publish_time)
                    kept[topic] = kept.get(topic, 0) + 1
        except BaseException:
            rec.abandon()
            raise
    rec.close()
    return kept
