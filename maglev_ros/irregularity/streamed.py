"""The inertial profile of a recording read window by window: :meth:`InertialProfiler.fit`
without holding the pass (no rclpy).

The batch fit holds every vehicle channel as float64 and a dozen per-sample arrays per magnet
(times, positions, speeds, masks, the FFT buffers of each clean stretch): about 40 x 8 bytes per
accelerometer sample, 1.2 GB for 30 min at 1 kHz. Only a few of its steps look at the whole
pass; :func:`profile_streamed` computes those in light passes over the windows of
:mod:`maglev_ros.bag_windows` and runs the fit itself window by window:

1. ``setup``: whether the gap samples share the accelerometers' time base (the batch rule,
   :meth:`InertialProfiler._timebase`) and, when not, the gap's median sample step;
2. ``dropouts``: every magnet's accelerometer and gap dropouts (:class:`DropoutScan`: the runs of
   ``detect_dropouts`` carried across windows, so the same intervals and warnings); with the
   moving stretches from the position they give the clean stretches, the automatic corner and
   the clean segments each magnet's double integration works on;
3. ``speeds``: the band speed's distribution (the 5th percentile of the band-test speed by
   distance: histogram, then the values of the one bin it falls in, exactly), the top speed,
   the samples without position, and each segment's mean and bias (``estimate_bias`` in two
   sums);
4. ``profile``: per window, :meth:`InertialProfiler.samples` on the window plus ``margin`` on
   each side, binning only the window's own samples.

Results. Step 4 is the batch computation on a piece of each clean segment. A segment wholly
inside one window (every segment of a record shorter than a window: the sample bags) is
integrated exactly as in the batch fit; a pass within one window is fitted whole by the batch
code. A longer segment is cut, and its pieces are integrated with the whole segment's means
(:func:`~maglev_ros.irregularity.integration.double_integrate`'s ``segment_means``). A sample
then misses only the segment beyond the cut, at least ``MARGIN_PER_CORNER / f_c`` away, where
the impulse response of the band-limited double integral has decayed as
exp(-2 pi sin(pi/8) f_c t), by e^-24; and within a few 1/f_c of the segment's true ends the batch
FFT wraps the segment's other end around over its 2/f_c zero pad, which a cut piece does not
see: 4e-7 of the profile's peak measured there, 1e-11 elsewhere. Sums are taken in another order
(segment means, grid bins: 1e-16 relative). tests/test_faults_memory.py states the tolerance
against the batch fit. Memory: one window and its two margins per topic, the dropout
intervals, the profile grid.
"""
from __future__ import annotations

import bisect
import math
from collections import Counter
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.irregularity.integration import DataWarning, _runs
from maglev_ros.irregularity.profile import InertialProfiler, _BinAccumulator, _finish

#: each window is processed with this many corner periods (1/f_c) of context on both sides
MARGIN_PER_CORNER = 10.0
#: histogram bins of the band-speed percentile (the bin holding it is then read exactly)
SPEED_BINS = 4096
#: values of one histogram bin read into memory at most; a fuller bin is split again
SPEED_BIN_VALUES = 200_000


# ------------------------------------------------------------------------- run tracking
class Runs:
    """Half-open index runs of True in a boolean stream given in consecutive pieces."""

    def __init__(self):
        self.n = 0
        self.open: int | None = None
        self.done: list[tuple[int, int]] = []

    def push(self, mask: np.ndarray) -> list[tuple[int, int]]:
        """Add the next piece; returns the runs it closed."""
        m = np.asarray(mask, bool)
        L = m.size
        closed = []
        if L == 0:
            return closed
        if self.open is not None and not m[0]:
            closed.append((self.open, self.n))
            self.open = None
        for i0, i1 in _runs(m):
            g0 = self.open if (i0 == 0 and self.open is not None) else self.n + int(i0)
            self.open = None
            if i1 == L:
                self.open = g0
            else:
                closed.append((g0, self.n + int(i1)))
        self.n += L
        self.done += closed
        return closed

    def finish(self) -> list[tuple[int, int]]:
        if self.open is not None:
            self.done.append((self.open, self.n))
            self.open = None
        return self.done


