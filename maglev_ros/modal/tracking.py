"""Online modal tracking over a sensor stream (no rclpy).

:class:`StreamingSSI` turns a stream of blocks into a :class:`ModalResult` every ``update_s`` of
stream time, identified from the last ``window_s`` (or from all of the stream once
``min_window_s`` has come, until it reaches ``window_s``). Per-update work is kept low:

* decimation by a stateful polyphase FIR (only the kept output samples are computed; linear
  phase, so no extra poles enter the data, unlike an IIR anti-alias filter);
* the window covariances are updated recursively: each chunk's lag products (pairs whose later
  sample lies in the chunk) are computed once and kept in a deque; the window sum is the sum over
  the deque (exact, no add/subtract drift). Groups of chunks give the block covariances for the
  uncertainty at no extra cost;
* the SVD is warm-started from the previous right singular subspace (two block subspace
  iterations); an exact SVD is redone every ``exact_svd_every`` updates.

:class:`ModeTracker` matches the modes of successive results by frequency and MAC (Hungarian
assignment on ``|df|/f + (1 - MAC)``), keeps stable ids (M1, M2, ...), reports ``new`` and
``lost`` (after ``max_misses`` consecutive misses) events and a running (exponentially weighted)
mean/std of each mode's frequency and damping.

Hand-written: no maintained library does streaming SSI with recursive covariances.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.signal import firwin

from maglev_ros.errors import UserError
from maglev_ros.modal.ssi_cov import ModalResult, SSICov, blas_threads, decimation_factor
from maglev_ros.modal.stabilization import mac


class StreamingDecimator:
    """Stateful anti-aliased integer decimator (linear-phase FIR, polyphase evaluation)."""

    def __init__(self, factor: int, n_channels: int, taps_per_factor: int = 16):
        self.q = int(factor)
        self.n_channels = int(n_channels)
        if self.q > 1:
            ntaps = taps_per_factor * self.q + 1
            self.h = firwin(ntaps, 0.8 / self.q)[::-1].copy()   # reversed for dot with windows
        else:
            self.h = np.ones(1)
        self._tail = np.zeros((len(self.h) - 1, self.n_channels))
        self._buf_start = -(len(self.h) - 1)     # global input index of the tail's first row
        self._next_out = 0                       # global input index of the next output sample

    def push(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if self.q == 1:
            return x
        if x.shape[0] == 0:
            return np.zeros((0, self.n_channels))
        L = len(self.h)
        buf = np.concatenate([self._tail, x], axis=0)
        win = np.lib.stride_tricks.sliding_window_view(buf, L, axis=0)  # (n-L+1, c, L)
        first = self._next_out - self._buf_start - (L - 1)                # window index
        sel = win[first::self.q]
        out = sel @ self.h
        self._next_out += self.q * sel.shape[0]
        self._buf_start += buf.shape[0] - (L - 1)
        self._tail = buf[-(L - 1):]
        return out


class StreamingSSI:
    """Sliding-window SSI-cov over a stream: ``push(block)`` returns the results produced.

    ``ssi`` holds the identification settings (its ``decimate_to_hz`` sets the decimation);
    ``window_s`` window length, ``update_s`` stream time between results; ``min_window_s``
    (default ``window_s``): the first result once this much has come, the window then grows
    with the stream up to ``window_s`` and slides from there.
    """

    def __init__(self, ssi: SSICov, fs_hz: float, channels, window_s: float = 120.0,
                 update_s: float = 2.0, exact_svd_every: int = 30, min_window_s: float | None = None):
        if fs_hz <= 0:
            raise UserError(f"fs_hz: expected a positive sampling rate, got {fs_hz!r}")
        if update_s <= 0 or window_s < update_s:
            raise UserError(f"window_s/update_s: expected 0 < update_s <= window_s, got "
                            f"{window_s!r}/{update_s!r}")
        self.ssi = ssi
        self.channels = tuple(str(c) for c in channels)
        self.fs_in_hz = float(fs_hz)
        q = decimation_factor(fs_hz, ssi.decimate_to_hz)
        self.fs_hz = self.fs_in_hz / q
        self.dec = StreamingDecimator(q, len(self.channels))
        self.refs = ssi._ref_indices(self.channels)
        self.max_lag = ssi.max_lag
        self.q = q
        # chunks end every update_s of INPUT samples (decimated: ceil(j C / q)), so streams of
        # several bands at different decimations complete their chunks on the same input sample
        self.chunk_in = max(int(round(update_s * self.fs_in_hz)), 1)
        self.n_chunks = max(int(round(window_s / update_s)), 1)
        self.min_chunks = min(max(int(round((min_window_s or window_s) / update_s)), 1), self.n_chunks)
        self._chunks_done = 0
        self._taken = 0                                    # decimated samples put into chunks
        self.window_s, self.update_s = float(window_s), float(update_s)
        self.exact_svd_every = int(exact_svd_every)
        self._hist = np.zeros((0, len(self.channels)))     # last max_lag decimated samples
        self._pending = np.zeros((0, len(self.channels)))
        self._chunks: deque = deque(maxlen=self.n_chunks)  # (sum (lags, l, r), count)
        self._mean_acc: deque = deque(maxlen=self.n_chunks)
        self._v = None
        self._n_updates = 0
        self.n_samples_in = 0
        self.time_s = 0.0                                   # stream time at the last result

    def push(self, block: np.ndarray) -> list[ModalResult]:
        return [self.identify(w) for w in self.push_windows(block)]

    def push_windows(self, block: np.ndarray) -> list[dict]:
        """The cheap half of :meth:`push`: the block taken in, and the covariances of each window it
        completes (what :meth:`identify` needs; a node identifies them on a worker thread)."""
        block = np.asarray(block, dtype=float)
        if block.ndim != 2 or block.shape[1] != len(self.channels):
            raise UserError(f"block: expected shape (n, {len(self.channels)}), got {block.shape}")
        self.n_samples_in += block.shape[0]
        with blas_threads(self.ssi.blas_threads):
            y = self.dec.push(block)
            self._pending = np.concatenate([self._pending, y], axis=0)
            out = []
            while (self._chunks_done + 1) * self.chunk_in <= self.n_samples_in:
                end_in = (self._chunks_done + 1) * self.chunk_in
                take = -(-end_in // self.q) - self._taken       # the decimator has made them
                chunk = self._pending[:take]
                self._pending = self._pending[take:]
                self._taken += take
                self._chunks_done += 1
                self._add_chunk(chunk)
                if len(self._chunks) >= self.min_chunks:
                    self.time_s = end_in / self.fs_in_hz
                    out.append(self._window())
        return out

    def _add_chunk(self, chunk: np.ndarray) -> None:
        seg = np.concatenate([self._hist, chunk], axis=0)
        h = self._hist.shape[0]
        n = chunk.shape[0]
        acc = np.zeros((self.max_lag + 1, len(self.channels), self.refs.size))
        pairs = np.zeros(self.max_lag + 1)
        for k in range(self.max_lag + 1):
            # products whose later sample lies in the chunk and whose earlier one exists (near
            # the stream's start, or with chunks shorter than the lags, fewer than n)
            lo = max(h, k)
            if lo < h + n:
                acc[k] = seg[lo:h + n].T @ seg[lo - k:h + n - k][:, self.refs]
                pairs[k] = h + n - lo
        self._chunks.append((acc, n, pairs))
        self._mean_acc.append(chunk.sum(axis=0))
        self._hist = seg[-self.max_lag:] if seg.shape[0] >= self.max_lag else seg

    def _window(self) -> dict:
        """The current window's covariances (and its blocks' for the uncertainty)."""
        sums = np.stack([c[0] for c in self._chunks])
        counts = np.array([c[1] for c in self._chunks], dtype=float)
        pairs = np.stack([c[2] for c in self._chunks])             # (chunks, lags)
        n_tot = counts.sum()
        mean = np.sum(self._mean_acc, axis=0) / n_tot
        corr = np.outer(mean, mean[self.refs])
        cov = sums.sum(axis=0) / np.maximum(pairs.sum(axis=0), 1)[:, None, None] - corr[None]
        nb = min(self.ssi.n_blocks, len(self._chunks))
        block_covs = None
        if self.ssi.uncertainty == "blocks" and nb >= 3:
            groups = np.array_split(np.arange(len(self._chunks)), nb)
            block_covs = np.stack([sums[g].sum(axis=0) / np.maximum(pairs[g].sum(axis=0), 1)[:, None, None]
                                   - corr[None] for g in groups])
        return {"cov": cov, "block_covs": block_covs,
                "window_s": len(self._chunks) * self.chunk_in / self.fs_in_hz}

    def identify(self, window: dict) -> ModalResult:
        """SSI of a :meth:`push_windows` window (the long part). Windows are identified in order;
        one left out only changes the warm start of the next SVD."""
        v0 = None if (self._v is None or self._n_updates % self.exact_svd_every == 0) else self._v
        with blas_threads(self.ssi.blas_threads):
            res, self._v = self.ssi.fit_covariances(window["cov"], self.fs_hz, self.channels,
                                                    block_covs=window["block_covs"], v0=v0)
        self._n_updates += 1
        return res


# --------------------------------------------------------------------------------------------
# tracker
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackedMode:
    id: str
    frequency_hz: float
    damping_ratio: float
    mode_shape: dict
    std_frequency_hz: float          # latest window's estimation std
    std_damping_ratio: float
    running_mean_frequency_hz: float  # exponentially weighted over updates
    running_std_frequency_hz: float
    running_mean_damping_ratio: float
    running_std_damping_ratio: float
    n_updates: int
    misses: int
    first_seen_s: float
    last_seen_s: float
    mpc: float = float("nan")          # modal phase collinearity of the latest estimate

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["mode_shape"] = {str(k): float(v) for k, v in self.mode_shape.items()}
        for k, v in d.items():
            if isinstance(v, float) and not np.isfinite(v):
                d[k] = None
        return d


@dataclass(frozen=True)
class TrackEvent:
    kind: str          # "new" | "lost"
    id: str
    frequency_hz: float
    time_s: float

    def to_dict(self) -> dict:
        return {"kind": self.kind, "id": self.id, "frequency_hz": float(self.frequency_hz),
                "time_s": float(self.time_s)}


@dataclass(frozen=True)
class TrackerUpdate:
    time_s: float
    modes: tuple            # TrackedMode, active (matched now or missing < max_misses)
    events: tuple           # TrackEvent

    def to_dict(self) -> dict:
        return {"schema": "maglev-mode-tracks/1", "time_s": float(self.time_s),
                "modes": [m.to_dict() for m in self.modes],
                "events": [e.to_dict() for e in self.events]}

    def by_id(self, mode_id: str) -> TrackedMode | None:
        for m in self.modes:
            if m.id == mode_id:
                return m
        return None


@dataclass
class _Track:
    id: str
    f: float
    z: float
    shape: np.ndarray           # complex or real, for MAC
    shape_dict: dict
    sf: float
    sz: float
    mf: float
    vf: float
    mz: float
    vz: float
    n: int
    misses: int
    first: float
    last: float
    mpc: float = float("nan")


class ModeTracker:
    """Keeps mode identities across successive :class:`ModalResult` objects.

    ``freq_tol`` max relative frequency change between matched updates, ``mac_min`` min MAC,
    ``max_misses`` consecutive updates without a match before a mode is reported lost,
    ``min_confirm`` updates a new candidate must be seen before it gets an id and a "new" event
    (1 = immediately), ``forgetting`` weight of the newest estimate in the running mean/variance.
    """

    def __init__(self, freq_tol: float = 0.03, mac_min: float = 0.8, max_misses: int = 3,
                 forgetting: float = 0.1, min_confirm: int = 2):
        self.freq_tol = float(freq_tol)
        self.mac_min = float(mac_min)
        self.max_misses = int(max_misses)
        self.forgetting = float(forgetting)
        self.min_confirm = int(min_confirm)
        self._tracks: list[_Track] = []
        self._next = 1

    def update(self, result: ModalResult, time_s: float) -> TrackerUpdate:
        modes = list(result.modes)
        shapes = [np.asarray(result.complex_shapes[k]) if k < len(result.complex_shapes)
                  else np.array(list(m.mode_shape.values())) for k, m in enumerate(modes)]
        events = []
        nt, nm = len(self._tracks), len(modes)
        assigned = {}
        if nt and nm:
            cost = np.full((nt, nm), 1e6)
            for a, tr in enumerate(self._tracks):
                for b, m in enumerate(modes):
                    df = abs(m.frequency_hz - tr.f) / tr.f
                    mm = mac(tr.shape, shapes[b]) if tr.shape.size == shapes[b].size else 1.0
                    if df <= self.freq_tol and mm >= self.mac_min:
                        cost[a, b] = df + (1.0 - mm)
            ra, cb = linear_sum_assignment(cost)
            for a, b in zip(ra, cb):
                if cost[a, b] < 1e6:
                    assigned[a] = b
        used = set(assigned.values())
        g = self.forgetting
        keep = []
        for a, tr in enumerate(self._tracks):
            if a in assigned:
                m = modes[assigned[a]]
                tr.f, tr.z = m.frequency_hz, m.damping_ratio
                tr.shape, tr.shape_dict = shapes[assigned[a]], dict(m.mode_shape)
                tr.sf, tr.sz = m.std_frequency_hz, m.std_damping_ratio
                tr.mpc = m.mpc
                if tr.n == 0:
                    tr.mf, tr.mz, tr.vf, tr.vz = tr.f, tr.z, 0.0, 0.0
                else:
                    w = max(g, 1.0 / (tr.n + 1))
                    df, dz = tr.f - tr.mf, tr.z - tr.mz
                    tr.mf += w * df
                    tr.mz += w * dz
                    tr.vf = (1 - w) * (tr.vf + w * df * df)
                    tr.vz = (1 - w) * (tr.vz + w * dz * dz)
                tr.n += 1
                tr.misses = 0
                tr.last = time_s
                if tr.id.startswith("?") and tr.n >= self.min_confirm:
                    tr.id = f"M{self._next}"
                    self._next += 1
                    events.append(TrackEvent("new", tr.id, tr.f, time_s))
                keep.append(tr)
            else:
                tr.misses += 1
                if tr.id.startswith("?"):
                    continue                      # unconfirmed candidate: drop silently
                if tr.misses >= self.max_misses:
                    events.append(TrackEvent("lost", tr.id, tr.f, time_s))
                else:
                    keep.append(tr)
        for b, m in enumerate(modes):
            if b in used:
                continue
            tr = _Track(id="?", f=m.frequency_hz, z=m.damping_ratio, shape=shapes[b],
                        shape_dict=dict(m.mode_shape), sf=m.std_frequency_hz,
                        sz=m.std_damping_ratio, mf=m.frequency_hz, vf=0.0, mz=m.damping_ratio,
                        vz=0.0, n=1, misses=0, first=time_s, last=time_s, mpc=m.mpc)
            if self.min_confirm <= 1:
                tr.id = f"M{self._next}"
                self._next += 1
                events.append(TrackEvent("new", tr.id, tr.f, time_s))
            keep.append(tr)
        keep.sort(key=lambda t: t.f)
        self._tracks = keep
        out = tuple(TrackedMode(
            id=t.id, frequency_hz=t.f, damping_ratio=t.z, mode_shape=t.shape_dict,
            std_frequency_hz=t.sf, std_damping_ratio=t.sz, running_mean_frequency_hz=t.mf,
            running_std_frequency_hz=float(np.sqrt(t.vf)), running_mean_damping_ratio=t.mz,
            running_std_damping_ratio=float(np.sqrt(t.vz)), n_updates=t.n, misses=t.misses,
            first_seen_s=t.first, last_seen_s=t.last, mpc=t.mpc) for t in keep if not t.id.startswith("?"))
        return TrackerUpdate(float(time_s), out, tuple(events))


def min_window_s(fmin_hz: float | None = None) -> float:
    """The shortest record on which the ``modes`` verb's rules look down to ``fmin_hz`` (default:
    their lowest mode, 1 Hz): its longest lag, PERIODS periods of fmin x 2, is LAG_FRACTION of
    the record (40 s for 1 Hz)."""
    from maglev_ros.modal.bands import FMIN_DEFAULT_HZ, LAG_FRACTION, PERIODS
    return 2.0 * PERIODS / (LAG_FRACTION * (fmin_hz or FMIN_DEFAULT_HZ))


@dataclass(frozen=True)
class OnlineModalConfig:
    """Settings of the online identification (the ``modal_id`` node's parameters). None: chosen
    from the stream as the ``modes`` verb chooses them from a recording
    (:func:`maglev_ros.modal.bands.plan_bands` on the shortest window identified, at the
    stream's rate: fmax 0.4 x the rate, bands of at most a decade each decimated for its top
    frequency, block rows of 2 periods of a band's lowest frequency, orders from the Hankel size).
    ``decimate_to_hz`` given: one band at that rate.

    The window: ``window_s`` given, the last ``window_s`` of stream; None, the recording so far,
    from :func:`min_window_s` (the first estimate) up to ``max_window_s`` (the tracking horizon:
    beyond it the window slides, so slow changes are followed and memory stays bounded)."""
    window_s: float | None = None
    max_window_s: float = 300.0
    update_s: float = 2.0
    decimate_to_hz: float | None = None
    block_rows: int | None = None
    max_order: int | None = None
    order_step: int = 4          # every 4th order: half the verb's diagram cost, per 2 s update
    fmin_hz: float | None = None
    fmax_hz: float | None = None
    n_blocks: int | None = None
    freq_tol: float = 0.03
    mac_min: float = 0.8
    max_misses: int = 3
    min_confirm: int = 2

    @property
    def first_window_s(self) -> float:
        """The stream time of the first estimate (the window the settings are planned for)."""
        return float(self.window_s) if self.window_s else min_window_s(self.fmin_hz)

    @property
    def longest_window_s(self) -> float:
        return float(self.window_s) if self.window_s else max(float(self.max_window_s), self.first_window_s)


class OnlineModalID:
    """Blocks of the guideway acceleration stream in, tracked modes out (no ROS).

    ``push(stamp_s, data, channels, fs_hz)`` feeds one block (n, c); it returns the tracker
    updates produced (one per ``update_s`` of stream once the first window has filled). Each band of
    the plan (``plan``, set from the first block's rate) runs its own :class:`StreamingSSI`;
    their chunks end on the same input samples, so each update merges the bands' results of the
    same window (:func:`maglev_ros.modal.bands.merge_band_results`, as the verb merges them). A
    change of channels or rate restarts the identification (reported in ``restarts``);
    :meth:`reset` starts afresh (a new recording).
    """

    def __init__(self, config: OnlineModalConfig = OnlineModalConfig()):
        self.config = config
        self.restarts = 0
        self.reset()

    def reset(self) -> None:
        c = self.config
        self.tracker = ModeTracker(freq_tol=c.freq_tol, mac_min=c.mac_min,
                                   max_misses=c.max_misses, min_confirm=c.min_confirm)
        self.streams: list[StreamingSSI] = []
        self.plan = None
        self.key = None
        self.t0_s = None

    @property
    def window_s(self) -> float:
        """The window of the last estimate [s] (the first window before any)."""
        st = self.streams[0] if self.streams else None
        if st is None or not st._chunks:
            return self.config.first_window_s
        return len(st._chunks) * st.chunk_in / st.fs_in_hz

    def _start(self, channels, fs_hz: float) -> None:
        from maglev_ros.modal.bands import plan_bands
        c = self.config
        n = int(round(c.first_window_s * fs_hz))
        self.plan = plan_bands(fs_hz, n, len(channels), stationary=True, fmin_hz=c.fmin_hz,
                               fmax_hz=c.fmax_hz, block_rows=c.block_rows, max_order=c.max_order,
                               decimate_to_hz=c.decimate_to_hz)
        self.streams = []
        for b in self.plan.bands:
            nb = b.n_blocks if c.n_blocks is None else int(c.n_blocks)
            ssi = SSICov(block_rows=b.block_rows, orders=range(c.order_step, b.max_order + 1, c.order_step),
                         decimate_to_hz=fs_hz / b.decimation if b.decimation > 1 else None,
                         freq_range_hz=b.search_hz, uncertainty="blocks" if nb >= 3 else "cluster",
                         n_blocks=max(nb, 1), spectrum=False)
            self.streams.append(StreamingSSI(ssi, fs_hz, channels, window_s=c.longest_window_s,
                                             update_s=c.update_s, min_window_s=c.first_window_s))
        self.key = (tuple(channels), float(fs_hz))

    def push(self, stamp_s: float, data: np.ndarray, channels, fs_hz: float) -> list[TrackerUpdate]:
        return [self.identify(job) for job in self.push_windows(stamp_s, data, channels, fs_hz)]

    def push_windows(self, stamp_s: float, data: np.ndarray, channels, fs_hz: float) -> list[dict]:
        """The cheap half of :meth:`push`: the block taken in; one job per window it completes (every
        band's covariances, the tracker, the time), for :meth:`identify`, which may run on another
        thread: jobs are identified in order, and one left out is an update that never was."""
        key = (tuple(channels), float(fs_hz))
        if self.key != key:
            if self.key is not None:
                self.restarts += 1
            self._start(channels, fs_hz)
            self.t0_s = float(stamp_s)
        x = np.asarray(data, dtype=float)
        per_band = [st.push_windows(x) for st in self.streams]
        time_s = self.t0_s + self.streams[0].time_s
        # every band completes the same chunks on the same input sample: windows pair up
        return [{"tracker": self.tracker, "plan": self.plan, "time_s": time_s,
                 "window_s": windows[0]["window_s"], "bands": list(zip(self.streams, windows))}
                for windows in zip(*per_band)]

    @staticmethod
    def identify(job: dict) -> TrackerUpdate:
        """The SSI of every band of a :meth:`push_windows` job, merged, and the tracker's update."""
        from maglev_ros.modal.bands import BandResult, merge_band_results
        results = [st.identify(w) for st, w in job["bands"]]
        merged = merge_band_results([BandResult(b, r) for b, r in zip(job["plan"].bands, results)])
        return job["tracker"].update(merged, job["time_s"])
