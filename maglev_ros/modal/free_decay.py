"""Modal identification from a vehicle pass: select the free decay after the vehicle has left the
span and identify from it (no rclpy).

While the vehicle is on the span the response is forced and non-stationary (moving loads, the
vehicle-guideway coupling shifts the poles), so it is not used. After the last magnet has left
the span the guideway rings down freely: ``y_k = C A^k x_0`` (+ weak ambient response + noise).
SSI-cov is applied to this window unchanged: with the fixed-range lag sums of
:func:`maglev_ros.modal.ssi_cov.output_covariances`, ``R_j = C A^j (sum_k x_k x_k^T) C^T``
keeps the exact shift structure of an impulse response, so SSI-cov on a free decay is
ERA-like (Juang & Pappa's ERA applied to the decay's correlations, i.e. the NExT/ERA idea) and
needs no stationarity. Uncertainty is the cluster spread (blocks of a decay are not
exchangeable).

Window selection, in order of preference:

1. ``position``: exit time = first stream time at which the vehicle's rearmost magnet
   (reference position + min magnet offset) is beyond the span end; start = exit + ``margin_s``.
2. ``envelope`` (no position channel): the multi-channel RMS envelope (window
   ``envelope_window_s``); the forced part is taken to end at the last time the envelope is
   above ``frac`` of its maximum; start = that + ``margin_s``. This is a heuristic: it assumes the
   ring-down starts from a level comparable to the pass' peak.

The window runs to the end of the record by default: the ambient response that follows the ring-
down has the same poles and, with the fixed-range covariances, only adds (unbiased) information;
cutting at the noise floor was tried on simulated passes and gave larger errors. With
``noise_factor > 0`` the window instead ends where the smoothed envelope has fallen to
``noise_factor`` x the floor (median envelope over the last 10 % of the record).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.modal.ssi_cov import ModalResult, SSICov


@dataclass(frozen=True)
class FreeDecayWindow:
    start_index: int
    stop_index: int
    start_s: float          # relative to the first sample of the data
    stop_s: float
    method: str             # "position" | "envelope"

    def to_dict(self) -> dict:
        return {"start_index": self.start_index, "stop_index": self.stop_index,
                "start_s": self.start_s, "stop_s": self.stop_s, "method": self.method}


def rms_envelope(data: np.ndarray, fs_hz: float, window_s: float = 0.1) -> np.ndarray:
    """Moving RMS over all channels (each channel scaled by its overall std)."""
    x = np.asarray(data, dtype=float)
    x = x - np.median(x, axis=0)
    sd = x.std(axis=0)
    x = x / np.where(sd > 0, sd, 1.0)
    p = np.mean(x * x, axis=1)
    w = max(int(round(window_s * fs_hz)), 1)
    c = np.concatenate([[0.0], np.cumsum(p)])
    lo = np.clip(np.arange(p.size) - w // 2, 0, p.size)
    hi = np.clip(np.arange(p.size) + (w - w // 2), 0, p.size)
    return np.sqrt((c[hi] - c[lo]) / np.maximum(hi - lo, 1))


def exit_time_s(position_m, position_time_s, span_end_m: float, rear_offset_m: float = 0.0) -> float:
    """First time the rearmost magnet (reference position + ``rear_offset_m``) is beyond
    ``span_end_m``, interpolated between position samples."""
    pos = np.asarray(position_m, dtype=float) + rear_offset_m
    past = np.flatnonzero(pos > span_end_m)
    if past.size == 0:
        raise UserError(f"position: the vehicle never leaves the span (end {span_end_m} m)")
    k = past[0]
    if k == 0:
        return position_time_s[0]
    p0, p1 = pos[k - 1], pos[k]
    a = (span_end_m - p0) / (p1 - p0) if p1 != p0 else 1.0
    return position_time_s[k - 1] + a * (position_time_s[k] - position_time_s[k - 1])


def position_window_streamed(time_chunks, fs_hz: float, t_exit_s: float, margin_s: float = 0.1,
                             min_length_s: float = 0.5) -> FreeDecayWindow:
    """:func:`select_free_decay`'s position window (``noise_factor`` 0, the default) from the
    record's sample times given in chunks (seconds after the first sample), without holding
    them: the start is the first sample at or after ``t_exit_s + margin_s``."""
    thr = t_exit_s + margin_s
    n = start = 0
    min_n = int(round(min_length_s * fs_hz))
    marks = {}                         # index -> time, for the window's two ends
    last = None
    for t in time_chunks:
        t = np.asarray(t, dtype=float)
        if not t.size:
            continue
        start += int(np.searchsorted(t, thr))
        for i in (start, start + min_n - 1):
            if n <= i < n + t.size:
                marks[i] = float(t[i - n])
        n += t.size
        last = float(t[-1])
    if start >= n - 1:
        raise UserError("data: no samples after the vehicle left the span; expected a record that "
                        "continues after the pass")
    stop = n
    if (stop - start) / fs_hz < min_length_s:
        stop = min(n, start + min_n)
    if stop - start < 8:
        raise UserError("data: free decay after the pass is too short to identify from")
    t_stop = last if stop == n else marks[stop - 1]
    return FreeDecayWindow(start, stop, marks[start], t_stop, "position")


def select_free_decay(data: np.ndarray, fs_hz: float, *, time_s: np.ndarray | None = None,
                      position_m: np.ndarray | None = None,
                      position_time_s: np.ndarray | None = None,
                      span_end_m: float | None = None, rear_offset_m: float = 0.0,
                      margin_s: float = 0.1, envelope_window_s: float = 0.1, frac: float = 0.3,
                      noise_factor: float = 0.0, min_length_s: float = 0.5) -> FreeDecayWindow:
    """Pick the free-decay window of a pass recording (see the module docstring)."""
    x = np.asarray(data, dtype=float)
    if x.ndim != 2 or x.shape[0] < 4:
        raise UserError(f"data: expected a 2-D array (n_samples, n_channels), got shape {x.shape}")
    n = x.shape[0]
    t = np.arange(n) / fs_hz if time_s is None else np.asarray(time_s, dtype=float)
    env = rms_envelope(x, fs_hz, envelope_window_s)
    if position_m is not None:
        if span_end_m is None or position_time_s is None:
            raise UserError("position: expected span_end_m and position_time_s with position_m")
        t_exit = exit_time_s(position_m, position_time_s, span_end_m, rear_offset_m)
        start = int(np.searchsorted(t, t_exit + margin_s))
        method = "position"
    else:
        peak = env.max()
        above = np.flatnonzero(env >= frac * peak)
        start = int(above[-1] + round(margin_s * fs_hz)) + 1
        method = "envelope"
    if start >= n - 1:
        raise UserError("data: no samples after the vehicle left the span; expected a record that "
                        "continues after the pass")
    env_s = rms_envelope(x, fs_hz, max(envelope_window_s, 0.25))   # smoother: beats of close modes
    floor = np.median(env_s[int(0.9 * n):])
    after = env_s[start:]
    low = np.flatnonzero(after <= noise_factor * floor)
    stop = n
    if (noise_factor > 0 and low.size and floor > 0
            and after[0] > 3 * noise_factor * floor):
        stop = int(start + low[0])
    if (stop - start) / fs_hz < min_length_s:
        stop = min(n, start + int(round(min_length_s * fs_hz)))
    if stop - start < 8:
        raise UserError("data: free decay after the pass is too short to identify from")
    return FreeDecayWindow(start, stop, float(t[start] - t[0]), float(t[stop - 1] - t[0]), method)


def identify_free_decay(data: np.ndarray, fs_hz: float, window: FreeDecayWindow,
                        ssi: SSICov | None = None, channels=None) -> ModalResult:
    """SSI-cov on the free-decay window (uncertainty from the cluster spread)."""
    est = ssi or SSICov(block_rows=40, orders=range(2, 61, 2))
    if est.uncertainty != "cluster":
        est = SSICov(block_rows=est.block_rows, orders=est.orders, decimate_to_hz=est.decimate_to_hz,
                     freq_range_hz=est.freq_range_hz, ref_channels=est.ref_channels,
                     criteria=est.criteria, uncertainty="cluster", n_blocks=1,
                     spectrum=est.spectrum, nperseg=est.nperseg, blas_threads=est.blas_threads,
                     lag_shift=est.lag_shift)
    seg = np.asarray(data, dtype=float)[window.start_index:window.stop_index]
    return est.fit(seg, fs_hz, channels)
