"""A SensorBlock topic read window by window in time order, so a long recording never sits in
memory whole (no rclpy).

``BagReader.read_topic`` returns a whole topic as float64: 8 bytes x channels per sample, 1.4 GB
for an hour of ten channels at 5 kHz, and a verb holds several copies while it works. The verbs
that walk a recording in time order read it here instead. :func:`scan_topic` reads the block
headers once (stamps, sizes, rates); :func:`window_edges` cuts the stamp span into windows;
:func:`read_window` returns the samples with ``lo_s <= t < hi_s``. Each window is read with
``read_topic`` over the window plus ``pad_s`` of neighbouring blocks on each side, so blocks are
sorted, deduplicated and trimmed as in a whole read, and, the edges being the same floats for
the windows on both sides, every sample lands in exactly one window: the windows concatenated
are ``read_topic(topic)`` sample for sample. (A block that overlaps a block more than ``pad_s``
away, or a receive time lagging its stamp by 10 s more than the first block's, is a contract
breach ``info`` reports; only there could a window differ from the whole read.)

:func:`read_checked_windows` is ``BagReader.read_checked`` for such topics: the same sensor-health
check (:func:`maglev_ros.health.check_feeds`), its channel scan fed window by window, and a
:class:`CheckedTopic` instead of the data, whose windows come in SI without the excluded
channels, as read_checked's arrays do.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from maglev_ros.bag_reader import BagReader, ChannelData

#: neighbouring blocks read around a window (blocks are 0.05-0.2 s long by the contract)
PAD_S = 1.0
#: values (samples x channels) per window when the caller gives no window length: 4 MB of float64
WINDOW_VALUES = 500_000


@dataclass(frozen=True, eq=False)
class TopicSpan:
    """What one pass over a topic's block headers tells: stamp span, rate, channels, and per
    block (as read, before sorting and repairs) stamp, sample count and stated rate."""
    topic: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    sample_rate_hz: float           # the most common block rate, as read_topic reports it
    first_s: float                  # earliest block stamp
    end_s: float                    # latest block end (stamp + samples / rate)
    n_samples: int                  # before duplicates / overlaps are dropped
    stamps: np.ndarray = field(repr=False, default=None)
    counts: np.ndarray = field(repr=False, default=None)
    rates: np.ndarray = field(repr=False, default=None)

    @property
    def span(self) -> "TopicSpan":
        return self

    def window_s(self, values: int | None = None) -> float:
        """A window length holding about ``values`` (default WINDOW_VALUES) samples x channels,
        at least 1 s."""
        per_s = self.sample_rate_hz * max(len(self.channels), 1)
        return max(1.0, (values or WINDOW_VALUES) / per_s)


@dataclass(frozen=True, eq=False)
class CheckedTopic:
    """A topic the health check passed, left in the bag: its windows come in SI (``factors``
    per recorded channel, None: no conversion) and with the recorded channels ``columns`` only
    (None: all); ``n_samples`` and ``first_time_s`` as read_topic would give them."""
    span: TopicSpan
    channels: tuple[str, ...]
    units: tuple[str, ...]
    factors: np.ndarray | None
    columns: list | None
    n_samples: int
    first_time_s: float | None

    @property
    def topic(self) -> str:
        return self.span.topic

    @property
    def sample_rate_hz(self) -> float:
        return self.span.sample_rate_hz

    def window_s(self, values: int | None = None) -> float:
        per_s = self.sample_rate_hz * max(len(self.channels), 1)
        return max(1.0, (values or WINDOW_VALUES) / per_s)


def scan_topic(reader: BagReader, topic: str) -> TopicSpan:
    """One pass over the topic's blocks (decoded one at a time, nothing kept but their headers)."""
    rates: Counter = Counter()
    stamps, counts, block_rates = [], [], []
    first = math.inf
    end = -math.inf
    channels = units = None
    for _, blk in reader.iter_blocks(topic):
        n = blk.data.shape[0]
        rates[blk.sample_rate_hz] += 1
        first = min(first, blk.stamp_ns * 1e-9)
        end = max(end, blk.stamp_ns * 1e-9 + n / blk.sample_rate_hz)
        stamps.append(blk.stamp_ns)
        counts.append(n)
        block_rates.append(blk.sample_rate_hz)
        if channels is None:
            channels, units = blk.channels, blk.units
    info = reader.topics[topic]
    if channels is None:
        channels, units = info.channels, info.units
    rate = rates.most_common(1)[0][0] if rates else float(info.sample_rate_hz or 0.0)
    return TopicSpan(topic, tuple(channels), tuple(units), float(rate), first, end,
                     int(sum(counts)), np.asarray(stamps, dtype=np.int64),
                     np.asarray(counts, dtype=np.int64), np.asarray(block_rates, dtype=np.float64))


