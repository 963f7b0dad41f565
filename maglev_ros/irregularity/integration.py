"""Band-limited double integration of accelerations that does not drift, with data checks.

The inertial reference method needs the magnet's vertical displacement z_m(t) from its upward
acceleration a(t). Plain double integration turns any accelerometer bias into a parabola and any
flat-lined or missing stretch into a ramp, so this module

1. checks each channel for non-finite samples, flat-lined stretches (stuck value, zero blocks) and
   breaks in the time axis, and reports them as :class:`DataWarning` (structured, JSON-ready);
2. splits the record at those dropouts and integrates every clean segment on its own (the result is
   NaN over the dropout plus a margin, never a ramp across it);
3. estimates the accelerometer bias of each segment from the trend of the integrated velocity
   (a real magnet cannot keep accelerating one way: its vertical velocity is bounded), reports it
   when it is significant, and removes it before integrating;
4. integrates in the frequency domain, ``Z(f) = -A(f) / (2 pi f)^2 * H(f)``, with the smooth
   zero-phase high-pass ``H(f) = (f/f_c)^(2n) / (1 + (f/f_c)^(2n))`` (the magnitude of an order-n
   Butterworth run forward and backward; default n = 4), so the corner ``f_c`` is exact and stated;
   edges are tapered (half-cosine, ``0.5/f_c`` long) and zero-padded (``2/f_c``), and the first and
   last ``edge_s`` (default ``1/f_c``) of every segment are returned as NaN because the taper and the
   filter's transient make them unreliable.

Why by hand: scipy has no drift-free double integrator; frequency-domain integration with an
explicit high-pass is a few lines of numpy FFT and lets the same H(f) be applied to other signals
(:func:`highpass_fd`) so the gap and the integrated acceleration share one band exactly.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from functools import lru_cache

import numpy as np
from scipy import fft as sfft

__all__ = [
    "DataWarning", "IntegrationResult", "highpass_gain", "highpass_fd", "double_integrate",
    "detect_dropouts", "estimate_bias", "valid_segments", "DEFAULT_FILTER_ORDER",
]

DEFAULT_FILTER_ORDER = 4


@dataclass(frozen=True)
class DataWarning:
    """One problem found in the data; ``kind`` is a stable machine-readable tag.

    kinds: ``nonfinite`` (NaN/inf samples), ``flatline`` (stuck value or zero block),
    ``time_gap`` (missing samples in the time axis), ``accel_bias`` (significant constant offset,
    removed before integration), ``short_segment`` (clean stretch too short to integrate),
    ``slow_section`` (vehicle slower than the band speed; positions dropped),
    ``band`` (requested band cannot be honoured), ``edge`` (edge margins set to NaN).
    """
    kind: str
    channel: str
    message: str
    start_s: float | None = None
    end_s: float | None = None
    value: float | None = None

    def to_dict(self) -> dict:
        def f(v):
            return None if v is None or not math.isfinite(v) else float(v)
        return {"kind": self.kind, "channel": self.channel, "message": self.message,
                "start_s": f(self.start_s), "end_s": f(self.end_s), "value": f(self.value)}


@dataclass(frozen=True, eq=False)
class IntegrationResult:
    """Displacement from :func:`double_integrate`; NaN where it is not trustworthy."""
    time_s: np.ndarray
    displacement_m: np.ndarray
    valid: np.ndarray                     # bool, same length
    highpass_hz: float
    filter_order: int
    edge_s: float
    bias_mps2: tuple[float, ...]          # removed offset per integrated segment
    warnings: tuple[DataWarning, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict:
        return {"highpass_hz": self.highpass_hz, "filter_order": self.filter_order,
                "edge_s": self.edge_s, "valid_fraction": float(np.mean(self.valid)),
                "bias_mps2": [float(b) for b in self.bias_mps2],
                "warnings": [w.to_dict() for w in self.warnings]}


def highpass_gain(freq_hz: np.ndarray, highpass_hz: float,
                  order: int = DEFAULT_FILTER_ORDER) -> np.ndarray:
    """Zero-phase high-pass gain (f/fc)^(2n) / (1 + (f/fc)^(2n)); 0.5 at the corner."""
    r = np.abs(np.asarray(freq_hz, dtype=float)) / float(highpass_hz)
    with np.errstate(over="ignore"):
        p = r ** (2 * order)
        g = p / (1.0 + p)
    return np.where(np.isinf(p), 1.0, g)


def _pad_len(n: int, fs_hz: float, highpass_hz: float) -> tuple[int, int]:
    npad = int(math.ceil(2.0 / highpass_hz * fs_hz))
    return npad, sfft.next_fast_len(n + 2 * npad, real=True)


def _taper(n: int, fs_hz: float, highpass_hz: float) -> np.ndarray:
    w = np.ones(n)
    nt = min(int(round(0.5 / highpass_hz * fs_hz)), n // 2)
    if nt > 1:
        ramp = 0.5 * (1.0 - np.cos(np.pi * np.arange(nt) / nt))
        w[:nt] = ramp
        w[n - nt:] = ramp[::-1]
    return w


FD_GAIN_CACHE_MAX_N = 2 ** 19     # a live window's FFT length; a whole recording's is not kept


@lru_cache(maxsize=16)
def _fd_gain(nfft: int, fs_hz: float, highpass_hz: float, order: int, integrate_twice: bool) -> np.ndarray:
    """The frequency response of :func:`_apply_fd` (read-only, cached: a stream's windows repeat a
    few FFT lengths, and the live profiles recompute them every second)."""
    f = sfft.rfftfreq(nfft, 1.0 / fs_hz)
    h = highpass_gain(f, highpass_hz, order)
    if integrate_twice:
        w2 = (2.0 * np.pi * f) ** 2
        w2[0] = np.inf
        h = -h / w2
    h.flags.writeable = False
    return h


def _apply_fd(x: np.ndarray, fs_hz: float, highpass_hz: float, order: int,
              integrate_twice: bool, mean: float | None = None) -> np.ndarray:
    n = x.size
    npad, nfft = _pad_len(n, fs_hz, highpass_hz)
    buf = np.zeros(nfft)
    buf[npad:npad + n] = (x - (np.mean(x) if mean is None else mean)) * _taper(n, fs_hz, highpass_hz)
    spec = sfft.rfft(buf)
    key = (nfft, float(fs_hz), float(highpass_hz), int(order), bool(integrate_twice))
    h = _fd_gain(*key) if nfft <= FD_GAIN_CACHE_MAX_N else _fd_gain.__wrapped__(*key)
    out = sfft.irfft(spec * h, nfft)
    return out[npad:npad + n]


def highpass_fd(x: np.ndarray, fs_hz: float, highpass_hz: float,
                order: int = DEFAULT_FILTER_ORDER) -> np.ndarray:
    """Apply the same zero-phase high-pass (and taper/padding) as :func:`double_integrate`."""
    return _apply_fd(np.asarray(x, dtype=float), fs_hz, highpass_hz, order, False)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index runs [i0, i1) where mask is True."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def detect_dropouts(time_s: np.ndarray, x: np.ndarray, fs_hz: float, channel: str,
                    flat_min_s: float = 0.02, flat_min_samples: int = 8,
                    rel_tol: float = 0.0) -> tuple[np.ndarray, list[DataWarning]]:
    """Return (bad mask, warnings) for one channel.

    Bad: non-finite samples; runs of identical consecutive values (|diff| <= rel_tol * robust
    scale) lasting at least ``max(flat_min_samples, flat_min_s * fs)`` samples (a stuck sensor or a
    zero block: real accelerometer and gap signals always carry noise); a break in ``time_s``
    larger than 1.5 sample periods marks the samples on both sides.
    """
    x = np.asarray(x, dtype=float)
    t = np.asarray(time_s, dtype=float)
    n = x.size
    bad = np.zeros(n, bool)
    warns: list[DataWarning] = []
    nonfin = ~np.isfinite(x)
    for i0, i1 in _runs(nonfin):
        warns.append(DataWarning("nonfinite", channel,
                                 f"{channel}: {i1 - i0} non-finite samples", t[i0], t[i1 - 1]))
    bad |= nonfin
    if n > 1:
        xf = np.where(nonfin, 0.0, x)
        scale = np.nanmedian(np.abs(np.diff(xf))) if rel_tol > 0 else 0.0
        same = np.abs(np.diff(xf)) <= rel_tol * scale
        same &= ~nonfin[1:] & ~nonfin[:-1]
        nmin = max(int(flat_min_samples), int(math.ceil(flat_min_s * fs_hz)))
        for i0, i1 in _runs(same):
            # diff run [i0, i1) means samples i0 .. i1 are equal
            if i1 - i0 + 1 >= nmin:
                bad[i0:i1 + 1] = True
                warns.append(DataWarning(
                    "flatline", channel,
                    f"{channel}: value stuck at {xf[i0]:.6g} for {i1 - i0 + 1} samples",
                    t[i0], t[i1], float(xf[i0])))
        dt = np.diff(t)
        for i in np.flatnonzero(dt > 1.5 / fs_hz):
            bad[i] = bad[i + 1] = True
            warns.append(DataWarning("time_gap", channel,
                                     f"{channel}: {dt[i]:.4g} s without samples", t[i], t[i + 1]))
    return bad, warns


def estimate_bias(a: np.ndarray, fs_hz: float) -> tuple[float, float]:
    """Bias of an acceleration record and its standard error, (bias_mps2, se_mps2).

    The least-squares slope of the integrated velocity v(t) = int a dt is the bias estimate (a
    parabola-weighted mean of a, insensitive to the velocity at the two ends). The magnet's true
    vertical velocity is a bounded, zero-mean process, so its contribution to the slope is
    ``sqrt(12) * std(resid) / T / sqrt(N_eff)`` with N_eff the number of independent excursions of
    the residual (half its zero crossings, at least 1): that is the standard error.
    """
    a = np.asarray(a, dtype=float)
    n = a.size
    if n < 4:
        return float(np.mean(a)) if n else 0.0, math.inf
    dt = 1.0 / fs_hz
    v = np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * dt)])
    t = np.arange(n) * dt
    tc = t - t.mean()
    slope = float(np.dot(tc, v - v.mean()) / np.dot(tc, tc))
    resid = v - v.mean() - slope * tc
    T = n * dt
    zc = int(np.count_nonzero(np.diff(np.signbit(resid))))
    neff = max(1.0, zc / 2.0)
    se = math.sqrt(12.0) * float(np.std(resid)) / T / math.sqrt(neff)
    return slope, se


def valid_segments(bad: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """Half-open runs of good samples at least ``min_len`` long."""
    return [(i0, i1) for i0, i1 in _runs(~np.asarray(bad, bool)) if i1 - i0 >= min_len]


def double_integrate(time_s: np.ndarray, accel_mps2: np.ndarray, fs_hz: float,
                     highpass_hz: float, order: int = DEFAULT_FILTER_ORDER,
                     edge_s: float | None = None, bad: np.ndarray | None = None,
                     channel: str = "accel", bias_sigma: float = 5.0,
                     bias_floor_mps2: float = 2e-3,
                     check_dropouts: bool = True,
                     plus_highpassed: np.ndarray | None = None,
                     segment_means=None, report_bias: bool = True) -> IntegrationResult:
    """Displacement [m] from acceleration [m/s^2], band-limited above ``highpass_hz``.

    ``bad`` marks extra samples to exclude (e.g. a dropout in a companion channel). Segments
    between dropouts shorter than ``2 * edge_s + 2 / highpass_hz`` are skipped (reported).
    A bias is reported when ``|b| > bias_sigma * se`` and ``|b| > bias_floor_mps2``; it is always
    removed (the segment mean) before integration.

    ``plus_highpassed`` (same length) is high-passed with the same H(f), taper and segments and
    added to the displacement; the inertial method passes the gap change here so that
    ``z_m + gap - g0`` carries one band exactly. Non-finite samples in it count as bad.

    ``segment_means(i0, i1)``: (accel mean, plus mean) to remove from the clean segment
    ``i0 .. i1-1`` instead of its own means, or None: a caller integrating a piece of a longer
    segment gives the whole segment's (the mean's tapered step at the segment's true ends
    reaches ~4/f_c into it).

    ``report_bias`` False: no bias warnings (the bias test, not the integration, is skipped: a caller
    that discards the warnings, e.g. a live profile's uncommitted tail, saves a third of its time).
    """
    if not (highpass_hz > 0):
        raise ValueError(f"highpass_hz must be > 0, got {highpass_hz}")
    t = np.asarray(time_s, dtype=float)
    a = np.asarray(accel_mps2, dtype=float)
    edge = (1.0 / highpass_hz) if edge_s is None else float(edge_s)
    mask = np.zeros(a.size, bool) if bad is None else np.asarray(bad, bool).copy()
    warns: list[DataWarning] = []
    if check_dropouts:
        m2, w2 = detect_dropouts(t, a, fs_hz, channel)
        mask |= m2
        warns += w2
    if plus_highpassed is not None:
        plus = np.asarray(plus_highpassed, dtype=float)
        mask |= ~np.isfinite(plus)
    out = np.full(a.size, np.nan)
    nedge = int(round(edge * fs_hz))
    min_len = 2 * nedge + int(math.ceil(2.0 / highpass_hz * fs_hz))
    biases = []
    for i0, i1 in _runs(~mask):
        if i1 - i0 < min_len:
            warns.append(DataWarning("short_segment", channel,
                                     f"{channel}: clean stretch of {(i1 - i0) / fs_hz:.3g} s is shorter "
                                     f"than {min_len / fs_hz:.3g} s needed at f_c={highpass_hz:g} Hz; "
                                     f"left out", t[i0], t[i1 - 1]))
            continue
        seg = a[i0:i1]
        b, se = estimate_bias(seg, fs_hz) if report_bias else (0.0, math.inf)
        biases.append(float(np.mean(seg)))
        if abs(b) > bias_sigma * se and abs(b) > bias_floor_mps2:
            warns.append(DataWarning(
                "accel_bias", channel,
                f"{channel}: constant offset {b:+.4g} m/s^2 (standard error {se:.2g}) removed before "
                f"integration", t[i0], t[i1 - 1], b))
        means = None if segment_means is None else segment_means(i0, i1)
        z = _apply_fd(seg, fs_hz, highpass_hz, order, True, None if means is None else means[0])
        if plus_highpassed is not None:
            z = z + _apply_fd(plus[i0:i1], fs_hz, highpass_hz, order, False,
                              None if means is None else means[1])
        z[:nedge] = np.nan
        z[z.size - nedge:] = np.nan
        out[i0:i1] = z
    return IntegrationResult(time_s=t, displacement_m=out, valid=np.isfinite(out),
                             highpass_hz=float(highpass_hz), filter_order=int(order),
                             edge_s=edge, bias_mps2=tuple(biases), warnings=tuple(warns))
