"""Display decimation of a SensorBlock stream: min, max and mean of each channel per display bin.

The rule: stream time is cut into bins of ``1 / display_rate_hz`` (default 50 Hz: 20 ms) on a grid
of whole multiples of the bin width (bin k holds the samples with k w <= t < (k + 1) w; sample
times stamp + i / rate, in integer nanoseconds so that a sample on a bin edge is never split by
rounding); a bin's value per channel is the mean, minimum and maximum of its finite samples (null
when it has none: a NaN residual where the twin has no valid prediction). The mean follows the
signal's shape, min / max keep its envelope, so a short spike that a mean would hide still shows.
A bin is complete, and emitted, once the stream has passed its end (the block's last sample period
ends at or beyond it, or a later block starts in a later bin); :meth:`Decimator.flush` emits the
last, incomplete one (end of a recording). Hand-written: the bins are a few numpy reduceat calls,
and they must carry over from block to block, which no resampling routine does.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DISPLAY_RATE_HZ = 50.0


@dataclass(frozen=True, eq=False)
class Bins:
    """Complete display bins of one stream: ``start_ns`` (k,), ``mean`` / ``min`` / ``max`` (k, n_ch)
    (NaN: no finite sample), ``count`` (k,) samples per bin."""
    channels: tuple[str, ...]
    width_ns: int
    start_ns: np.ndarray
    count: np.ndarray
    mean: np.ndarray
    min: np.ndarray
    max: np.ndarray

    def __len__(self) -> int:
        return int(self.start_ns.size)


class Decimator:
    """Bins one stream's blocks (see the module docstring); ``add(block)`` -> the bins completed."""

    def __init__(self, display_rate_hz: float = DISPLAY_RATE_HZ) -> None:
        if not display_rate_hz > 0:
            raise ValueError(f"display_rate_hz must be > 0, got {display_rate_hz!r}")
        self.width_ns = max(1, int(round(1e9 / float(display_rate_hz))))
        self.channels: tuple[str, ...] | None = None
        # the open bin: k, samples, finite count / sum / min / max per channel
        self._k: int | None = None
        self._n = 0
        self._cnt = self._sum = self._min = self._max = None

    def add(self, block) -> Bins | None:
        """The bins ``block`` completes (with the open bin before it when it starts later)."""
        out = []
        if self.channels != tuple(block.channels):
            if self._k is not None:        # a new layout (a new recording): close the old stream
                out.append(self._take_open())
            self.channels = tuple(block.channels)
        n = block.n_samples
        if n == 0:
            return self._pack(out)
        t_ns = int(block.stamp_ns) + np.round(np.arange(n) * (1e9 / block.sample_rate_hz)).astype(np.int64)
        k = t_ns // self.width_ns
        x = np.asarray(block.data, dtype=np.float64)
        fin = np.isfinite(x)
        starts = np.r_[0, np.flatnonzero(np.diff(k)) + 1]
        ks = k[starts]
        seg_n = np.diff(np.r_[starts, n])
        cnt = np.add.reduceat(fin.astype(np.int64), starts, axis=0)
        tot = np.add.reduceat(np.where(fin, x, 0.0), starts, axis=0)
        lo = np.fmin.reduceat(np.where(fin, x, np.nan), starts, axis=0)
        hi = np.fmax.reduceat(np.where(fin, x, np.nan), starts, axis=0)
        if self._k is not None:
            if self._k == ks[0]:           # the open bin continues in this block
                seg_n[0] += self._n
                cnt[0] += self._cnt
                tot[0] += self._sum
                lo[0] = np.fmin(lo[0], self._min)
                hi[0] = np.fmax(hi[0], self._max)
                self._k = None
            else:                          # a later bin (or time went back: a loop): close it
                out.append(self._take_open())
        # the last segment stays open unless the stream has already passed its end
        last_done = int(block.end_ns) >= (int(ks[-1]) + 1) * self.width_ns
        m = len(ks) if last_done else len(ks) - 1
        if m:
            out.append((ks[:m], seg_n[:m], cnt[:m], tot[:m], lo[:m], hi[:m]))
        if not last_done:
            self._k, self._n = int(ks[-1]), int(seg_n[-1])
            self._cnt, self._sum, self._min, self._max = cnt[-1], tot[-1], lo[-1], hi[-1]
        return self._pack(out)

    def flush(self) -> Bins | None:
        """The open (incomplete) bin, if any: call when the stream ends."""
        return self._pack([self._take_open()] if self._k is not None else [])

    def _take_open(self):
        part = (np.array([self._k]), np.array([self._n]), self._cnt[None], self._sum[None],
                self._min[None], self._max[None])
        self._k = None
        return part

    def _pack(self, parts) -> Bins | None:
        if not parts:
            return None
        ks, seg_n, cnt, tot, lo, hi = (np.concatenate(a) for a in zip(*parts))
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)
        return Bins(self.channels or (), self.width_ns, ks.astype(np.int64) * self.width_ns,
                    seg_n.astype(np.int64), mean, lo, hi)


def _num(v: float):
    return float(v) if np.isfinite(v) else None


def series_messages(bins: Bins, source: str = "") -> list[tuple[int, dict]]:
    """One JSON message per bin: ``(log_time_ns, message)``; message = ``t_s`` (bin start),
    ``bin_s``, ``n`` (samples), ``mean`` / ``min`` / ``max`` ({channel: value or null}) and
    ``source`` (the block's frame_id, e.g. the twin's "twin rev 3")."""
    out = []
    for i in range(len(bins)):
        t_ns = int(bins.start_ns[i])
        msg = {"t_s": t_ns * 1e-9, "bin_s": bins.width_ns * 1e-9, "n": int(bins.count[i]), "source": source}
        for stat in ("mean", "min", "max"):
            row = getattr(bins, stat)[i]
            msg[stat] = {ch: _num(v) for ch, v in zip(bins.channels, row)}
        out.append((t_ns, msg))
    return out


def series_schema(channels=(), title: str = "maglev.view.Series") -> dict:
    """JSON schema of :func:`series_messages`: ``channels`` named, any other channel name a number
    too (the bridge advertises its channels before a recording names its sensors)."""
    per_channel = {"type": "object", "properties": {c: {"type": "number"} for c in channels},
                   "additionalProperties": {"type": "number"}}
    return {"title": title, "type": "object",
            "properties": {"t_s": {"type": "number", "description": "bin start, stream time [s]"},
                           "bin_s": {"type": "number"}, "n": {"type": "integer"},
                           "source": {"type": "string"},
                           "mean": per_channel, "min": per_channel, "max": per_channel}}
