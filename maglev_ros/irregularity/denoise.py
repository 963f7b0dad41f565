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
