"""Keep only the part of a reconstructed irregularity that the magnets agree on (coherent Wiener gain).

Every magnet reconstructs the same rail r(x) plus its own error e_k(x) (gap-sensor noise, the
imperfect cancellation of the magnet's own motion between the double-integrated acceleration and
the gap). Over wavenumber k the magnets' mean auto-spectrum is A = R + N and their mean pairwise
co-spectrum (real part of the cross-spectrum) is C = R: the rail is common and in phase, the errors
are not. The average of n magnets carries R + N / n, so the Wiener gain for it is

    G(k) = R / (R + N / n),   R = clip(C, 0, A),   N = A - R.

Why: driven by the raw average, the twin saw a "rail" at 0.2-0.4 m wavelength that the magnets did
not agree on (coherence 0.02-0.3 there, 1.00 at 2.6 m, on a slow simulated pass) and
predicted 10-1000x the measured magnet acceleration at 60-110 Hz; a fixed low-pass would
also cut real short waves of a rough rail, which the magnets do agree on. The gain needs two or more
magnets; with one the profile is returned unchanged. Hand-written: Welch spectra from scipy, the
gain is one line; no library applies a multi-sensor coherence gain to a spatial profile.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from .integration import _runs

__all__ = ["CoherentGain", "coherent_gain", "apply_gain"]


@dataclass(frozen=True, eq=False)
class CoherentGain:
    wavenumber_cpm: np.ndarray     # cycles per metre
    gain: np.ndarray               # Wiener gain for the magnets' mean, 0..1
    n_magnets: int
    n_points: int

    def cut_wavelength_m(self, level: float = 0.5) -> float | None:
        """Longest wavelength below which the gain first falls under ``level`` (None: never)."""
        k = self.wavenumber_cpm
        low = np.flatnonzero((self.gain < level) & (k > 0))
        return float(1.0 / k[low[0]]) if low.size else None

    def to_dict(self) -> dict:
        cut = self.cut_wavelength_m()
        return {"method": "coherent Wiener gain of the magnets' mean (co-spectrum / auto-spectrum)",
                "n_magnets": self.n_magnets, "n_points": self.n_points, "half_gain_wavelength_m": cut}


def coherent_gain(magnet_profiles_m: np.ndarray, spacing_m: float, nperseg: int = 256,
                  smooth_bins: int = 3) -> CoherentGain | None:
    """Gain over wavenumber from the per-magnet profiles (n_magnets, n_points) on one grid (NaN where
    a magnet has none); the longest stretch that every magnet covers is used. None when fewer than
    two magnets or too short a common stretch (< 4 segments)."""
    P = np.asarray(magnet_profiles_m, float)
    if P.ndim != 2 or P.shape[0] < 2:
        return None
    runs = _runs(np.all(np.isfinite(P), axis=0))
    i0, i1 = max(runs, key=lambda r: r[1] - r[0]) if runs else (0, 0)
    seg = P[:, i0:i1]
    n = seg.shape[1]
    nps = int(min(nperseg, n // 4))
    if nps < 16:
        return None
    fs = 1.0 / spacing_m
    autos, k = [], None
    for p in seg:
        k, a = signal.welch(p, fs=fs, nperseg=nps)
        autos.append(a)
    co = [signal.csd(seg[i], seg[j], fs=fs, nperseg=nps)[1].real
          for i in range(len(seg)) for j in range(i + 1, len(seg))]
    A = np.mean(autos, axis=0)
    R = np.clip(np.mean(co, axis=0), 0.0, A)
    m = len(seg)
    with np.errstate(invalid="ignore", divide="ignore"):
        G = np.where(A > 0, R / (R + (A - R) / m), 0.0)
    if smooth_bins > 1:
        G = np.convolve(np.pad(G, smooth_bins // 2, mode="edge"), np.ones(smooth_bins) / smooth_bins, "valid")
    G[0] = 1.0
    return CoherentGain(k, np.clip(G, 0.0, 1.0), m, n)


def apply_gain(profile_m: np.ndarray, spacing_m: float, g: CoherentGain) -> np.ndarray:
    """Zero-phase filter of a finite profile (zeros, not NaN, outside its valid part) by the gain."""
    r = np.asarray(profile_m, float)
    nfft = 1 << int(np.ceil(np.log2(2 * r.size)))
    k = np.fft.rfftfreq(nfft, spacing_m)
    H = np.interp(k, g.wavenumber_cpm, g.gain, right=float(g.gain[-1]))
    return np.fft.irfft(np.fft.rfft(r, nfft) * H, nfft)[:r.size]


# ----------------------------------------------------------------------------------------------
# Noise-aware gain: the rail spectrum and each magnet's own error spectrum measured on the pass
@dataclass(frozen=True, eq=False)
class RailGain:
    """Spectra measured on one pass's magnet profiles and the Wiener gain they give.

    ``noise_psd`` N(k) is one magnet's own error (half the spectrum of two magnets' difference where
    both measured the same rail); ``rail_psd`` R(k) the magnets' mean auto-spectrum minus N, set to 0
    where it does not clear ``z`` standard errors of the two estimates. Both are smoothed over a
    band of constant relative width (``rel_width`` of k): the error spectrum is smooth (white gap
    noise, double-integrated accelerometer noise), so many Welch bins go into each value and the
    gain does not pass noise where the rail has none."""
    wavenumber_cpm: np.ndarray
    rail_psd: np.ndarray
    noise_psd: np.ndarray
    n_magnets: int
    n_points: int                  # grid points where two or more magnets measured (the noise's data)
    segment_m: float

    def gain(self, n_eff: float = 1.0) -> np.ndarray:
        """Wiener gain R / (R + N / n_eff) for a mean over ``n_eff`` magnets' independent errors."""
        with np.errstate(invalid="ignore", divide="ignore"):
            g = self.rail_psd / (self.rail_psd + self.noise_psd / max(float(n_eff), 1.0))
        return np.where(np.isfinite(g), g, 0.0)

    def cut_wavelength_m(self, n_eff: float = 1.0, level: float = 0.5) -> float | None:
        """Longest wavelength where the gain first falls below ``level`` (None: never)."""
        k, g = self.wavenumber_cpm, self.gain(n_eff)
        low = np.flatnonzero((g < level) & (k > 0))
        return float(1.0 / k[low[0]]) if low.size else None

    def to_dict(self) -> dict:
        return {"method": "Wiener gain from the rail spectrum and each magnet's own error spectrum "
                          "(half the spectrum of two magnets' difference), smoothed in relative bands",
                "n_magnets": self.n_magnets, "n_points_two_or_more": self.n_points,
                "segment_m": self.segment_m,
                "half_gain_wavelength_m": {"one_magnet": self.cut_wavelength_m(1.0),
                                           "all_magnets": self.cut_wavelength_m(self.n_magnets)}}


