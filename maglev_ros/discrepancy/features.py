"""Time-frequency band powers (the common currency of localization, fitting and acceptance).

Every channel is cut into Hann frames (``frame_s`` long, hop ``hop_s``) on a common frame-time grid;
in each frame the power of each band of ``BAND_EDGES_HZ`` is the one-sided periodogram integrated
with triangular weights that peak at the band's centre and reach zero at the neighbouring centres
(a partition of unity, so the band powers of a frame still sum to its mean square). Triangular
rather than rectangular bands make the features change smoothly when a mode moves by a few
percent, as it does between FE meshes or integrators, instead of jumping across a band edge. Bands above
``nyquist_fraction`` of Nyquist are dropped (anti-alias filters differ between instruments).
The fit measure is the NRMSE of band *amplitudes* sqrt(P): phase-insensitive, so deterministic
physics (a stiffer bearing) and stochastic physics (ambient vibration, judged by its power) are
scored on the same scale. Hand-written: a framed periodogram summed over bands is ~20 lines of
numpy; scipy.signal.stft gives the same frames but not the band integration we need.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .recording import Recording

BAND_EDGES_HZ = np.array([0.0, 3.0, 6.0, 10.0, 14.0, 18.0, 22.0, 26.0, 31.0, 37.0, 44.0, 52.0, 62.0,
                          74.0, 88.0, 105.0, 125.0, 150.0, 180.0, 215.0])
FRAME_S = 0.5
HOP_S = 0.25


@dataclass(frozen=True, eq=False)
class FrameGrid:
    t_center_s: np.ndarray          # (nf,)
    frame_s: float
    edges_hz: np.ndarray            # (nb + 1,)

    @property
    def n_frames(self) -> int:
        return int(self.t_center_s.size)

    @property
    def n_bands(self) -> int:
        return int(self.edges_hz.size - 1)

    @property
    def band_center_hz(self) -> np.ndarray:
        e = self.edges_hz
        return 0.5 * (e[:-1] + e[1:])


def frame_grid(rec: Recording, frame_s: float = FRAME_S, hop_s: float = HOP_S,
               edges_hz: np.ndarray = BAND_EDGES_HZ) -> FrameGrid:
    t0, t1 = rec.t0_s, rec.t1_s
    n = max(1, int(np.floor((t1 - t0 - frame_s) / hop_s)) + 1)
    return FrameGrid(t0 + frame_s / 2 + hop_s * np.arange(n), frame_s, np.asarray(edges_hz, float))


def usable_bands(grid: FrameGrid, fs_hz: float, nyquist_fraction: float = 0.7) -> np.ndarray:
    """Mask of bands wholly below ``nyquist_fraction`` * fs/2."""
    return grid.edges_hz[1:] <= nyquist_fraction * fs_hz / 2 + 1e-9


def _frames(t_s: np.ndarray, size: int, fs_hz: float, grid: FrameGrid):
    """Hann frames of the grid on a signal of ``size`` samples stamped ``t_s``: window, frequencies,
    mask of frames inside the signal and their sample indices (n_ok, n)."""
    n = int(round(grid.frame_s * fs_hz))
    starts = np.searchsorted(t_s, grid.t_center_s - grid.frame_s / 2)
    ok = (starts >= 0) & (starts + n <= size)
    idx = starts[ok][:, None] + np.arange(n)[None, :]
    w, f = _window_and_freqs(n, float(fs_hz))
    return w, f, ok, idx


@lru_cache(maxsize=64)
def _window_and_freqs(n: int, fs_hz: float):
    # the same few frame lengths recur for every frame of every channel (read-only: shared)
    w, f = np.hanning(n), np.fft.rfftfreq(n, 1.0 / fs_hz)
    w.flags.writeable = f.flags.writeable = False
    return w, f


def _band_power(X: np.ndarray, w: np.ndarray, fs_hz: float, W: np.ndarray) -> np.ndarray:
    """Band powers (rows of X, n_bands) of the one-sided periodogram of Hann-windowed frames X."""
    n = w.size
    p = np.abs(X) ** 2 / (np.sum(w ** 2) * fs_hz)
    p[:, 1:] *= 2.0
    if n % 2 == 0:
        p[:, -1] /= 2.0
    return (p @ W.T) * (fs_hz / n)


def band_powers(t_s: np.ndarray, x: np.ndarray, fs_hz: float, grid: FrameGrid) -> np.ndarray:
    """(n_frames, n_bands) band powers of signal x (NaN for frames outside the signal)."""
    w, f, ok, idx = _frames(t_s, x.size, fs_hz, grid)
    out = np.full((grid.n_frames, grid.n_bands), np.nan)
    if ok.any():
        out[ok] = _band_power(np.fft.rfft(x[idx] * w[None, :], axis=1), w, fs_hz, band_weights(grid, f))
    return out


def band_weights(grid: FrameGrid, f_hz: np.ndarray) -> np.ndarray:
    """Triangular partition-of-unity weights (n_bands, len(f)) on the band centres; frequencies
    above the last band's upper edge get no weight (read-only array, cached: every frame of every
    channel asks for the same few)."""
    f = np.asarray(f_hz, float)
    return _band_weights(np.asarray(grid.edges_hz, float).tobytes(), f.tobytes())


@lru_cache(maxsize=64)
def _band_weights(edges_bytes: bytes, f_bytes: bytes) -> np.ndarray:
    e = np.frombuffer(edges_bytes)
    f = np.frombuffer(f_bytes)
    c = 0.5 * (e[:-1] + e[1:])
    W = np.zeros((c.size, f.size))
    for b in range(c.size):
        w = np.zeros_like(f)
        if b == 0:
            w[f <= c[0]] = 1.0
        else:
            sel = (f > c[b - 1]) & (f <= c[b])
            w[sel] = (f[sel] - c[b - 1]) / (c[b] - c[b - 1])
        if b == c.size - 1:
            w[(f > c[b]) & (f < e[-1])] = 1.0
        else:
            sel = (f > c[b]) & (f < c[b + 1])
            w[sel] = (c[b + 1] - f[sel]) / (c[b + 1] - c[b])
        W[b] = w
    W.flags.writeable = False
    return W


def band_widths(grid: FrameGrid) -> np.ndarray:
    """Integral over frequency of each band's triangular weight [Hz] (white noise of PSD S gives
    band power S * width)."""
    c = grid.band_center_hz
    w = np.empty(c.size)
    if c.size == 1:
        return np.array([grid.edges_hz[-1]])
    w[1:-1] = (c[2:] - c[:-2]) / 2
    w[0] = c[0] + (c[1] - c[0]) / 2
    w[-1] = (c[-1] - c[-2]) / 2 + (grid.edges_hz[-1] - c[-1])
    return w


def channel_powers(rec: Recording, signals: dict[str, np.ndarray], grid: FrameGrid,
                   refs: dict[str, float] | None = None) -> dict[str, np.ndarray]:
    """Band powers of each channel's signal (minus its rest value ``refs[name]``)."""
    out = {}
    for name, ch in rec.channels.items():
        y = signals[name] - (refs or {}).get(name, 0.0)
        out[name] = band_powers(ch.time_s, y, ch.sample_rate_hz, grid)
    return out


