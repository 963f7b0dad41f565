"""Online mismatch detection on the twin's residual stream (core of the ``discrepancy`` node).

``OnlineDetector.add_block(group, block)`` takes residual SensorBlocks (measured minus twin) as
they arrive; ``add_position(t_s, x_m)`` the vehicle position. Every ``hop_s`` each channel's last
``frame_s`` of residual is cut into the bands of :mod:`.features`; the noise floor of each band is
the running 20th percentile of that band's power over the last ``history_frames`` frames (minimum
statistics: a mismatch that lasts less than most of the history does not raise its own floor).
A band is flagged when its power exceeds max(``threshold``, chi2 ratio) x floor in ``min_frames`` consecutive
frames (chi2 ratio = 1e-5 upper quantile / 20 % quantile of a chi-square band power with the band's
degrees of freedom, so low-frequency bands with few periodogram bins are not called on noise); when the flagged run ends (or lasts ``max_s``) one ``MismatchEvent`` is emitted with the
channels, time, place of the vehicle, band and severity (mean power / floor). Naming the missing
physics needs the batch fit of several passes (``maglev-ros diagnose``); the event says so.
"""
from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .features import BAND_EDGES_HZ, FrameGrid, band_powers


@dataclass(frozen=True)
class MismatchEvent:
    channels: tuple[str, ...]
    t0_s: float
    t1_s: float
    position_start_m: float
    position_end_m: float
    f0_hz: float
    f1_hz: float
    severity: float
    effect: str = ""
    category: str = ""
    explanation: str = ""
    detail: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["channels"] = list(self.channels)
        return d

    @property
    def detail_json(self) -> str:
        return json.dumps(self.detail)


class OnlineDetector:
    def __init__(self, frame_s: float = 0.5, hop_s: float = 0.25, threshold: float = 10.0,
                 min_frames: int = 2, history_frames: int = 40, max_s: float = 5.0,
                 edges_hz=BAND_EDGES_HZ):
        self.frame_s, self.hop_s = float(frame_s), float(hop_s)
        self.threshold, self.min_frames = float(threshold), int(min_frames)
        self.history_frames, self.max_s = int(history_frames), float(max_s)
        self.edges = np.asarray(edges_hz, float)
        self._buf: dict[str, deque] = {}        # channel -> deque of (t, x)
        self._rate: dict[str, float] = {}
        self._hist: dict[str, deque] = {}       # channel -> band powers of past frames
        self._next_t: dict[str, float] = {}
        self._runs: dict[tuple[str, int], dict] = {}
        self._pos_t: deque = deque(maxlen=20000)
        self._pos_x: deque = deque(maxlen=20000)
        self.events: list[MismatchEvent] = []
        self._thr_cache: dict[float, np.ndarray] = {}

    def _thresholds(self, fs: float) -> np.ndarray:
        thr = self._thr_cache.get(fs)
        if thr is None:
            from scipy.stats import chi2
            f = np.fft.rfftfreq(int(round(self.frame_s * fs)), 1.0 / fs)
            nbins = np.array([max(1, int(np.sum((f >= a) & (f < b)))) for a, b in zip(self.edges[:-1], self.edges[1:])])
            dof = 2.0 * nbins
            thr = self._thr_cache[fs] = np.maximum(self.threshold, chi2.ppf(1 - 1e-5, dof) / chi2.ppf(0.2, dof))
        return thr

    def add_position(self, t_s, x_m) -> None:
        for t, x in zip(np.atleast_1d(t_s), np.atleast_1d(x_m)):
            self._pos_t.append(float(t)); self._pos_x.append(float(x))

    def _pos(self, t: float) -> float:
        if not self._pos_t:
            return float("nan")
        return float(np.interp(t, np.asarray(self._pos_t), np.asarray(self._pos_x)))

    def add_block(self, block) -> list[MismatchEvent]:
        """Feed one residual Block (core ``sensor_block.Block``); returns events completed now."""
        t = block.times_s()
        out = []
        for j, ch in enumerate(block.channels):
            buf = self._buf.setdefault(ch, deque())
            for tt, xx in zip(t, block.data[:, j].astype(float)):
                buf.append((tt, xx))
            self._rate[ch] = float(block.sample_rate_hz)
            n_keep = int(self.frame_s * block.sample_rate_hz) + 2
            if ch not in self._next_t:
                self._next_t[ch] = buf[0][0] + self.frame_s
            while buf and buf[-1][0] >= self._next_t[ch]:
                tend = self._next_t[ch]
                out += self._frame(ch, tend)
                self._next_t[ch] = tend + self.hop_s
            while len(buf) > n_keep:
                buf.popleft()
        self.events += out
        return out

    def _frame(self, ch: str, tend: float) -> list[MismatchEvent]:
        buf = self._buf[ch]
        arr = np.array([v for v in buf if tend - self.frame_s <= v[0] <= tend])
        if arr.shape[0] < 8:
            return []
        grid = FrameGrid(np.array([tend - self.frame_s / 2]), self.frame_s, self.edges)
        fs = self._rate[ch]
        p = band_powers(arr[:, 0], arr[:, 1] - np.mean(arr[:, 1]) * 0, fs, grid)[0]
        hist = self._hist.setdefault(ch, deque(maxlen=self.history_frames))
        usable = self.edges[1:] <= 0.7 * fs / 2
        events = []
        if len(hist) >= 4:
            floor = np.percentile(np.array(hist), 20, axis=0) + 1e-300
            ratio = p / floor
            thr = self._thresholds(fs)
            for b in np.flatnonzero(usable):
                key = (ch, int(b))
                run = self._runs.get(key)
                if ratio[b] > thr[b]:
                    if run is None:
                        run = self._runs[key] = {"t0": tend - self.frame_s, "n": 0, "sev": []}
                    run["n"] += 1
                    run["sev"].append(float(ratio[b]))
                    run["t1"] = tend
                    if run["t1"] - run["t0"] >= self.max_s:
                        events += self._close(key)
                elif run is not None:
                    events += self._close(key)
        hist.append(p)
        return self._merge(events)

    def _close(self, key) -> list[MismatchEvent]:
        run = self._runs.pop(key)
        if run["n"] < self.min_frames:
            return []
        ch, b = key
        t0, t1 = run["t0"], run["t1"]
        x0, x1 = self._pos(t0), self._pos(t1)
        return [MismatchEvent((ch,), t0, t1, min(x0, x1), max(x0, x1), float(self.edges[b]), float(self.edges[b + 1]),
                              float(np.mean(run["sev"])), explanation=(
                                  f"{ch}: residual {np.mean(run['sev']):.0f}x its noise floor in "
                                  f"{self.edges[b]:.0f}-{self.edges[b + 1]:.0f} Hz; run `maglev-ros diagnose` on "
                                  f"the recordings to name the missing physics"),
                              detail={"frames": run["n"], "band_index": b})]

    @staticmethod
    def _merge(events: list[MismatchEvent]) -> list[MismatchEvent]:
        """Merge events of one channel in adjacent bands that end together."""
        if len(events) < 2:
            return events
        events = sorted(events, key=lambda e: (e.channels, e.f0_hz))
        out = [events[0]]
        for e in events[1:]:
            o = out[-1]
            if e.channels == o.channels and abs(e.f0_hz - o.f1_hz) < 1e-9:
                out[-1] = MismatchEvent(o.channels, min(o.t0_s, e.t0_s), max(o.t1_s, e.t1_s), o.position_start_m,
                                        o.position_end_m, o.f0_hz, e.f1_hz, max(o.severity, e.severity),
                                        explanation=o.explanation, detail=o.detail)
            else:
                out.append(e)
        return out