def _welch_runs(rows: list, fs: float, nperseg: int):
    """Welch PSD averaged over every finite run (of each row) holding a segment; (k, psd, n_segments)."""
    acc, nseg, k = None, 0, None
    for y in rows:
        for i0, i1 in _runs(np.isfinite(y)):
            if i1 - i0 < nperseg:
                continue
            seg = y[i0:i1]
            k, p = signal.welch(seg - seg.mean(), fs=fs, nperseg=nperseg)
            n = 1 + (seg.size - nperseg) // (nperseg // 2)
            acc = p * n if acc is None else acc + p * n
            nseg += n
    return (None, None, 0) if acc is None else (k, acc / nseg, nseg)


def _smooth_relative(k: np.ndarray, p: np.ndarray, rel_width: float):
    """Mean of p over |k' - k| <= rel_width * k / 2 (at least the bin itself); and the bin counts."""
    out, cnt = np.empty_like(p), np.empty(p.size)
    for i, kk in enumerate(k):
        m = np.abs(k - kk) <= 0.5 * rel_width * kk
        m[i] = True
        out[i], cnt[i] = p[m].mean(), m.sum()
    return out, cnt


def rail_gain(magnet_profiles_m: np.ndarray, spacing_m: float, nperseg: int = 256,
              rel_width: float = 0.25, z: float = 2.0, min_segments: int = 4) -> RailGain | None:
    """Rail and per-magnet error spectra of the profiles (n_magnets, n_points; NaN where a magnet has
    none) and their Wiener gain (:class:`RailGain`). None with one magnet or when the stretches that
    two magnets share hold fewer than ``min_segments`` Welch segments."""
    P = np.asarray(magnet_profiles_m, float)
    if P.ndim != 2 or P.shape[0] < 2:
        return None
    fs = 1.0 / spacing_m
    n_both = int(np.sum(np.sum(np.isfinite(P), axis=0) >= 2))
    diffs = [P[i] - P[j] for i in range(len(P)) for j in range(i + 1, len(P))]
    best = max((i1 - i0 for d in diffs for i0, i1 in _runs(np.isfinite(d))), default=0)
    nps = int(min(nperseg, 2 ** int(np.floor(np.log2(max(best, 2) / 2)))))
    if nps < 16:
        return None
    k, D, nd = _welch_runs(diffs, fs, nps)
    _, A, na = _welch_runs(list(P), fs, nps)
    if k is None or nd < min_segments or A is None:
        return None
    N, cnt = _smooth_relative(k, D / 2.0, rel_width)
    A, _ = _smooth_relative(k, A, rel_width)
    # relative standard error of a Welch average: 1 / sqrt(segments x bins averaged) (Hann, 50 %)
    se = np.sqrt((A ** 2) / (na * cnt) + (N ** 2) / (nd * cnt))
    R = A - N
    R = np.where(R > z * se, R, 0.0)
    R[0] = max(R[0], A[0])
    return RailGain(k, R, N, int(P.shape[0]), n_both, nps * spacing_m)