class DropoutScan:
    """:func:`~maglev_ros.irregularity.integration.detect_dropouts` (default thresholds) of one
    channel given in consecutive pieces: the same bad intervals and warnings, in its order."""

    def __init__(self, fs_hz: float, channel: str, flat_min_s: float = 0.02,
                 flat_min_samples: int = 8):
        self.fs, self.channel = float(fs_hz), channel
        self.nmin = max(int(flat_min_samples), int(math.ceil(flat_min_s * fs_hz)))
        self.n = 0
        self.nonfin = Runs()                     # over samples
        self.same = Runs()                       # over pairs (i, i+1), indexed by i
        self.nf_start_t = None                   # time of the open non-finite run's first sample
        self.same_start = None                   # (time, value) of the open equal run's first sample
        self.last = None                         # (t, xf, non-finite) of the last sample so far
        self.warn = {"nonfinite": [], "flatline": [], "time_gap": []}
        self.bad: list[tuple[int, int]] = []

    def _nonfinite(self, g0, g1, t0, t1):
        self.warn["nonfinite"].append(DataWarning(
            "nonfinite", self.channel, f"{self.channel}: {g1 - g0} non-finite samples", t0, t1))
        self.bad.append((g0, g1))

    def _flat(self, g0, g1, t0, v0, t1):
        # pairs [g0, g1) equal: samples g0 .. g1
        if g1 - g0 + 1 >= self.nmin:
            self.bad.append((g0, g1 + 1))
            self.warn["flatline"].append(DataWarning(
                "flatline", self.channel,
                f"{self.channel}: value stuck at {v0:.6g} for {g1 - g0 + 1} samples", t0, t1, v0))

    def push(self, t: np.ndarray, x: np.ndarray) -> None:
        t = np.asarray(t, float)
        x = np.asarray(x, float)
        L = x.size
        if L == 0:
            return
        n0 = self.n
        nonfin = ~np.isfinite(x)
        xf = np.where(nonfin, 0.0, x)
        for g0, g1 in self.nonfin.push(nonfin):
            t0 = float(t[g0 - n0]) if g0 >= n0 else self.nf_start_t
            t1 = float(t[g1 - 1 - n0]) if g1 - 1 >= n0 else self.last[0]
            self._nonfinite(g0, g1, t0, t1)
        o = self.nonfin.open
        if o is not None and o >= n0:
            self.nf_start_t = float(t[o - n0])
        # pairs (i, i + 1), from the previous piece's last sample on: sample of pair p is p - p0
        if self.last is not None:
            te = np.concatenate([[self.last[0]], t])
            xe = np.concatenate([[self.last[1]], xf])
            ne = np.concatenate([[self.last[2]], nonfin])
            p0 = n0 - 1
        else:
            te, xe, ne, p0 = t, xf, nonfin, n0
        same = (np.abs(np.diff(xe)) <= 0.0) & ~ne[1:] & ~ne[:-1]
        for g0, g1 in self.same.push(same):
            if g0 >= p0:
                t0, v0 = float(te[g0 - p0]), float(xe[g0 - p0])
            else:
                t0, v0 = self.same_start
            self._flat(g0, g1, t0, v0, float(te[g1 - p0]))
        o = self.same.open
        if o is not None and o >= p0:
            self.same_start = (float(te[o - p0]), float(xe[o - p0]))
        dt = np.diff(te)
        for i in np.flatnonzero(dt > 1.5 / self.fs):
            g = p0 + int(i)
            self.bad.append((g, g + 2))
            self.warn["time_gap"].append(DataWarning(
                "time_gap", self.channel, f"{self.channel}: {dt[i]:.4g} s without samples",
                float(te[i]), float(te[i + 1])))
        self.last = (float(t[-1]), float(xf[-1]), bool(nonfin[-1]))
        self.n += L

    def finish(self) -> tuple[list[tuple[int, int]], list[DataWarning]]:
        """(merged bad intervals, warnings in detect_dropouts' order)."""
        if self.nonfin.open is not None:
            g0 = self.nonfin.open
            self._nonfinite(g0, self.n, self.nf_start_t, self.last[0])
        if self.same.open is not None:
            t0, v0 = self.same_start
            self._flat(self.same.open, self.n - 1, t0, v0, self.last[0])
        self.nonfin.finish()
        self.same.finish()
        return (_merge(self.bad),
                self.warn["nonfinite"] + self.warn["flatline"] + self.warn["time_gap"])


def _merge(intervals) -> list[tuple[int, int]]:
    """Sorted, merged half-open intervals."""
    out: list[list[int]] = []
    for a, b in sorted(intervals):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _complement(bad, n: int) -> list[tuple[int, int]]:
    """Runs of 0..n-1 outside the merged intervals ``bad``."""
    out, i = [], 0
    for a, b in bad:
        if a > i:
            out.append((i, a))
        i = max(i, b)
    if i < n:
        out.append((i, n))
    return out


