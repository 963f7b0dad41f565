"""A channel's time base: its sample rate, its contiguous stretches and the gaps between them.

DAQ exports give time as a column of stamps (rounded to the digits the export writes), as a
stated rate, or as the format's own waveform properties. :func:`analyse` turns stamps into a
rate and stretches on that rate's grid; a duplicated or backwards stamp, a step under half a
sample period or a stamp off the grid is one line naming the row (CSV) or sample index.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from maglev_ros.errors import UserError

__all__ = ["Segment", "Gap", "Timeline", "uniform", "analyse", "same_grid"]

Label = Callable[[int], str]


@dataclass(frozen=True)
class Segment:
    """Samples [start, stop) of a channel on one uninterrupted grid from stamp ``t0_ns``."""

    start: int
    stop: int
    t0_ns: int

    @property
    def n(self) -> int:
        return self.stop - self.start


@dataclass(frozen=True)
class Gap:
    """Missing samples before sample ``index`` (``where``: its row or sample index)."""

    index: int
    where: str
    gap_s: float
    missing: int

    def to_dict(self) -> dict:
        return {"index": self.index, "where": self.where, "gap_s": self.gap_s, "missing": self.missing}


@dataclass(frozen=True)
class Timeline:
    """Time base of ``n`` samples: one rate, stretches on its grid, gaps between them."""

    rate_hz: float
    n: int
    segments: tuple[Segment, ...]
    gaps: tuple[Gap, ...] = ()
    origin: str = "time column"       # where the rate came from (stated in the output)

    def times_ns(self) -> np.ndarray:
        """Grid stamp of every sample [ns, int64]: segment start + round(k / rate)."""
        out = np.empty(self.n, dtype=np.int64)
        for s in self.segments:
            k = np.arange(s.n, dtype=np.float64)
            out[s.start:s.stop] = s.t0_ns + np.round(k * 1e9 / self.rate_hz).astype(np.int64)
        return out

    @property
    def start_ns(self) -> int:
        return self.segments[0].t0_ns

    @property
    def end_ns(self) -> int:
        """Stamp just after the last sample."""
        s = self.segments[-1]
        return s.t0_ns + int(round(s.n * 1e9 / self.rate_hz))


def uniform(n: int, rate_hz: float, t0_ns: int, origin: str = "stated rate") -> Timeline:
    """``n`` samples at ``rate_hz`` from ``t0_ns``, no gaps."""
    return Timeline(float(rate_hz), int(n), (Segment(0, int(n), int(t0_ns)),), (), origin)


def _snap_rate(rate: float) -> float:
    """A rate estimated from rounded stamps, moved to the nearest 1 mHz when it is within 10 ppm
    of it (exports write 2000 Hz as stamps rounded to 1 us: the estimate lands a few ppb off)."""
    r = round(rate * 1000.0) / 1000.0
    return r if abs(rate - r) <= 1e-5 * rate else rate


def analyse(t0_ns: int, rel_s: np.ndarray, label: Label, where: str,
            origin: str = "time column") -> Timeline:
    """The time base of samples stamped ``t0_ns + rel_s`` (seconds, float64).

    A step above 1.5 sample periods is a gap (kept, reported with the sample after it); a step
    of zero, a negative step, a step under half a period or a stamp more than half a period
    off its stretch's grid is a UserError naming ``where`` and the sample's label."""
    t = np.asarray(rel_s, dtype=np.float64)
    n = t.size
    if n < 2:
        raise UserError(f"{where}: {n} sample(s); at least 2 are needed to know the sample rate")
    if not np.all(np.isfinite(t)):
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise UserError(f"{where}: {label(i)}: time {t[i]!r} is not a finite number")
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        what = "duplicated time" if d[i - 1] == 0 else "time goes backwards"
        raise UserError(f"{where}: {label(i)}: {what} ({t[i]:.9g} s after {t[i - 1]:.9g} s at "
                        f"{label(i - 1)}); time must increase")
    dt = float(np.median(d))
    short = np.flatnonzero(d < 0.5 * dt)
    if short.size:
        i = int(short[0]) + 1
        raise UserError(f"{where}: {label(i)}: time step {d[i - 1]:.9g} s is under half the sample "
                        f"period {dt:.9g} s (irregular sampling; a contract topic needs one rate)")
    cuts = np.flatnonzero(d > 1.5 * dt) + 1
    bounds = np.concatenate([[0], cuts, [n]])
    # rate over every stretch of >= 2 samples: (samples - 1) / elapsed, least-squares-like
    steps = sum(int(b - a - 1) for a, b in zip(bounds[:-1], bounds[1:]))
    elapsed = sum(float(t[b - 1] - t[a]) for a, b in zip(bounds[:-1], bounds[1:]))
    rate = _snap_rate(steps / elapsed) if steps > 0 and elapsed > 0 else 1.0 / dt
    period = 1.0 / rate
    segments, gaps = [], []
    for a, b in zip(bounds[:-1], bounds[1:]):
        a, b = int(a), int(b)
        off = t[a:b] - (t[a] + np.arange(b - a) * period)
        worst = int(np.argmax(np.abs(off)))
        if abs(off[worst]) > 0.5 * period:
            i = a + worst
            raise UserError(f"{where}: {label(i)}: time {t[i]:.9g} s is {off[worst]:+.3g} s off the "
                            f"{rate:.6g} Hz grid of the samples before it (irregular sampling)")
        segments.append(Segment(a, b, int(t0_ns) + int(round(t[a] * 1e9))))
        if a > 0:
            g = float(t[a] - t[a - 1])
            gaps.append(Gap(a, label(a), g, max(1, int(round(g * rate)) - 1)))
    return Timeline(rate, n, tuple(segments), tuple(gaps), origin)


def same_grid(a: Timeline, b: Timeline) -> bool:
    """Whether two time bases sample at the same stamps (rate to 1 ppm, stretches to 1/4 sample)."""
    if a.n != b.n or len(a.segments) != len(b.segments) or abs(a.rate_hz - b.rate_hz) > 1e-6 * a.rate_hz:
        return False
    tol = 0.25e9 / a.rate_hz
    return all(sa.start == sb.start and sa.stop == sb.stop and abs(sa.t0_ns - sb.t0_ns) <= tol
               for sa, sb in zip(a.segments, b.segments))
