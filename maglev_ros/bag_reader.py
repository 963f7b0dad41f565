"""BagReader: stream contract bags (rosbag2 MCAP / sqlite3, ROS1 .bag) without rclpy.

Reading goes through rosbags' AnyReader and its generated CDR deserialisers (float32[] comes
back as a numpy view on the message bytes, so no per-sample Python work). Type definitions are
taken from the bag itself (so bags written by anyone from the contract's .msg text decode),
falling back to the suite's typestore.

Times: the header stamp is the truth; the bag's receive time may lag it. ``start_s`` /
``duration_s`` windows are seconds after ``reader.start_time_s`` (the earliest header stamp of
the bag's data topics), while ``Block.stamp_ns`` and ``ChannelData.time_s`` are absolute stream
time (header stamp).

Contract checks (:meth:`BagReader.check`) stream over the bag, keeping only one small record
per block (stamp, length, rate, data digest) to find gaps, overlaps, disorder and duplicates.
"""
from __future__ import annotations

import hashlib
import os
import struct
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from maglev_ros.contract import (SENSORBLOCK_TYPE, STRING_TYPE, TOPIC_METADATA, Issue, Metadata,
                                 check_units, metadata_issues, parse_metadata)
from maglev_ros.errors import ContractError, UserError
from maglev_ros.sensor_block import (Block, DecodedBlock, SensorBlockDecoder,
                                     same_sensorblock_definition, typestore)

__all__ = ["BagReader", "TopicInfo", "ChannelData", "Issue", "SENSORBLOCK_FIELDS"]

SENSORBLOCK_FIELDS = ("header", "sample_rate_hz", "channels", "units", "data")
#: How far (beyond the lag seen on the first message) receive time may lag a header stamp
#: before a windowed read stops scanning.
LAG_SLACK_NS = 10_000_000_000
#: At most this many issues of one kind per topic are listed; the rest are summarised.
MAX_ISSUES_PER_KIND = 20
#: Header stamp (int32 sec, uint32 nanosec) right after the 4-byte CDR encapsulation.
_STAMP_LE = struct.Struct("<iI")


@dataclass(frozen=True)
class TopicInfo:
    """What one topic of the bag holds (channels/units/rate from its first message)."""

    topic: str
    msgtype: str
    count: int
    channels: tuple[str, ...] = ()
    units: tuple[str, ...] = ()
    sample_rate_hz: float | None = None
    frame_id: str | None = None
    first_stamp_ns: int | None = None
    first_lag_ns: int | None = None       # receive time - header stamp of the first message
    block_samples: int | None = None      # samples in the first block

    @property
    def is_sensor_block(self) -> bool:
        return self.msgtype == SENSORBLOCK_TYPE

    def to_dict(self) -> dict:
        d = {"topic": self.topic, "type": self.msgtype, "count": self.count}
        if self.is_sensor_block:
            d.update({"channels": list(self.channels), "units": list(self.units),
                      "sample_rate_hz": self.sample_rate_hz, "frame_id": self.frame_id,
                      "block_samples": self.block_samples,
                      "first_stamp_s": None if self.first_stamp_ns is None
                      else self.first_stamp_ns * 1e-9})
        return d


@dataclass(frozen=True, eq=False)
class ChannelData:
    """A whole topic (or a window of it) as arrays. Gaps are kept (time jumps, no NaN fill).

    ``time_s`` (n,) stream time of each sample; ``data`` (n, c) float64; ``issues`` lists what
    was repaired while reading (duplicates dropped, disorder sorted, overlaps trimmed).
    """

    topic: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    sample_rate_hz: float
    time_s: np.ndarray
    data: np.ndarray
    issues: tuple[Issue, ...] = field(default=())

    def channel(self, name: str) -> np.ndarray:
        try:
            return self.data[:, self.channels.index(name)]
        except ValueError:
            raise UserError(f"{self.topic}: no channel {name!r} "
                            f"(channels: {', '.join(self.channels)})") from None

    @property
    def n_samples(self) -> int:
        return int(self.time_s.shape[0])

    def unit(self, name: str) -> str:
        return self.units[self.channels.index(name)]

    @classmethod
    def from_blocks(cls, topic: str, blocks) -> "ChannelData":
        """A topic from its streamed blocks (``sensor_block.Block``, already in SI), as
        :meth:`BagReader.read_topic` makes it of the same blocks in a bag: sorted by stamp, an exact
        repeat of a stamp dropped, blocks with another channel list than the first left out, sample
        times stamp + j / rate in float64 (overlapping blocks are not trimmed here)."""
        bs = sorted((b for b in blocks if b.n_samples), key=lambda b: b.stamp_ns)
        bs = [b for i, b in enumerate(bs) if i == 0 or b.stamp_ns != bs[i - 1].stamp_ns]
        if not bs:
            raise UserError(f"{topic}: no samples received")
        chans, units = bs[0].channels, bs[0].units
        bs = [b for b in bs if b.channels == chans]
        n = np.array([b.n_samples for b in bs])
        idx = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        rates = np.repeat([float(b.sample_rate_hz) for b in bs], n)
        stamps_s = np.asarray([b.stamp_ns for b in bs], dtype=np.int64) * 1e-9
        time_s = np.repeat(stamps_s, n) + idx / rates
        rate = Counter(float(b.sample_rate_hz) for b in bs).most_common(1)[0][0]
        data = np.concatenate([np.asarray(b.data, np.float64) for b in bs])
        return cls(topic, tuple(chans), tuple(units), float(rate), time_s, data)

    def delayed_by(self, delay_s: float) -> "ChannelData":
        """The same samples with ``time_s`` moved back by an acquisition delay (the time each
        sample describes, see Metadata.acquisition_delay_s); self when the delay is 0."""
        if not delay_s:
            return self
        return ChannelData(self.topic, self.channels, self.units, self.sample_rate_hz,
                           self.time_s - float(delay_s), self.data, self.issues)