def _intersect(a, b) -> list[tuple[int, int]]:
    """Intersection of two sorted lists of disjoint half-open intervals."""
    out, i, j = [], 0, 0
    while i < len(a) and j < len(b):
        lo, hi = max(a[i][0], b[j][0]), min(a[i][1], b[j][1])
        if lo < hi:
            out.append((lo, hi))
        if a[i][1] < b[j][1]:
            i += 1
        else:
            j += 1
    return out


def _mask(intervals, i0: int, i1: int) -> np.ndarray:
    """Boolean mask of indices i0 .. i1-1 covered by the merged intervals."""
    m = np.zeros(i1 - i0, bool)
    if intervals:
        starts = np.array([a for a, _ in intervals])
        k = max(int(np.searchsorted(starts, i0, side="right")) - 1, 0)
        for a, b in intervals[k:]:
            if a >= i1:
                break
            if b > i0:
                m[max(a, i0) - i0:min(b, i1) - i0] = True
    return m


# ------------------------------------------------------------------------------- reading
EDGE_EPS_S = 1e-3            # raw read range beyond a delayed window (ulps of shifted edges)


@dataclass
class VehicleTopics:
    """The vehicle topics of an open bag: accel and gap read in windows (each a
    ``bag_windows.CheckedTopic``; acquisition delays), the position whole (small: 2 channels at
    50-1000 Hz), delayed."""
    reader: object
    accel: object
    gap: object
    accel_delay_s: float
    gap_delay_s: float
    position: object                   # ChannelData, delayed
    window_s: float | None = None      # core window length (default: bag_windows' rule)


def _read(src: VehicleTopics, scan, delay: float, lo: float, hi: float):
    """(times, data) of the samples whose delayed time is in [lo, hi)."""
    from maglev_ros.bag_windows import read_window
    w = read_window(src.reader, scan, lo + delay - EDGE_EPS_S, hi + delay + EDGE_EPS_S)
    t = w.time_s - float(delay) if delay else w.time_s
    m = (t >= lo) & (t < hi)
    return t[m], w.data[m]


class _RowsByIndex:
    """A topic's samples by index, loaded window by window in record order; rows before the
    last request's start are dropped. ``on_load(t, data)`` sees every sample once."""

    def __init__(self, src: VehicleTopics, scan, delay: float, window_s: float, on_load=None):
        from maglev_ros.bag_windows import window_edges
        self.src, self.scan, self.delay = src, scan, delay
        self.edges = iter(window_edges(scan, window_s))
        self.t = np.zeros(0)
        self.d = np.zeros((0, len(scan.channels)))
        self.i0 = 0
        self.on_load = on_load
        self.done = False

    def _load(self) -> bool:
        for lo, hi in self.edges:
            t, d = _read(self.src, self.scan, self.delay, lo - self.delay, hi - self.delay)
            if self.on_load is not None:
                self.on_load(t, d)
            self.t = np.concatenate([self.t, t])
            self.d = np.concatenate([self.d, d])
            return True
        self.done = True
        return False

    def take(self, a: int, b: int):
        """Rows a .. b-1 (fewer when the topic ends first); a never decreases between calls."""
        while self.i0 + self.t.size < b and self._load():
            pass
        k = max(a - self.i0, 0)
        self.t, self.d, self.i0 = self.t[k:], self.d[k:], self.i0 + k
        return self.t[:b - a], self.d[:b - a]

    def drain(self) -> None:
        while self._load():
            self.t, self.d = self.t[:0], self.d[:0]


@dataclass
class _Setup:
    n: int                             # accel samples
    same: bool                         # gap on the accel time base (the batch rule)
    gap_step_s: float | None = None    # the gap's median sample step (when not the same)
    gap_span_s: tuple | None = None    # its first and last time


@dataclass
class _Segment:
    """One clean stretch of a magnet's double integration and the sums of its statistics."""
    i0: int
    i1: int
    t0: float = math.nan
    t1: float = math.nan
    sum_a: float = 0.0
    sum_dg: float = 0.0
    last_a: float = math.nan
    last_v: float = 0.0
    sum_v: float = 0.0
    sum_jv: float = 0.0
    sum_r: float = 0.0
    sum_r2: float = 0.0
    last_sign: bool | None = None
    crossings: int = 0