def nrmse_amplitude(pm: np.ndarray, pt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """||sqrt(pm) - sqrt(pt)|| / ||sqrt(pm)|| over finite entries (and ``mask``)."""
    am, at = np.sqrt(np.clip(pm, 0, None)), np.sqrt(np.clip(pt, 0, None))
    ok = np.isfinite(am) & np.isfinite(at)
    if mask is not None:
        ok &= mask
    den = np.sqrt(np.sum(am[ok] ** 2))
    return float(np.sqrt(np.sum((am[ok] - at[ok]) ** 2)) / den) if den > 0 else 0.0


S_MIN_HZ = 2.5      # below this the frame's 1/w^2 integration of the acceleration is not trusted


def rail_transmissibility(t_s: np.ndarray, accel_mps2: np.ndarray, gap_m: np.ndarray, fs_hz: float,
                          grid: FrameGrid, with_rail_power: bool = False):
    """(n_frames, n_bands) squared gap-to-rail transmissibility of one magnet: band power of the
    gap over band power of the rail under it, y = z + g (magnet displacement z = -A / w^2 from the
    acceleration's spectrum, plus the gap), per Hann frame. For a linear levitation loop this is
    |S(f)|^2, the loop's sensitivity, whatever the rail: an error in the irregularity that drives the
    twin cancels to first order (measured on a clean case: gap band amplitudes off by 10-36 % from a
    reconstructed irregularity, this ratio within 2-12 %, the 12 % being a kp/kv mis-calibration).
    Anti-alias filters and acquisition delays common to both channels cancel too. Bands below
    ``S_MIN_HZ`` and frames outside the signal are NaN. ``with_rail_power``: also return the band
    powers of the rail y (same shape)."""
    w, f, ok, idx = _frames(t_s, min(accel_mps2.size, gap_m.size), fs_hz, grid)
    W = band_weights(grid, f)
    out = np.full((grid.n_frames, grid.n_bands), np.nan)
    rail = out.copy()
    if not ok.any():
        return (out, rail) if with_rail_power else out
    g = gap_m[idx]
    A = np.fft.rfft(accel_mps2[idx] * w, axis=1)
    G = np.fft.rfft((g - g.mean(axis=1, keepdims=True)) * w, axis=1)
    keep = f >= S_MIN_HZ
    inv = np.zeros_like(f)
    inv[keep] = -1.0 / (2 * np.pi * f[keep]) ** 2
    Y = A * inv[None, :] + G
    pg = _band_power(G * keep[None, :], w, fs_hz, W)
    py = _band_power(Y, w, fs_hz, W)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(py > 0, pg / py, np.nan)
    r[:, W[:, ~keep].sum(axis=1) > 0.5 * W.sum(axis=1)] = np.nan     # bands mostly below S_MIN_HZ
    out[ok] = r
    rail[ok] = py
    return (out, rail) if with_rail_power else out


def without_long_waves(x: np.ndarray, fs_hz: float, corners) -> np.ndarray:
    """``x`` with its content below the rail reconstruction's band removed except its mean: each
    (corner_hz, order) of ``corners`` applied as a zero-phase Butterworth high-pass (gain
    (f/fc)^(2 order) / (1 + (f/fc)^(2 order)), the reconstruction's own filters), NaN samples kept
    NaN. Used on gaps before their frame means: the twin's rail holds the rail's waves only through
    those filters, so the gap's slow tracking of the waves below them cannot be predicted and the
    measured gap is compared through the same filters; the mean (a sensor offset) can be.
    ``corners`` None or empty: ``x`` unchanged."""
    corners = [(float(c), int(o)) for c, o in (corners or ()) if c and 0 < c < 0.5 * fs_hz]
    if not corners:
        return x
    from scipy import signal
    ok = np.isfinite(x)
    if ok.sum() < 16:
        return x
    idx = np.arange(x.size)
    out = np.interp(idx, idx[ok], x[ok])
    for corner_hz, order in corners:
        out = signal.sosfiltfilt(signal.butter(order, corner_hz, btype="high", fs=fs_hz, output="sos"), out)
    out = out + float(np.mean(x[ok]))
    out[~ok] = np.nan
    return out


def frame_means(t_s: np.ndarray, x: np.ndarray, fs_hz: float, grid: FrameGrid) -> np.ndarray:
    """(n_frames,) Hann-weighted mean of x in each frame (NaN outside the signal)."""
    w, _, ok, idx = _frames(t_s, x.size, fs_hz, grid)
    out = np.full(grid.n_frames, np.nan)
    if ok.any():
        out[ok] = (x[idx] @ w) / w.sum()
    return out