def window_edges(src, window_s: float) -> list[tuple[float, float]]:
    """Consecutive (lo_s, hi_s) covering all of the topic: the first starts at -inf, the last
    ends at +inf, and each inner edge is one float shared by the two windows beside it."""
    span = src.span
    if not math.isfinite(span.first_s):
        return [(-math.inf, math.inf)]
    k = max(1, math.ceil((span.end_s - span.first_s) / window_s))
    inner = [span.first_s + j * window_s for j in range(1, k)]
    lo = [-math.inf] + inner
    hi = inner + [math.inf]
    return list(zip(lo, hi))


def read_window(reader: BagReader, src, lo_s: float, hi_s: float,
                pad_s: float = PAD_S) -> ChannelData:
    """The topic's samples with ``lo_s <= t < hi_s`` (absolute stream seconds; +-inf: open);
    ``src``: a :class:`TopicSpan` (as recorded) or a :class:`CheckedTopic` (SI, kept channels)."""
    span = src.span
    t0 = reader.start_time_s
    a = (lo_s if math.isfinite(lo_s) else span.first_s) - pad_s
    b = (hi_s if math.isfinite(hi_s) else span.end_s) + pad_s
    # a finite duration also sizes read_topic's buffer to the window, not to the whole topic
    cd = reader.read_topic(span.topic, start_s=a - t0, duration_s=b - a)
    t = cd.time_s
    m = (t >= lo_s) & (t < hi_s)
    t, d = (t, cd.data) if m.all() else (t[m], cd.data[m])
    if isinstance(src, CheckedTopic):
        if src.factors is not None:
            d = d * src.factors
        if src.columns is not None:
            d = d[:, src.columns]
        return ChannelData(cd.topic, src.channels, src.units, cd.sample_rate_hz, t, d, cd.issues)
    return cd if d is cd.data else ChannelData(cd.topic, cd.channels, cd.units,
                                               cd.sample_rate_hz, t, d, cd.issues)


def iter_windows(reader: BagReader, src, window_s: float | None = None):
    """``read_window`` over :func:`window_edges`: the topic in time order, window by window."""
    for lo, hi in window_edges(src, window_s or src.window_s()):
        yield read_window(reader, src, lo, hi)


class WindowFeed:
    """A topic for :func:`maglev_ros.health.check_feeds` that stays in the bag: its health scan
    reads it window by window, its result is a :class:`CheckedTopic`."""

    def __init__(self, reader: BagReader, span: TopicSpan):
        self.reader, self.span = reader, span
        self.channels, self.units = span.channels, span.units
        self.sample_rate_hz = span.sample_rate_hz
        self.stamps, self.counts, self.rates = span.stamps, span.counts, span.rates
        self.n = 0
        self.first = None

    @property
    def empty(self) -> bool:
        return self.span.n_samples == 0

    def scan(self, scan, factors, converted: bool) -> tuple[float, float]:
        f = np.asarray(factors)
        last = None
        for w in iter_windows(self.reader, self.span):
            if not w.time_s.size:
                continue
            scan.add(w.data * f if converted else w.data)
            if self.first is None:
                self.first = float(w.time_s[0])
            last = float(w.time_s[-1])
            self.n += w.time_s.size
        return self.first, last + 1.0 / self.sample_rate_hz

    def result(self, si_units, factors, converted: bool, keep) -> CheckedTopic:
        cols = None if keep is None else list(keep)
        names = self.channels if cols is None else tuple(self.channels[j] for j in cols)
        units = tuple(si_units) if cols is None else tuple(si_units[j] for j in cols)
        return CheckedTopic(self.span, tuple(names), units,
                            np.asarray(factors, dtype=float) if converted else None, cols,
                            self.n, self.first)


def read_checked_windows(reader: BagReader, windowed, whole=(), sensor_map: bool = False):
    """``BagReader.read_checked`` with the topics ``windowed`` left in the bag: ({topic:
    :class:`CheckedTopic` for those, ChannelData in SI for the ``whole`` ones}, HealthReport)."""
    from maglev_ros.health import ArrayFeed, check_feeds

    feeds = {t: WindowFeed(reader, scan_topic(reader, t)) for t in windowed}
    for t in whole:
        feeds[t] = ArrayFeed(*reader._read_topic_blocks(t))
    return check_feeds(str(reader.path), reader.metadata, feeds, sensor_map=sensor_map,
                       other_intervals=reader.unread_intervals(feeds))
