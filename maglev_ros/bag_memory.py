"""A recording received as SensorBlocks, read like a bag (no rclpy).

A node that must give, at the end of a recording, what an offline verb gives on the recorded bag
keeps the blocks it received in a :class:`MemoryBag` and hands that to the verb's own function
(``modes.identify_modes``, ``updating.pipeline.update_from_bags``). MemoryBag is a
:class:`~maglev_ros.bag_reader.BagReader` whose blocks come from memory instead of a file: every
read (``read_topic``, ``read_checked``, ``bag_windows``) goes through the reader's own code, so
sorting, duplicate and overlap repair, the sensor-health check, SI conversion and the windows are
those of the bag, and the same blocks give the same floats. Blocks are kept as received (float32,
recorded units): the recording once, half its float64 size.
"""
from __future__ import annotations

import itertools
from pathlib import Path
from typing import Iterable

import numpy as np

from maglev_ros.bag_reader import BagReader, TopicInfo
from maglev_ros.contract import SENSORBLOCK_TYPE, STRING_TYPE, TOPIC_METADATA, Metadata, parse_metadata
from maglev_ros.sensor_block import Block


class MemoryBag(BagReader):
    """Blocks added with :meth:`add` (receive order), under the recording's metadata JSON;
    ``source`` names it in messages and results (the bag it was replayed from, when known)."""

    def __init__(self, source: str, metadata: str | Metadata | None = None) -> None:
        super().__init__(source, strict=True)
        self._seq = itertools.count()
        self._blocks: dict[str, list] = {}       # topic -> [(arrival, Block)]
        self.metadata = None
        if metadata is not None:
            self.set_metadata(metadata)

    def set_metadata(self, metadata: str | Metadata) -> None:
        self.metadata = (metadata if isinstance(metadata, Metadata)
                         else parse_metadata(metadata, str(self.path)))

    def add(self, topic: str, block: Block) -> None:
        """One block as received (recorded units; float32 samples (n, channels))."""
        self._blocks.setdefault(topic, []).append((next(self._seq), block))

    @property
    def n_blocks(self) -> int:
        return sum(len(v) for v in self._blocks.values())

    def has(self, topic: str) -> bool:
        return bool(self._blocks.get(topic))

    def span_s(self, topic: str) -> tuple[float, float] | None:
        """(first stamp, latest block end) of ``topic`` in stream seconds; None without blocks."""
        bs = self._blocks.get(topic)
        if not bs:
            return None
        return (min(b.stamp_ns for _, b in bs) * 1e-9,
                max(b.stamp_ns * 1e-9 + b.n_samples / b.sample_rate_hz for _, b in bs))

    # ----------------------------------------------------------------- the BagReader interface
    def open(self) -> "MemoryBag":
        return self

    def close(self) -> None:          # the blocks stay: the reader may be opened again
        pass

    def _need_open(self) -> None:
        pass

    @property
    def topics(self) -> dict[str, TopicInfo]:
        out = {}
        if self.metadata is not None:
            out[TOPIC_METADATA] = TopicInfo(TOPIC_METADATA, STRING_TYPE, 1)
        for topic in sorted(self._blocks):
            bs = self._blocks[topic]
            b = bs[0][1]
            out[topic] = TopicInfo(topic, SENSORBLOCK_TYPE, len(bs), tuple(b.channels), tuple(b.units),
                                   float(b.sample_rate_hz), b.frame_id, int(b.stamp_ns), 0, b.n_samples)
        return out

    @topics.setter
    def topics(self, value) -> None:  # BagReader.__init__ assigns it; the blocks define it here
        pass

    @property
    def storage(self) -> str:
        return "memory"

    def _t0_ns(self) -> int:
        stamps = [bs[0][1].stamp_ns for bs in self._blocks.values() if bs]
        return min(stamps) if stamps else 0

    def _iter_parts(self, topics, start_s, duration_s):
        """BagReader._iter_parts over the kept blocks: receive order, the same stamp window."""
        names = self._names(topics)
        ws = we = None
        if start_s is not None or duration_s is not None:
            ws = self._t0_ns() + int(round((start_s or 0.0) * 1e9))
            we = None if duration_s is None else ws + int(round(duration_s * 1e9))
        parts = sorted((seq, t, b) for t in names for seq, b in self._blocks.get(t, []))
        for _, topic, b in parts:
            data = np.asarray(b.data)
            n = data.shape[0]
            if ws is not None:
                end = b.stamp_ns + int(n / b.sample_rate_hz * 1e9)
                if end <= ws or (we is not None and b.stamp_ns >= we):
                    continue
            yield (topic, int(b.stamp_ns), b.frame_id, float(b.sample_rate_hz), tuple(b.channels),
                   tuple(b.units), data)

    def _names(self, topics: Iterable[str] | str | None) -> list[str]:
        if topics is None:
            return sorted(self._blocks)
        names = [topics] if isinstance(topics, str) else list(topics)
        for t in names:
            if t not in self._blocks:
                raise self._fail(f"topic {t} not in the recording (topics: {', '.join(sorted(self._blocks))})")
        return names


