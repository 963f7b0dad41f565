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
away is a contract breach ``info`` reports; only there could a window trim differently.)
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from maglev_ros.bag_reader import BagReader, ChannelData

#: neighbouring blocks read around a window (blocks are 0.05-0.2 s long by the contract)
PAD_S = 1.0
#: values (samples x channels) per window when the caller gives no window length: 4 MB of float64
WINDOW_VALUES = 500_000


@dataclass(frozen=True)
class TopicScan:
    """What one pass over a topic's block headers tells: stamp span, rate, channels."""
    topic: str
    channels: tuple[str, ...]
    units: tuple[str, ...]
    sample_rate_hz: float           # the most common block rate, as read_topic reports it
    first_s: float                  # earliest block stamp
    end_s: float                    # latest block end (stamp + samples / rate)
    n_blocks: int
    n_samples: int                  # before duplicates / overlaps are dropped

    def window_s(self, values: int = WINDOW_VALUES) -> float:
        """A window length holding about ``values`` samples x channels, at least 1 s."""
        return max(1.0, values / (self.sample_rate_hz * max(len(self.channels), 1)))


def scan_topic(reader: BagReader, topic: str) -> TopicScan:
    """One pass over the topic's blocks (decoded one at a time, nothing kept but their headers)."""
    rates: Counter = Counter()
    first = math.inf
    end = -math.inf
    n_blocks = n_samples = 0
    channels = units = None
    for _, blk in reader.iter_blocks(topic):
        n = blk.data.shape[0]
        rates[blk.sample_rate_hz] += 1
        first = min(first, blk.stamp_ns * 1e-9)
        end = max(end, blk.stamp_ns * 1e-9 + n / blk.sample_rate_hz)
        n_blocks += 1
        n_samples += n
        if channels is None:
            channels, units = blk.channels, blk.units
    info = reader.topics[topic]
    if channels is None:
        channels, units = info.channels, info.units
    rate = rates.most_common(1)[0][0] if rates else float(info.sample_rate_hz or 0.0)
    return TopicScan(topic, tuple(channels), tuple(units), float(rate), first, end, n_blocks,
                     n_samples)


def window_edges(scan: TopicScan, window_s: float) -> list[tuple[float, float]]:
    """Consecutive (lo_s, hi_s) covering all of the topic: the first starts at -inf, the last
    ends at +inf, and each inner edge is one float shared by the two windows beside it."""
    if not math.isfinite(scan.first_s):
        return [(-math.inf, math.inf)]
    k = max(1, math.ceil((scan.end_s - scan.first_s) / window_s))
    inner = [scan.first_s + j * window_s for j in range(1, k)]
    lo = [-math.inf] + inner
    hi = inner + [math.inf]
    return list(zip(lo, hi))


def read_window(reader: BagReader, scan: TopicScan, lo_s: float, hi_s: float,
                pad_s: float = PAD_S) -> ChannelData:
    """The topic's samples with ``lo_s <= t < hi_s`` (absolute stream seconds; +-inf: open)."""
    t0 = reader.start_time_s
    a = (lo_s if math.isfinite(lo_s) else scan.first_s) - pad_s
    b = (hi_s if math.isfinite(hi_s) else scan.end_s) + pad_s
    # a finite duration also sizes read_topic's buffer to the window, not to the whole topic
    cd = reader.read_topic(scan.topic, start_s=a - t0, duration_s=b - a)
    t = cd.time_s
    m = (t >= lo_s) & (t < hi_s)
    if m.all():
        return cd
    return ChannelData(cd.topic, cd.channels, cd.units, cd.sample_rate_hz, t[m], cd.data[m],
                       cd.issues)


def iter_windows(reader: BagReader, scan: TopicScan, window_s: float | None = None):
    """``read_window`` over :func:`window_edges`: the topic in time order, window by window."""
    for lo, hi in window_edges(scan, window_s or scan.window_s()):
        yield read_window(reader, scan, lo, hi)


def concatenated(windows) -> ChannelData:
    """The windows as one ChannelData (for tests and small topics)."""
    ws = list(windows)
    if not ws:
        raise ValueError("no windows")
    w0 = ws[0]
    return ChannelData(w0.topic, w0.channels, w0.units, w0.sample_rate_hz,
                       np.concatenate([w.time_s for w in ws]),
                       np.concatenate([w.data for w in ws]), ())