class _BlockViews:
    """datas[i] -> rows of block i inside the concatenated array (for duplicate checks)."""

    def __init__(self, out, offs, counts):
        self.out, self.offs, self.counts = out, offs, counts

    def __getitem__(self, i):
        o = int(self.offs[i])
        return self.out[o:o + int(self.counts[i])]


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 300 else text[:297] + "..."


class BagReader:
    """Context manager reading one contract bag: ``with BagReader(path) as bag: ...``.

    ``strict=True``: a missing or invalid metadata message raises ContractError on open, and
    :meth:`read_topic` raises on NaN/inf or malformed blocks. ``strict=False`` records such
    problems as issues (``metadata`` may then be None) and skips malformed blocks.
    ``fast_decode``: use :class:`~maglev_ros.sensor_block.SensorBlockDecoder` when the bag's
    SensorBlock definition is ours (False: always rosbags' deserialiser).
    """

    def __init__(self, path: str | os.PathLike, strict: bool = True,
                 fast_decode: bool = True) -> None:
        self.path = Path(path)
        self.strict = strict
        self.fast_decode = fast_decode
        self._fast = False
        self.metadata: Metadata | None = None
        self.topics: dict[str, TopicInfo] = {}
        self.open_issues: list[Issue] = []
        #: filled by check(): per SensorBlock topic blocks, samples, first_stamp_s, end_s,
        #: sample_rates_hz, block_samples (header-stamp based)
        self.topic_stats: dict[str, dict] = {}
        self._reader = None
        self._conns: dict[str, list] = {}
        self._deser = None
        self._is2 = True

    # --------------------------------------------------------------------------- opening
    def _fail(self, what: str) -> ContractError:
        return ContractError(f"{self.path}: {what}")

    def _resolve_path(self) -> Path:
        p = self.path
        if not p.exists():
            raise self._fail("no such bag (file or directory not found)")
        if p.is_dir():
            if (p / "metadata.yaml").is_file():
                return p
            files = sorted(list(p.glob("*.mcap")) + list(p.glob("*.db3")))
            if len(files) == 1:
                return files[0]
            raise self._fail("not a bag: directory has no metadata.yaml"
                             + ("" if not files else f" and {len(files)} storage files"))
        if p.suffix not in (".mcap", ".db3", ".bag"):
            raise self._fail("not a bag: expected a rosbag2 directory, a .mcap or .db3 file, "
                             "or a ROS1 .bag file")
        return p

    def open(self) -> "BagReader":
        from rosbags.highlevel import AnyReader

        target = self._resolve_path()
        try:
            reader = AnyReader([target], default_typestore=typestore())
            reader.open()
        except ContractError:
            raise
        except Exception as exc:  # rosbags raises many types for a broken file
            msg = _one_line(exc)
            if any(w in msg.lower() for w in ("magic", "truncat", "malformed", "damaged",
                                               "could not be read", "unexpected end")):
                msg = f"truncated or corrupt bag file ({msg})"
            raise self._fail(f"cannot open bag: {msg}") from None
        self._reader = reader
        self._is2 = reader.is2
        ts = reader.typestore
        self._deser = ts.deserialize_cdr if self._is2 else ts.deserialize_ros1
        self._fast = self.fast_decode and self._is2 and same_sensorblock_definition(ts)
        try:
            self._conns = defaultdict(list)
            for c in reader.connections:
                self._conns[c.topic].append(c)
            self._check_types(ts)
            self._read_metadata()
            self._read_topic_infos()
        except BaseException:
            self.close()
            raise
        return self

    def _check_types(self, ts) -> None:
        if SENSORBLOCK_TYPE in ts.fielddefs:
            names = [f[0] for f in ts.fielddefs[SENSORBLOCK_TYPE][1]]
            missing = [f for f in SENSORBLOCK_FIELDS if f not in names]
            if missing:
                raise self._fail(f"{SENSORBLOCK_TYPE} definition in the bag lacks field(s) "
                                 f"{', '.join(missing)}")

    def _messages(self, conns, start=None, stop=None):
        """rosbags message generator with low-level failures turned into one-line errors."""
        gen = self._reader.messages(connections=conns, start=start, stop=stop)
        try:
            yield from gen
        except ContractError:
            raise
        except Exception as exc:  # broken chunk / truncated storage
            raise self._fail(f"cannot read bag (corrupt or truncated): {_one_line(exc)}") from None

    def _read_metadata(self) -> None:
        conns = self._conns.get(TOPIC_METADATA)
        problem = None
        if not conns:
            problem = (f"topic {TOPIC_METADATA} missing: the recording contract requires the "
                       "metadata JSON as the first message")
        elif conns[0].msgtype != STRING_TYPE:
            problem = f"topic {TOPIC_METADATA} has type {conns[0].msgtype}, expected {STRING_TYPE}"
        else:
            first = next(self._messages(conns), None)
            if first is None:
                problem = f"topic {TOPIC_METADATA} holds no message"
            else:
                conn, _, raw = first
                try:
                    text = self._deser(raw, conn.msgtype).data
                except Exception as exc:  # noqa: BLE001
                    raise self._fail(f"{TOPIC_METADATA}: cannot decode message: {_one_line(exc)}") from None
                try:
                    self.metadata = parse_metadata(text, str(self.path))
                except ContractError as exc:
                    if self.strict:
                        raise
                    self.open_issues.append(Issue("error", TOPIC_METADATA, None, None,
                                                  "metadata", str(exc)))
        if problem is not None:
            if self.strict:
                raise self._fail(problem)
            self.open_issues.append(Issue("error", TOPIC_METADATA, None, None, "metadata",
                                          f"{self.path}: {problem}"))

    def _read_topic_infos(self) -> None:
        infos = {}
        for topic in sorted(self._conns):
            conns = self._conns[topic]
            msgtype = conns[0].msgtype
            count = sum(c.msgcount for c in conns)
            if msgtype != SENSORBLOCK_TYPE:
                infos[topic] = TopicInfo(topic, msgtype, count)
                continue
            first = next(self._messages(conns), None)
            if first is None:
                infos[topic] = TopicInfo(topic, msgtype, count)
                continue
            conn, log_ns, raw = first
            msg = self._decode(raw, topic)
            st = msg.header.stamp
            stamp = st.sec * 1_000_000_000 + st.nanosec
            nch = max(len(msg.channels), 1)
            infos[topic] = TopicInfo(topic, msgtype, count, tuple(msg.channels), tuple(msg.units),
                                     float(msg.sample_rate_hz), msg.header.frame_id, stamp,
                                     log_ns - stamp, len(msg.data) // nch)
        self.topics = infos

    def close(self) -> None:
        if self._reader is not None:
            reader, self._reader = self._reader, None
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing a broken reader
                pass

    def __enter__(self) -> "BagReader":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False

    # ------------------------------------------------------------------------ properties
    def _need_open(self) -> None:
        if self._reader is None:
            raise UserError(f"{self.path}: BagReader is not open (use it as a context manager)")

    @property
    def storage(self) -> str:
        self._need_open()
        if not self._is2:
            return "ros1"
        p = self.path
        if p.is_dir():
            if any(p.glob("*.mcap")):
                return "mcap"
            if any(p.glob("*.db3")):
                return "sqlite3"
        return {".mcap": "mcap", ".db3": "sqlite3"}.get(p.suffix, "unknown")

    @property
    def sensor_topics(self) -> list[str]:
        return [t for t, i in self.topics.items() if i.is_sensor_block]

    @property
    def start_time_s(self) -> float:
        """Earliest header stamp of the data topics [s] (receive time of the bag if none)."""
        return self._t0_ns() * 1e-9

    def _t0_ns(self) -> int:
        stamps = [i.first_stamp_ns for i in self.topics.values() if i.first_stamp_ns is not None]
        return min(stamps) if stamps else self._reader.start_time

    @property
    def log_start_ns(self) -> int:
        return self._reader.start_time

    @property
    def log_end_ns(self) -> int:
        return self._reader.end_time

    @property
    def duration_s(self) -> float:
        """Receive-time span of the bag [s]."""
        return max(self._reader.end_time - self._reader.start_time, 0) * 1e-9

    @property
    def message_count(self) -> int:
        return self._reader.message_count

    # --------------------------------------------------------------------------- reading
    def _decode(self, raw, topic: str):
        try:
            return self._deser(raw, SENSORBLOCK_TYPE)
        except Exception as exc:  # noqa: BLE001
            raise self._fail(f"{topic}: cannot decode SensorBlock: {_one_line(exc)}") from None

    def _select(self, topics: Iterable[str] | str | None, sensor_only: bool) -> list:
        self._need_open()
        if topics is None:
            names = self.sensor_topics if sensor_only else list(self._conns)
        else:
            names = [topics] if isinstance(topics, str) else list(topics)
            for t in names:
                if t not in self._conns:
                    raise self._fail(f"topic {t} not in bag (topics: {', '.join(sorted(self._conns))})")
                if sensor_only and self._conns[t][0].msgtype != SENSORBLOCK_TYPE:
                    raise self._fail(f"topic {t} has type {self._conns[t][0].msgtype}, "
                                     f"expected {SENSORBLOCK_TYPE}")
        return [c for t in names for c in self._conns[t]]

    def _window(self, conns, start_s, duration_s):
        """(window start ns, window end ns, log start, log stop) in absolute ns; None = open."""
        if start_s is None and duration_s is None:
            return None, None, None, None
        t0 = self._t0_ns()
        ws = t0 + int(round((start_s or 0.0) * 1e9))
        we = None if duration_s is None else ws + int(round(duration_s * 1e9))
        topics = {c.topic for c in conns}
        infos = [self.topics[t] for t in topics if t in self.topics]
        lags = [i.first_lag_ns for i in infos if i.first_lag_ns is not None] or [0]
        block_ns = [int(i.block_samples / i.sample_rate_hz * 1e9) for i in infos
                    if i.block_samples and i.sample_rate_hz] or [0]
        log_start = ws + min(lags) - 4 * max(block_ns) - 1_000_000_000
        log_stop = None if we is None else we + max(max(lags), 0) + LAG_SLACK_NS
        return ws, we, (log_start if log_start > self._reader.start_time else None), log_stop

    def iter_blocks(self, topics: Iterable[str] | str | None = None, start_s: float | None = None,
                    duration_s: float | None = None) -> Iterator[tuple[str, Block]]:
        """Yield (topic, Block) in receive order, one message at a time (bounded memory).

        ``topics``: SensorBlock topics (default: all). With a window, blocks that overlap
        [start_time_s + start_s, ... + duration_s) are yielded whole (not trimmed).
        Malformed blocks raise ContractError (strict) or are skipped (strict=False).
        """
        for topic, stamp, frame, rate, chans, units, data in self._iter_parts(topics, start_s,
                                                                               duration_s):
            yield topic, Block(stamp, frame, rate, chans, units, data)

    def _decoder(self):
        """A function raw -> DecodedBlock (fast path when the bag's SensorBlock is ours; one
        instance per topic so the channel/unit cache sees that topic's repeating strings)."""
        deser = self._deser
        fast = SensorBlockDecoder().decode if self._fast else None
        last = [None, None, (), ()]     # rosbags path: reuse tuples while the lists repeat

        def decode(raw):
            if fast is not None:
                out = fast(raw)
                if out is not None:
                    return out
            msg = deser(raw, SENSORBLOCK_TYPE)
            chans, units = msg.channels, msg.units
            if chans != last[0] or units != last[1]:
                last[:] = [chans, units, tuple(chans), tuple(units)]
            st = msg.header.stamp
            data = msg.data
            if not isinstance(data, np.ndarray) or data.dtype != np.float32:
                data = np.asarray(data, dtype=np.float32)
            return DecodedBlock(st.sec * 1_000_000_000 + st.nanosec, msg.header.frame_id,
                                float(msg.sample_rate_hz), last[2], last[3], data)
        return decode

    def _iter_parts(self, topics, start_s, duration_s):
        """iter_blocks without the Block wrapper: (topic, stamp_ns, frame, rate, channels, units, data)."""
        conns = self._select(topics, sensor_only=True)
        if not conns:
            return
        ws, we, log_start, log_stop = self._window(conns, start_s, duration_s)
        decoders: dict[str, object] = {}
        strict = self.strict
        for conn, _log_ns, raw in self._messages(conns, start=log_start, stop=log_stop):
            topic = conn.topic
            dec = decoders.get(topic)
            if dec is None:
                dec = decoders[topic] = self._decoder()
            try:
                b = dec(raw)
            except Exception as exc:  # noqa: BLE001
                if strict:
                    raise self._fail(f"{topic}: cannot decode SensorBlock: {_one_line(exc)}") from None
                continue
            flat = b.data
            nch = len(b.channels)
            rate = b.sample_rate_hz
            if nch == 0 or flat.size % nch or len(b.units) != nch or not rate > 0:
                if strict:
                    raise self._fail(f"{topic}: malformed SensorBlock at t={b.stamp_ns * 1e-9:.6f} s: "
                                     f"{flat.size} values, {nch} channels, {len(b.units)} units, "
                                     f"rate {rate}")
                continue
            stamp = b.stamp_ns
            if ws is not None:
                end = stamp + int(flat.size // nch / rate * 1e9)
                if end <= ws or (we is not None and stamp >= we):
                    continue
            yield (topic, stamp, b.frame_id, rate, b.channels, b.units, flat.reshape(-1, nch))

    def iter_raw(self, topics: Iterable[str] | str | None = None, start_s: float | None = None,
                 duration_s: float | None = None) -> Iterator[tuple[str, str, int, bytes]]:
        """Yield (topic, msgtype, stamp_ns, raw CDR bytes) in receive order, for replay.

        stamp_ns is the header stamp for SensorBlocks (and other types with a header) and the
        receive time otherwise. ROS1 payloads are converted to CDR. ``topics``: default all,
        metadata included (always, even outside a window). A window (seconds after
        ``start_time_s``, as in :meth:`iter_blocks`) keeps messages with stamp_ns inside it.
        """
        conns = self._select(topics, sensor_only=False)
        if not conns:
            return
        ws, we, log_start, log_stop = self._window(conns, start_s, duration_s)
        ts = self._reader.typestore
        has_header = {}
        is2 = self._is2
        unpack = _STAMP_LE.unpack_from
        for conn, log_ns, raw in self._messages(conns, start=log_start, stop=log_stop):
            mt = conn.msgtype
            hh = has_header.get(mt)
            if hh is None:
                fields = ts.fielddefs.get(mt, (None, []))[1]
                hh = has_header[mt] = bool(fields) and fields[0][0] == "header"
            stamp = log_ns
            if not is2:
                raw, stamp = self._ros1_to_ros2_cdr(raw, mt, conn.topic, log_ns)
            elif hh:
                if len(raw) >= 12 and raw[1] == 1:        # little-endian CDR: the common case
                    sec, nsec = unpack(raw, 4)
                    stamp = sec * 1_000_000_000 + nsec
                else:
                    stamp = self._header_stamp(raw, mt, conn.topic)
            if ws is not None and conn.topic != TOPIC_METADATA:
                if stamp < ws or (we is not None and stamp >= we):
                    continue
            yield conn.topic, mt, stamp, raw if type(raw) is bytes else bytes(raw)

    def _ros1_to_ros2_cdr(self, raw, msgtype: str, topic: str, log_ns: int):
        """ROS1 payload -> ROS 2 CDR (headers lose their ``seq``), and its stamp."""
        ts = self._reader.typestore
        ours = typestore()
        try:
            msg = ts.deserialize_ros1(raw, msgtype)
        except Exception as exc:  # noqa: BLE001
            raise self._fail(f"{topic}: cannot decode ROS1 message: {_one_line(exc)}") from None
        if msgtype == SENSORBLOCK_TYPE:
            from maglev_ros.sensor_block import block_to_msg, msg_to_block
            blk = msg_to_block(msg, f"{self.path} {topic}")
            return bytes(ours.serialize_cdr(block_to_msg(blk, ours), msgtype)), blk.stamp_ns
        if msgtype == STRING_TYPE:
            return bytes(ours.serialize_cdr(ours.types[STRING_TYPE](data=msg.data), msgtype)), log_ns
        stamp = log_ns
        hdr = getattr(msg, "header", None)
        if hdr is not None and hasattr(hdr, "stamp"):
            stamp = hdr.stamp.sec * 1_000_000_000 + hdr.stamp.nanosec
        return bytes(ts.ros1_to_cdr(raw, msgtype)), stamp

    @staticmethod
    def _cdr_stamp(raw) -> int:
        """Header stamp from CDR bytes: after the 4-byte encapsulation, int32 sec, uint32 nsec."""
        little = bool(raw[1])
        order = "little" if little else "big"
        sec = int.from_bytes(bytes(raw[4:8]), order, signed=True)
        nsec = int.from_bytes(bytes(raw[8:12]), order, signed=False)
        return sec * 1_000_000_000 + nsec

    def _header_stamp(self, raw, msgtype: str, topic: str) -> int:
        if len(raw) < 12:
            raise self._fail(f"{topic}: message too short for a header ({len(raw)} bytes)")
        return self._cdr_stamp(raw)

    def read_metadata_json(self) -> str | None:
        return None if self.metadata is None else self.metadata.to_json()

    def read_topic(self, topic: str, start_s: float | None = None,
                   duration_s: float | None = None) -> ChannelData:
        """All samples of one SensorBlock topic as arrays (float64), with sample times.

        Blocks are sorted by header stamp; exact duplicates are dropped; samples of a block that
        start before the end of the previous block (overlap) are dropped; all of it is listed in
        ``ChannelData.issues``. Blocks whose channel list differs from the first are refused
        (ContractError in strict mode, skipped and reported otherwise). With a window, samples
        outside [start_time_s + start_s, + duration_s) are cut off. NaN/inf samples raise
        ContractError in strict mode and are kept (and reported) otherwise.
        """
        return self._read_topic_blocks(topic, start_s, duration_s)[0]

    def read_checked(self, topics: Iterable[str] | str, sensor_map: bool = False):
        """Read topics through the sensor-health check (:func:`maglev_ros.health.check_topics`):
        ({topic: ChannelData in SI, bad channels left out where that is safe}, HealthReport).

        What every verb reads its data with. ``sensor_map``: the verb places channels by the
        metadata's sensors (magnet, position), so a channel the metadata does not place is an
        error. Raises one UserError line where a result would be wrong."""
        from maglev_ros.health import check_topics

        names = [topics] if isinstance(topics, str) else list(topics)
        read = {t: self._read_topic_blocks(t) for t in names}
        return check_topics(str(self.path), self.metadata, read, sensor_map=sensor_map,
                            other_intervals=self.unread_intervals(read))

    def unread_intervals(self, read) -> dict:
        """Sensor topics not in ``read``, each spanned (start, end) [s] from its first block's stamp,
        block count and rate: enough to see an hour's offset without reading them."""
        return {t: (i.first_stamp_ns * 1e-9, i.first_stamp_ns * 1e-9
                    + i.count * (i.block_samples or 0) / i.sample_rate_hz)
                for t, i in self.topics.items() if t not in read and i.is_sensor_block
                and i.first_stamp_ns is not None and i.sample_rate_hz}

    def _read_topic_blocks(self, topic: str, start_s: float | None = None,
                           duration_s: float | None = None) -> tuple:
        """(read_topic's ChannelData, every block's header stamp [ns], sample count and stated
        rate as read, before sorting and repairs: what the stated rate is checked against)."""
        if topic not in self.topics:
            self._need_open()
            raise self._fail(f"topic {topic} not in bag (topics: {', '.join(sorted(self.topics))})")
        issues: list[Issue] = []
        channels = units = None
        # Copy each block straight into one growing float64 array, so message buffers are
        # released as we go (retaining them costs far more than the copy).
        info = self.topics[topic]
        est = max(int(info.count) * int(info.block_samples or 1), 1)
        if duration_s is not None and info.sample_rate_hz:
            est = min(est, int(duration_s * info.sample_rate_hz) + 4 * int(info.block_samples or 1))
        out = None
        pos = 0
        stamps, rates, offs = [], [], []
        for _, stamp, _f, rate, bch, bun, bdata in self._iter_parts(topic, start_s, duration_s):
            if channels is None:
                channels, units = bch, bun
                out = np.empty((est, len(channels)), dtype=np.float64)
            elif bch is not channels and (bch != channels or bun != units):
                msg = (f"channels/units change at t={stamp * 1e-9:.6f} s "
                       f"({', '.join(bch)}) vs first block ({', '.join(channels)})")
                if self.strict:
                    raise self._fail(f"{topic}: {msg}")
                issues.append(Issue("error", topic, None, stamp * 1e-9, "channels_changed",
                                    msg + "; block skipped"))
                continue
            n = bdata.shape[0]
            if pos + n > out.shape[0]:
                grown = np.empty((max(2 * out.shape[0], pos + n), out.shape[1]), dtype=np.float64)
                grown[:pos] = out[:pos]
                out = grown
            out[pos:pos + n] = bdata
            stamps.append(stamp)
            rates.append(rate)
            offs.append(pos)
            pos += n
        if channels is None:
            return (ChannelData(topic, info.channels, info.units, info.sample_rate_hz or 0.0,
                                np.zeros(0), np.zeros((0, len(info.channels))), tuple(issues)),
                    np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        stamps_a = np.asarray(stamps, dtype=np.int64)
        offs_a = np.asarray(offs, dtype=np.int64)
        counts_a = np.diff(np.append(offs_a, pos))
        rates_a = np.asarray(rates, dtype=np.float64)
        datas = _BlockViews(out, offs_a, counts_a)
        if np.any(np.diff(stamps_a) < 0):
            bad = np.nonzero(np.diff(stamps_a) < 0)[0]
            issues.append(Issue("warning", topic, None, float(stamps_a[bad[0] + 1]) * 1e-9,
                                "out_of_order", f"{bad.size} block(s) out of stamp order; sorted"))
            order = np.argsort(stamps_a, kind="stable")
        else:
            order = np.arange(stamps_a.size)
        keep, heads = self._resolve_overlaps(topic, order, stamps_a, counts_a, rates_a, datas,
                                             issues)
        sel = order[keep]
        heads = heads[keep]
        n_per = counts_a[sel] - heads
        total = int(n_per.sum())
        starts = np.cumsum(n_per) - n_per
        idx = np.arange(total) - np.repeat(starts - heads, n_per)   # sample index in its block
        if total == pos and np.array_equal(sel, np.arange(stamps_a.size)):
            data = out[:pos]
        else:
            data = out[np.repeat(offs_a[sel], n_per) + idx]
        # sample times without a Python loop over samples: stamp + j / rate
        rates_sel = rates_a[sel]
        if np.all(rates_sel == rates_sel[0]):
            time_s = np.repeat(stamps_a[sel] * 1e-9, n_per) + idx / rates_sel[0]
        else:
            time_s = np.repeat(stamps_a[sel] * 1e-9, n_per) + idx / np.repeat(rates_sel, n_per)
            issues.append(Issue("warning", topic, None, None, "rate_change",
                                f"sample rate varies between blocks: "
                                f"{sorted(set(rates_sel.tolist()))} Hz"))
        if start_s is not None or duration_s is not None:
            ws = self._t0_ns() * 1e-9 + (start_s or 0.0)
            m = time_s >= ws - 1e-12
            if duration_s is not None:
                m &= time_s < ws + duration_s - 1e-12
            time_s, data = time_s[m], data[m]
        # column sums are finite iff every sample is (float32-range data cannot overflow float64)
        if not np.isfinite(np.add.reduce(data, axis=0)).all():
            rows, cols = np.nonzero(~np.isfinite(data))
            for c in np.unique(cols):
                r = rows[cols == c]
                msg = f"{r.size} NaN/inf sample(s), first at t={time_s[r[0]]:.6f} s"
                if self.strict:
                    raise self._fail(f"{topic} [{channels[c]}]: {msg}")
                issues.append(Issue("error", topic, channels[c], float(time_s[r[0]]), "nan", msg))
        rate = Counter(rates_sel.tolist()).most_common(1)[0][0]
        return (ChannelData(topic, channels, units, float(rate), time_s, data, tuple(issues)),
                stamps_a, counts_a, rates_a)

    @staticmethod
    def _resolve_overlaps(topic, order, stamps_a, counts_a, rates_a, datas, issues):
        """Per sorted block: keep flag and leading samples to drop (duplicates / overlaps).

        Vectorised test first; the per-block loop only runs when something overlaps.
        """
        n = order.size
        keep = np.ones(n, dtype=bool)
        heads = np.zeros(n, dtype=np.int64)
        base = int(stamps_a.min())
        st = stamps_a[order] - base          # relative ns: exact in float64
        ends = st + counts_a[order] * 1e9 / rates_a[order]
        half = 0.5e9 / rates_a[order]
        if n < 2 or np.all(st[1:] >= np.maximum.accumulate(ends)[:-1] - half[1:]):
            return keep, heads
        prev_k = None
        prev_end = None
        for k in range(n):
            i = order[k]
            if prev_k is not None and st[k] < prev_end - half[k]:
                pi = order[prev_k]
                if st[k] == st[prev_k] and counts_a[i] == counts_a[pi] \
                        and np.array_equal(datas[i], datas[pi], equal_nan=True):
                    keep[k] = False
                    issues.append(Issue("warning", topic, None, (int(st[k]) + base) * 1e-9, "duplicate",
                                        "exact duplicate block dropped"))
                    continue
                n_over = int(np.ceil((prev_end - half[k] - st[k]) * rates_a[i] / 1e9))
                n_over = min(n_over, int(counts_a[i]))
                heads[k] = n_over
                issues.append(Issue("warning", topic, None, (int(st[k]) + base) * 1e-9, "overlap",
                                    f"block overlaps the previous one by "
                                    f"{(prev_end - st[k]) * 1e-9:.6g} s; "
                                    f"{n_over} leading sample(s) dropped"))
                if n_over == counts_a[i]:
                    keep[k] = False
                    continue
            prev_end = ends[k] if prev_end is None else max(prev_end, ends[k])
            prev_k = k
        return keep, heads

    # ---------------------------------------------------------------------------- checks
    def check(self, health: bool = True) -> list[Issue]:
        """Stream over the bag and list every contract problem (see module docstring).

        ``health``: also the sensor-health findings (:mod:`maglev_ros.health`): stated rate vs
        stamps and topics that do not overlap in time as errors; flat-lined, clipped and
        implausible channels (scanned in SI) and metadata naming no sensors as warnings."""
        from maglev_ros import health as hl

        self._need_open()
        scans: dict[str, tuple] = {}
        issues: list[Issue] = list(self.open_issues)
        per_kind: Counter = Counter()
        overflow: Counter = Counter()

        def add(issue: Issue) -> None:
            key = (issue.topic, issue.kind)
            per_kind[key] += 1
            if per_kind[key] <= MAX_ISSUES_PER_KIND:
                issues.append(issue)
            else:
                overflow[key] += 1

        known = set(self.metadata.sensors) if self.metadata is not None else None
        if self.metadata is not None:
            for mi in metadata_issues(self.metadata):
                add(mi)
        recorded: set[str] = set()
        conns = self._select(None, sensor_only=True)
        # per topic: list of (stamp_ns, n_samples, rate, digest)
        recs: dict[str, list] = defaultdict(list)
        seen_lists: dict[str, set] = defaultdict(set)
        nan_stats: dict[tuple, list] = {}
        decoders: dict[str, object] = {}
        for conn, _log_ns, raw in self._messages(conns):
            topic = conn.topic
            dec = decoders.get(topic)
            if dec is None:
                dec = decoders[topic] = self._decoder()
            try:
                b = dec(raw)
            except Exception as exc:  # noqa: BLE001
                add(Issue("error", topic, None, None, "undecodable", f"cannot decode: {_one_line(exc)}"))
                continue
            stamp = b.stamp_ns
            t_s = stamp * 1e-9
            chans, units = b.channels, b.units
            flat = b.data
            rate = float(b.sample_rate_hz)
            nch = len(chans)
            key = (chans, units)
            if key not in seen_lists[topic]:
                seen_lists[topic].add(key)
                if len(seen_lists[topic]) > 1:
                    add(Issue("warning", topic, None, t_s, "channels_changed",
                              f"channel/unit list changed to {list(chans)} / {list(units)}"))
                if len(units) != nch:
                    add(Issue("error", topic, None, t_s, "units_mismatch",
                              f"{nch} channels but {len(units)} units"))
                for ui in check_units(topic, chans, units[:nch], t_s):
                    add(ui)
                for ch in chans:
                    recorded.add(ch)
                    if known is not None and ch not in known:
                        add(Issue("warning", topic, ch, t_s, "unknown_channel",
                                  f"channel {ch!r} is not listed in metadata sensors"))
                    elif known is not None and self.metadata.sensors[ch].topic != topic:
                        add(Issue("warning", topic, ch, t_s, "wrong_topic",
                                  f"metadata lists channel {ch!r} on "
                                  f"{self.metadata.sensors[ch].topic}"))
            if nch == 0 or flat.size % nch:
                add(Issue("error", topic, None, t_s, "data_length",
                          f"{flat.size} values is not a multiple of {nch} channels"))
                continue
            if not rate > 0 or not np.isfinite(rate):
                add(Issue("error", topic, None, t_s, "bad_rate", f"sample_rate_hz {rate!r}"))
                continue
            data = flat.reshape(-1, nch)
            fin = np.isfinite(data)
            if not fin.all():
                bad_cols = np.nonzero(~fin.all(axis=0))[0]
                for c in bad_cols:
                    rows = np.nonzero(~fin[:, c])[0]
                    k = (topic, chans[c])
                    if k not in nan_stats:
                        nan_stats[k] = [t_s + rows[0] / rate, 0, 0]
                    else:
                        nan_stats[k][0] = min(nan_stats[k][0], t_s + rows[0] / rate)
                    nan_stats[k][1] += rows.size
                    nan_stats[k][2] += 1
            if health:
                sc = scans.get(topic)
                if sc is None:
                    sc = scans[topic] = self._health_scan(topic, chans, units, rate)
                if chans == sc[1] and fin.all():
                    sc[0].add(data[:, sc[2]] * sc[3])
            digest = hashlib.blake2b(flat.tobytes(), digest_size=8).digest()
            recs[topic].append((stamp, data.shape[0], rate, digest))

        self.topic_stats = {}
        for topic, rec in recs.items():
            st = np.array([r[0] for r in rec], dtype=np.int64)
            ns = np.array([r[1] for r in rec], dtype=np.int64)
            rt = np.array([r[2] for r in rec], dtype=np.float64)
            i_last = int(np.argmax(st))
            self.topic_stats[topic] = {
                "blocks": len(rec), "samples": int(ns.sum()),
                "first_stamp_s": float(st.min()) * 1e-9,
                "end_s": float(st[i_last]) * 1e-9 + float(ns[i_last] / rt[i_last]),
                "sample_rates_hz": sorted(set(rt.tolist())),
                "block_samples": sorted(set(ns.tolist()))[:10],
            }
        for (topic, ch), (t_first, n, nb) in nan_stats.items():
            add(Issue("error", topic, ch, t_first, "nan",
                      f"{n} NaN/inf sample(s) in {nb} block(s), first at t={t_first:.6f} s"))
        for topic, rec in recs.items():
            self._check_timing(topic, rec, add)
        if health:
            for topic, rec in recs.items():
                bad = hl.rate_issue(topic, [r[2] for r in rec], [r[0] for r in rec], [r[1] for r in rec])
                if bad is not None:
                    add(bad)
            for i in hl.time_offset_issues({t: (st["first_stamp_s"], st["end_s"])
                                            for t, st in self.topic_stats.items()}):
                add(i)
            for sc in scans.values():
                for i in sc[0].issues():
                    add(i)
            if self.metadata is not None and not self.metadata.sensors:
                add(Issue("warning", TOPIC_METADATA, None, None, "sensor_map",
                          "metadata key sensors: names no sensors; verbs that place channels by "
                          "magnet or position (irregularity, update, diagnose, modes of a pass) "
                          "refuse the recording"))
        if known is not None:
            for sid, s in self.metadata.sensors.items():
                if s.topic in self.topics and sid not in recorded:
                    add(Issue("warning", s.topic, sid, None, "missing_channel",
                              f"metadata sensor {sid!r} is not recorded on {s.topic}"))
        for (topic, kind), n in overflow.items():
            issues.append(Issue("warning", topic, None, None, kind,
                                f"... and {n} more '{kind}' issue(s) on this topic"))
        # errors first, then by topic and time (stable: open-time issues keep their place)
        issues.sort(key=lambda i: (i.severity != "error", i.topic or "",
                                   float("inf") if i.time_s is None else i.time_s))
        return issues

    def _health_scan(self, topic: str, chans, units, rate: float) -> tuple:
        """(TopicScan over the channels whose unit converts to the topic's SI unit, their
        column indices, their SI factors) for check()."""
        from maglev_ros.contract import si_factor
        from maglev_ros.health import TopicScan
        cols, factors = [], []
        for j, (ch, u) in enumerate(zip(chans, units)):
            f = si_factor(topic, ch, u)
            if f is not None:
                cols.append(j)
                factors.append(f[1])
        g0 = self.metadata.nominal_gap_m if self.metadata is not None else None
        scan = TopicScan(topic, [chans[j] for j in cols], rate, g0)
        return scan, chans, np.asarray(cols, dtype=np.int64), np.asarray(factors)

    @staticmethod
    def _check_timing(topic: str, rec: list, add) -> None:
        stamps = np.array([r[0] for r in rec], dtype=np.int64)
        # out-of-order: a stamp below the running maximum (in receive order)
        runmax = np.maximum.accumulate(stamps)
        for i in np.nonzero(stamps[1:] < runmax[:-1])[0] + 1:
            add(Issue("warning", topic, None, stamps[i] * 1e-9, "out_of_order",
                      f"block stamped {stamps[i] * 1e-9:.6f} s arrives after one stamped "
                      f"{runmax[i - 1] * 1e-9:.6f} s"))
        order = sorted(range(len(rec)), key=lambda i: (rec[i][0], i))
        prev = None
        for i in order:
            stamp, n, rate, digest = rec[i]
            if prev is not None:
                pstamp, pn, prate, pdigest = prev
                if rate != prate:
                    add(Issue("warning", topic, None, stamp * 1e-9, "rate_change",
                              f"sample rate changes from {prate:g} Hz to {rate:g} Hz"))
                if stamp == pstamp and n == pn and digest == pdigest:
                    add(Issue("warning", topic, None, stamp * 1e-9, "duplicate",
                              "duplicate block (same stamp and data)"))
                    continue
                # differences in integer ns first: float64 cannot hold epoch stamps to the ns
                late_ns = (stamp - pstamp) - pn * 1e9 / prate
                half = 0.5e9 / prate
                if late_ns > half:
                    add(Issue("warning", topic, None, (pstamp + pn * 1e9 / prate) * 1e-9, "gap",
                              f"gap of {late_ns * 1e-9:.6g} s "
                              f"(~{late_ns * prate / 1e9:.0f} samples missing) "
                              f"before block at {stamp * 1e-9:.6f} s"))
                elif late_ns < -half:
                    add(Issue("warning", topic, None, stamp * 1e-9, "overlap",
                              f"block starts {-late_ns * 1e-9:.6g} s before the "
                              f"previous block ends"))
            prev = (stamp, n, rate, digest)