class _Stream:
    """The windows of the accel topic and the gap on its time base, in delayed time."""

    def __init__(self, src: VehicleTopics, cfg: InertialProfiler, setup: _Setup | None,
                 window_s: float | None = None):
        from maglev_ros.bag_windows import window_edges
        self.src, self.cfg, self.setup = src, cfg, setup
        self.fs = float(src.accel.sample_rate_hz)
        self.window_s = window_s or src.window_s or src.accel.window_s()
        da = src.accel_delay_s
        self.edges = [(lo - da, hi - da) for lo, hi in window_edges(src.accel, self.window_s)]

    def windows(self, context_s: float = 0.0, gap: bool = False):
        """Per core window: (t, accel, gap on t or None, core slice, global index of t[0])."""
        src, s = self.src, self.setup
        rows = (_RowsByIndex(src, src.gap, src.gap_delay_s, self.window_s)
                if gap and s.same else None)
        done = 0
        for lo, hi in self.edges:
            t, a = _read(src, src.accel, src.accel_delay_s, lo - context_s, hi + context_s)
            j0 = int(np.searchsorted(t, lo))
            j1 = int(np.searchsorted(t, hi))
            first = done - j0
            g = None
            if gap and s.same:
                tg, g = rows.take(first, first + t.size)
                if tg.size < t.size:       # cannot happen when the counts are equal
                    raise UserError("/testline/vehicle/gap: fewer samples than the accelerations")
            elif gap:
                pad = 2.0 + 5.0 * s.gap_step_s
                tg, gd = _read(src, src.gap, src.gap_delay_s, lo - context_s - pad,
                               hi + context_s + pad)
                g = (np.column_stack([self.cfg._gap_on(t, tg, False, gd[:, c], s.gap_step_s,
                                                        s.gap_span_s)
                                      for c in range(gd.shape[1])])
                     if tg.size >= 2 else np.full((t.size, len(src.gap.channels)), np.nan))
            yield t, a, g, slice(j0, j1), first
            done += j1 - j0