def open_reader(source) -> BagReader:
    """A reader for ``source``: a bag path, or a :class:`MemoryBag` (used as it is)."""
    return source if isinstance(source, BagReader) else BagReader(source)


def source_name(source) -> str:
    """What results call ``source`` (``info["bag"]``): the path, or the MemoryBag's name."""
    return str(source.path) if isinstance(source, BagReader) else str(source)


def same_source(a, b) -> bool:
    """The same recording given twice (``update --ambient A --pass A``)."""
    if isinstance(a, BagReader) or isinstance(b, BagReader):
        return a is b
    return Path(a).resolve() == Path(b).resolve()


class RecordingCollector:
    """The blocks of ``topics`` received for the current recording, as a :class:`MemoryBag` when
    it ends, under that recording's metadata.

    A replay says where recordings end (:meth:`end`, on its recording_end event) and publishes each
    recording's metadata once, latched, after the previous recording has ended everywhere. DDS
    orders nothing across topics: the metadata can reach a node after some of the recording's
    blocks, or even after its end event (seen on a loaded machine: a pass's blocks were taken
    under the ambient's metadata). So a recording's metadata is the first received since the
    previous end; an end before it comes waits (``waiting``) and ``set_metadata`` returns the
    recording when it does (or :meth:`abandon` gives it up when the next recording begins without
    it). A live stream has no end events: with ``metadata_ends=True`` new
    metadata that differs from the current while blocks are held ends the recording
    (``set_metadata`` returns it).

    A recording whose samples exceed ``max_bytes`` (as received) is not kept: its blocks are
    dropped, ``overflowed`` is set and it gives no MemoryBag (a live stream that never ends must
    not fill the memory)."""

    def __init__(self, topics: Iterable[str], name: str = "live recording", max_bytes: float = 1e9) -> None:
        self.topics = frozenset(topics)
        self.name = name
        self.max_bytes = float(max_bytes)
        self.metadata_json: str | None = None
        self.n_recordings = 0
        self.overflowed = False
        self._bytes = 0
        self._bag = MemoryBag(name)
        self._fresh = False                  # metadata received since the last end
        self._waiting: tuple | None = None   # (source,) of an end that waits for its metadata

    @property
    def waiting(self) -> bool:
        """An ended recording waits for its metadata."""
        return self._waiting is not None

    @property
    def has_data(self) -> bool:
        return self._bag.n_blocks > 0 or self.overflowed

    def span_s(self, topic: str) -> tuple[float, float] | None:
        """The current recording's (first stamp, latest block end) of ``topic`` [s], as received."""
        return self._bag.span_s(topic)

    def add(self, topic: str, block: Block) -> bool:
        """Keep the block; False when it made the recording too large to keep (then and after)."""
        if topic not in self.topics:
            return True
        if self.overflowed:
            return False
        self._bytes += np.asarray(block.data).nbytes
        if self._bytes > self.max_bytes:
            self.overflowed = True
            self._bag = MemoryBag(self.name)
            return False
        self._bag.add(topic, block)
        return True

    def set_metadata(self, text: str, metadata_ends: bool = False) -> MemoryBag | None:
        """New metadata; returns a recording it completes (an end that waited for it, or, with
        ``metadata_ends``, the recording it ends), else None."""
        if self._waiting is not None:
            (source,), self._waiting = self._waiting, None
            self.metadata_json = text
            return self.finish(source)
        done = None
        if metadata_ends and self.has_data and self.metadata_json is not None and text != self.metadata_json:
            done = self.finish()
        self.metadata_json = text
        self._fresh = True
        return done

    def abandon(self) -> str | None:
        """Give up an end that waits for its metadata (the next recording has begun: the metadata
        never came); returns its source, None when nothing waited. Its blocks are dropped."""
        if self._waiting is None:
            return None
        (source,), self._waiting = self._waiting, None
        self._bag, self.overflowed, self._bytes = MemoryBag(self.name), False, 0
        return source or f"{self.name} {self.n_recordings + 1}"

    def end(self, source: str | None = None) -> MemoryBag | None:
        """The replay's end of the recording: :meth:`finish`; when no metadata has come since the
        previous end while blocks have, None and the end waits for it (``waiting``)."""
        if not self._fresh and self.has_data:
            self._waiting = (source,)
            return None
        return self.finish(source)

    def finish(self, source: str | None = None) -> MemoryBag | None:
        """The recording so far under ``source`` (default: "<name> <n>") with the last metadata,
        or None without blocks or metadata; collecting starts afresh. ContractError when the
        metadata is not valid."""
        bag, self._bag = self._bag, MemoryBag(self.name)
        over, self.overflowed, self._bytes = self.overflowed, False, 0
        self._fresh = False
        if over or not bag.n_blocks or self.metadata_json is None:
            return None
        self.n_recordings += 1
        bag.path = Path(source or f"{self.name} {self.n_recordings}")
        bag.set_metadata(self.metadata_json)
        return bag