def magnets_averaged(magnet_profiles_m: np.ndarray, ramp_bins: int) -> np.ndarray:
    """Effective number of magnets with independent errors in the weighted mean at each point,
    (sum w)^2 / sum w^2 with the coverage weights of the profiler (:func:`.profile._coverage_weights`)."""
    from .profile import _coverage_weights
    W = _coverage_weights(np.isfinite(magnet_profiles_m), ramp_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.sum(W, axis=0) ** 2 / np.sum(W ** 2, axis=0)
    return np.where(np.isfinite(n), n, 1.0)


def apply_rail_gain(profile_m: np.ndarray, spacing_m: float, g: RailGain, n_eff) -> np.ndarray:
    """The profile filtered (zero phase) by the gain for the number of magnets averaged at each point
    (``n_eff``: scalar or per point; the filtered profiles for whole magnet counts are blended)."""
    r = np.asarray(profile_m, float)
    n_eff = np.broadcast_to(np.clip(np.asarray(n_eff, float), 1.0, g.n_magnets), r.shape)
    nfft = 1 << int(np.ceil(np.log2(2 * r.size)))
    k = np.fft.rfftfreq(nfft, spacing_m)
    R = np.fft.rfft(r, nfft)
    levels = np.arange(1, g.n_magnets + 1)
    fil = {}
    for m in levels:
        if np.any(np.abs(n_eff - m) < 1):
            H = np.interp(k, g.wavenumber_cpm, g.gain(m), right=0.0)
            fil[m] = np.fft.irfft(R * H, nfft)[:r.size]
    out = np.zeros_like(r)
    for m in fil:
        w = np.clip(1.0 - np.abs(n_eff - m), 0.0, 1.0)
        out += w * fil[m]
    return out