# --------------------------------------------------------------------------------- passes
def _setup(src: VehicleTopics, stream: _Stream) -> _Setup:
    """Accel count; whether the gap shares its time base (np.allclose on the whole records, as
    the batch fit decides); the gap's median step and span."""
    steps: Counter = Counter()
    state = {"last": None, "first": None, "n": 0}

    def on_load(t, _d):
        if not t.size:
            return
        if state["first"] is None:
            state["first"] = float(t[0])
        te = t if state["last"] is None else np.concatenate([[state["last"]], t])
        steps.update(np.diff(te).tolist())
        state["last"] = float(t[-1])
        state["n"] += t.size

    rows = _RowsByIndex(src, src.gap, src.gap_delay_s, stream.window_s, on_load)
    n = 0
    close = True
    atol = 0.25 / stream.fs
    for lo, hi in stream.edges:
        t, _ = _read(src, src.accel, src.accel_delay_s, lo, hi)
        tg, _ = rows.take(n, n + t.size)
        k = tg.size
        if close and k and not np.all(np.abs(tg - t[:k]) <= atol + 1e-5 * np.abs(t[:k])):
            close = False
        n += t.size
    rows.drain()
    same = close and state["n"] == n
    step = None
    if not same and sum(steps.values()):
        vals = sorted(steps)
        cum = np.cumsum([steps[v] for v in vals])
        m = int(cum[-1])
        # np.median: the middle value, or the mean of the two middle values
        pick = [int(np.searchsorted(cum, k, side="right")) for k in
                ((m - 1) // 2, m // 2)]
        step = float(np.mean([vals[pick[0]], vals[pick[1]]]))
    span = None if state["first"] is None else (state["first"], state["last"])
    return _Setup(n, same, step, span)


def profile_streamed(src: VehicleTopics, profiler: InertialProfiler, magnet_offsets_m,
                     nominal_gap_m: float = 0.010, channel_pairs: dict | None = None):
    """:meth:`InertialProfiler.fit` (no deflection) of the recording ``src``, read window by
    window (see the module docstring); a recording within one window is read whole and fitted
    by the batch code."""
    from maglev_ros.bag_windows import read_window, window_edges
    cfg = profiler
    stream = _Stream(src, cfg, None)
    acc_ns = SimpleNamespace(channels=src.accel.channels)
    gap_ns = SimpleNamespace(channels=src.gap.channels)
    specs = cfg._specs(acc_ns, gap_ns, magnet_offsets_m, channel_pairs)
    for t in (src.accel, src.gap):
        if t.n_samples < 4:
            raise UserError(f"{t.topic}: fewer than 4 samples")
    if len(window_edges(src.accel, stream.window_s)) == 1:
        accel, gap = (read_window(src.reader, t, -math.inf, math.inf).delayed_by(d)
                      for t, d in ((src.accel, src.accel_delay_s), (src.gap, src.gap_delay_s)))
        return cfg.fit(accel, gap, src.position, magnet_offsets_m, nominal_gap_m, None,
                       channel_pairs)
    stream.setup = setup = _setup(src, stream)
    n, fs = setup.n, stream.fs
    if n < 4:
        raise UserError("/testline/vehicle/accel: fewer than 4 samples")
    a_col = [src.accel.channels.index(s.accel_channel) for s in specs]
    g_col = [src.gap.channels.index(s.gap_channel) for s in specs]

    # dropouts of every magnet's accel and gap (on the accel time base), moving stretches
    scans_a = [DropoutScan(fs, s.accel_channel) for s in specs]
    scans_g = [DropoutScan(fs, s.gap_channel) for s in specs]
    moving = Runs()
    for t, a, g, core, _ in stream.windows(gap=True):
        _, v = cfg.reference_motion(t, src.position)
        moving.push(np.isfinite(v) & (v >= cfg.stop_speed_mps))
        for k in range(len(specs)):
            scans_a[k].push(t, a[:, a_col[k]])
            scans_g[k].push(t, g[:, g_col[k]])
    moving_runs = moving.finish()
    bad, drop_warns = [], []
    for k in range(len(specs)):
        ba, wa = scans_a[k].finish()
        bg, wg = scans_g[k].finish()
        bad.append(_merge(ba + bg))
        drop_warns.append((wg, wa))
    if cfg.highpass_hz is None:
        best = max((b - a for k in range(len(specs))
                    for a, b in _intersect(_complement(bad[k], n), moving_runs)), default=0)
        if best == 0:
            raise UserError("/testline/vehicle/position: no clean stretch where the vehicle moves "
                            f"faster than stop_speed_mps={cfg.stop_speed_mps:g} m/s")
        cfg = cfg.with_corner(cfg.corner_for(best / fs))
        stream.cfg = cfg
    fc = cfg.highpass_hz
    nedge = int(round(cfg.edge_s * fs))
    min_len = 2 * nedge + int(math.ceil(2.0 / fc * fs))
    segs = [[_Segment(a, b) for a, b in _complement(bad[k], n)] for k in range(len(specs))]

    # band-test speeds (histogram of the percentile), top speed, samples without position,
    # segment sums; the band speed given by the caller needs no histogram
    need_pct = cfg.max_wavelength_m is None and cfg.band_speed_mps is None
    spd = np.abs(np.asarray(src.position.channel("speed_mps"), float))
    spd = spd[np.isfinite(spd)]
    top = float(spd.max()) if spd.size else cfg.stop_speed_mps
    hist = _SpeedHistogram(cfg.stop_speed_mps, max(top, cfg.stop_speed_mps) * (1 + 1e-9) + 1e-12)
    v_max = -math.inf
    nopos = [0, None, None]
    ctx = 1.0 / fc + 1.0
    dt = 1.0 / fs
    g0 = float(nominal_gap_m)
    for t, a, g, core, first in stream.windows(context_s=ctx, gap=True):
        _, v_raw = cfg.reference_motion(t, src.position)
        v = cfg.band_speed_series(v_raw, fs)[core]
        tc = t[core]
        mv = v >= cfg.stop_speed_mps
        if mv.any():
            v_max = max(v_max, float(v[mv].max()))
            if need_pct:
                hist.add(v[mv], v[mv] * dt)
        bad_pos = ~np.isfinite(v)
        if bad_pos.any():
            nopos[0] += int(bad_pos.sum())
            nopos[1] = float(tc[bad_pos][0]) if nopos[1] is None else nopos[1]
            nopos[2] = float(tc[bad_pos][-1])
        i_core = first + core.start
        for k in range(len(specs)):
            _segment_sums(segs[k], a[core, a_col[k]], tc, i_core, dt, min_len, stage=1,
                          dg=g[core, g_col[k]] - g0)
    # the band (batch: InertialProfiler._band), the percentile read exactly from its bin
    if cfg.max_wavelength_m is not None:
        v_band = cfg.band_factor * fc * float(cfg.max_wavelength_m)
    elif cfg.band_speed_mps is not None:
        v_band = float(cfg.band_speed_mps)
    else:
        if not hist.total_n:
            raise UserError("/testline/vehicle/position: vehicle never moves faster than "
                            f"stop_speed_mps={cfg.stop_speed_mps}")
        v_band = None
    stage2 = [False]

    def speed_pass(chain, keep):
        """One pass: the histogram of the speeds in the bins ``chain`` [(histogram, bin)] (their
        values too when ``keep``), and the bias statistics' second sums the first time."""
        h, k = chain[-1]
        lo, hi = h.edges(k)
        sub = _SpeedHistogram(lo, hi)
        for t, a, _, core, first in stream.windows(context_s=ctx):
            _, v_raw = cfg.reference_motion(t, src.position)
            v = cfg.band_speed_series(v_raw, fs)[core]
            sel = v >= cfg.stop_speed_mps
            for hh, kk in chain:
                sel &= hh.bins(v) == kk
            sub.add(v[sel], v[sel] * dt, keep)
            if not stage2[0]:
                for j in range(len(specs)):
                    _segment_sums(segs[j], a[core, a_col[j]], t[core], first + core.start, dt,
                                  min_len, stage=2)
        stage2[0] = True
        return sub

    if v_band is None:
        v_band = _percentile(hist, speed_pass, cfg.speed_percentile)
    if not stage2[0]:
        for t, a, _, core, first in stream.windows():
            for j in range(len(specs)):
                _segment_sums(segs[j], a[core, a_col[j]], t[core], first + core.start, dt,
                              min_len, stage=2)
    v_band = max(v_band, cfg.stop_speed_mps)
    v_top = v_max if math.isfinite(v_max) else v_band
    lam_min = cfg.shortest_wavelength_m(v_top, fs)
    lam_max = cfg.longest_wavelength_m(v_band)
    slow_mps = cfg.slow_speed_mps(v_band)

    # the profile: the batch computation on each window and its margins, binned on the core
    margin = MARGIN_PER_CORNER / fc
    acc = _BinAccumulator(cfg.spacing_m)
    slow = _SlowRuns(slow_mps, dt)
    for t, a, g, core, first in stream.windows(context_s=margin, gap=True):
        if t.size < 4:
            continue
        a_ns = SimpleNamespace(time_s=t, data=a, channels=src.accel.channels, sample_rate_hz=fs)
        g_ns = SimpleNamespace(time_s=t, data=g, channels=src.gap.channels, sample_rate_hz=fs)
        # a piece of a segment loses its whole segment's means, not its own
        hooks = [_means_hook(segs[k], first, min_len) for k in range(len(specs))]
        _, samp, _, _, _, _ = cfg.samples(a_ns, g_ns, src.position, magnet_offsets_m,
                                          g0, None, channel_pairs, hooks, report_bias=False)
        for k, (x, r, vv) in enumerate(samp):
            x, r, vv = x[core], r[core], vv[core]
            keep = np.isfinite(r) & (vv >= slow_mps)
            acc.add(k, x[keep], r[keep])
        slow.push(t[core], samp[0][2][core])

    warns, biases = [], []
    for k, spec in enumerate(specs):
        wg, wa = drop_warns[k]
        warns += wg + wa + _segment_warnings(segs[k], spec.accel_channel, fs, fc, min_len, cfg)
        means = [s.sum_a / (s.i1 - s.i0) for s in segs[k] if s.i1 - s.i0 >= min_len]
        biases.append(float(np.mean(means)) if means else 0.0)
    warns += slow.warnings(cfg.stop_speed_mps)
    if nopos[0]:
        warns.append(DataWarning(
            "position_coverage", "/testline/vehicle/position",
            f"{nopos[0]} accel samples lie outside the position record; not mapped",
            nopos[1], nopos[2]))
    step_m = v_max / fs if math.isfinite(v_max) else 0.0
    return _finish(acc, specs, warns, biases, cfg, v_band, lam_min, lam_max, kind="loaded",
                   sample_step_m=step_m)


def _means_hook(segs, first: int, min_len: int):
    """double_integrate's ``segment_means`` for a window whose sample 0 is record sample
    ``first``: the means of the magnet's whole segment holding a local clean run."""
    starts = [s.i0 for s in segs]

    def means(i0: int, i1: int):
        j = bisect.bisect_right(starts, first + i0) - 1
        if j < 0:
            return None
        s = segs[j]
        n = s.i1 - s.i0
        if not (first + i1 <= s.i1 and n >= min_len):
            return None
        return s.sum_a / n, s.sum_dg / n
    return means


def _segment_sums(segs, a, t, i_core: int, dt: float, min_len: int, stage: int,
                  dg=None) -> None:
    """Add the samples ``i_core ..`` (accel ``a`` at times ``t``) to the sums of the segments
    they fall in: stage 1 the end times, the means (with the gap change ``dg``) and the
    velocity's trend (estimate_bias' slope), stage 2 the residual's spread and zero crossings
    (they need the slope)."""
    i_end = i_core + a.size
    for s in segs:
        if s.i0 >= i_end:
            break
        if s.i1 <= i_core:
            continue
        lo, hi = max(s.i0, i_core), min(s.i1, i_end)
        if stage == 1:
            if lo == s.i0:
                s.t0 = float(t[lo - i_core])
            if hi == s.i1:
                s.t1 = float(t[hi - 1 - i_core])
        nseg = s.i1 - s.i0
        if nseg < min_len:
            continue
        x = a[lo - i_core:hi - i_core]
        j = np.arange(lo - s.i0, hi - s.i0, dtype=float) - 0.5 * (nseg - 1)
        # velocity by the trapezoid rule from the segment's first sample (0 there), carried
        # across windows; summed in order, as np.cumsum does
        inc = 0.5 * (x + np.concatenate([[s.last_a if lo > s.i0 else x[0]], x[:-1]])) * dt
        if lo == s.i0:
            inc[0] = 0.0
        v = np.cumsum(np.concatenate([[s.last_v if lo > s.i0 else 0.0], inc]))[1:]
        if stage == 1:
            s.sum_a = float(np.add.reduce(np.concatenate([[s.sum_a], x])))
            s.sum_dg = float(np.add.reduce(np.concatenate([[s.sum_dg],
                                                           dg[lo - i_core:hi - i_core]])))
            s.sum_v += float(v.sum())
            s.sum_jv += float(np.dot(j, v))
        else:
            r = v - s.sum_v / nseg - _slope(s, dt) * j * dt
            s.sum_r += float(r.sum())
            s.sum_r2 += float(np.dot(r, r))
            sb = np.signbit(r)
            if lo > s.i0:
                sb = np.concatenate([[s.last_sign], sb])
            s.crossings += int(np.count_nonzero(np.diff(sb)))
            s.last_sign = bool(sb[-1])
        s.last_a = float(x[-1])
        s.last_v = float(v[-1])


def _slope(s: _Segment, dt: float) -> float:
    """estimate_bias' least-squares slope of the velocity: sum (j - jbar) v_j / (dt sum (j - jbar)^2)."""
    n = s.i1 - s.i0
    return s.sum_jv / (dt * n * (n * n - 1) / 12.0)


def _segment_warnings(segs, channel: str, fs: float, fc: float, min_len: int, cfg) -> list:
    """double_integrate's per-segment warnings (short stretch left out; significant bias)."""
    out = []
    dt = 1.0 / fs
    for s in segs:
        n = s.i1 - s.i0
        if n < min_len:
            out.append(DataWarning("short_segment", channel,
                                   f"{channel}: clean stretch of {n / fs:.3g} s is shorter "
                                   f"than {min_len / fs:.3g} s needed at f_c={fc:g} Hz; "
                                   f"left out", s.t0, s.t1))
            continue
        b = _slope(s, dt)
        if n < 4:
            continue
        mean_r = s.sum_r / n
        sd = math.sqrt(max(s.sum_r2 / n - mean_r * mean_r, 0.0))
        T = n * dt
        se = math.sqrt(12.0) * sd / T / math.sqrt(max(1.0, s.crossings / 2.0))
        if abs(b) > cfg.bias_sigma * se and abs(b) > cfg.bias_floor_mps2:
            out.append(DataWarning(
                "accel_bias", channel,
                f"{channel}: constant offset {b:+.4g} m/s^2 (standard error {se:.2g}) removed before "
                f"integration", s.t0, s.t1, b))
    return out


class _SlowRuns:
    """_slow_warnings of the batch fit over windows: runs of at least 2 samples below the band's
    slowest speed, with their duration and distance."""

    def __init__(self, slow_mps: float, dt: float):
        self.slow, self.dt = slow_mps, dt
        self.runs = Runs()
        self.open_sum = 0.0
        self.open_t0 = None
        self.last_t = None
        self.found = []                  # (n, distance, t0, t1)

    def push(self, t, v) -> None:
        if not t.size:
            return
        m = v < self.slow
        n0 = self.runs.n
        closed = self.runs.push(m)
        for g0, g1 in closed:
            if g0 < n0:
                dist = self.open_sum + float(np.sum(v[:g1 - n0])) if g1 > n0 else self.open_sum
                t0 = self.open_t0
            else:
                dist, t0 = float(np.sum(v[g0 - n0:g1 - n0])), float(t[g0 - n0])
            t1 = float(t[g1 - 1 - n0]) if g1 - 1 >= n0 else self.last_t
            self.found.append((g1 - g0, dist, t0, t1))
        o = self.runs.open
        if o is not None:
            if o >= n0:
                self.open_sum, self.open_t0 = float(np.sum(v[o - n0:])), float(t[o - n0])
            else:
                self.open_sum += float(np.sum(v))
        self.last_t = float(t[-1])

    def warnings(self, stop: float) -> list:
        if self.runs.open is not None:
            self.found.append((self.runs.n - self.runs.open, self.open_sum, self.open_t0,
                               self.last_t))
            self.runs.finish()
        out = []
        for n, dist, t0, t1 in self.found:
            if n < 2:
                continue
            dist *= self.dt
            out.append(DataWarning(
                "slow_section", "/testline/vehicle/position",
                f"speed below {self.slow:.3g} m/s (the band's slowest) for {n * self.dt:.3g} s "
                f"({dist:.3g} m travelled, stops below {stop:g} m/s); those positions are dropped",
                t0, t1, dist))
        return out


class _SpeedHistogram:
    """Weights (distance) of band-test speeds in SPEED_BINS equal bins over [lo, hi) (outside
    values go to the end bins), with each bin's count and extreme values; ``keep`` also keeps
    the values themselves."""

    def __init__(self, lo: float, hi: float):
        self.lo, self.hi = float(lo), float(hi)
        self.w = np.zeros(SPEED_BINS)
        self.n = np.zeros(SPEED_BINS, dtype=np.int64)
        self.vmin = np.full(SPEED_BINS, np.inf)
        self.vmax = np.full(SPEED_BINS, -np.inf)
        self.total_n = 0
        self.total_w = 0.0
        self.values: list = []
        self.weights: list = []

    def bins(self, v):
        width = self.hi - self.lo
        if not width > 0:
            return np.zeros(np.shape(v), dtype=np.int64)
        k = np.floor((v - self.lo) / width * SPEED_BINS)
        return np.clip(np.nan_to_num(k, nan=0.0), 0, SPEED_BINS - 1).astype(np.int64)

    def edges(self, k: int) -> tuple[float, float]:
        width = (self.hi - self.lo) / SPEED_BINS
        return self.lo + k * width, self.lo + (k + 1) * width

    def add(self, v, w, keep: bool = False) -> None:
        if not v.size:
            return
        k = self.bins(v)
        self.w += np.bincount(k, weights=w, minlength=SPEED_BINS)
        self.n += np.bincount(k, minlength=SPEED_BINS)
        np.minimum.at(self.vmin, k, v)
        np.maximum.at(self.vmax, k, v)
        self.total_n += v.size
        self.total_w += float(np.sum(w))
        if keep:
            self.values.append(np.asarray(v, float))
            self.weights.append(np.asarray(w, float))


def _percentile(hist: _SpeedHistogram, speed_pass, percentile: float) -> float:
    """InertialProfiler._band's percentile (values sorted, cumulative weight, the first value
    whose cumulative weight reaches ``percentile`` % of the total) from the histogram ``hist``:
    the bin it falls in is read again by ``speed_pass(chain, keep)`` and its values sorted, or,
    when it holds more than SPEED_BIN_VALUES, split into a finer histogram first."""
    target = hist.total_w * percentile / 100.0
    below = 0.0
    chain = []
    h = hist
    while True:
        cum = below + np.cumsum(h.w)
        k = int(min(np.searchsorted(cum, target), SPEED_BINS - 1))
        while h.n[k] == 0 and k > 0 and (k == SPEED_BINS - 1 or not h.n[k:].any()):
            k -= 1                     # past the last value (rounding): the last non-empty bin
        while h.n[k] == 0 and k < SPEED_BINS - 1:
            k += 1
        if h.vmin[k] == h.vmax[k]:
            return float(h.vmin[k])
        below_k = below + float(np.sum(h.w[:k]))
        chain.append((h, k))
        keep = h.n[k] <= SPEED_BIN_VALUES
        sub = speed_pass(chain, keep)
        if keep:
            v = np.concatenate(sub.values)
            w = np.concatenate(sub.weights)
            order = np.argsort(v)
            i = int(np.searchsorted(below_k + np.cumsum(w[order]), target))
            return float(v[order][min(i, v.size - 1)])
        h, below = sub, below_k
