"""Whether an identified pole is a spectral peak of its own (a local maximum of the measured PSD).

A pole that an identification places on the skirt of a stronger neighbour (off a band edge, or a
two-channel group whose shapes cannot tell poles apart) has no peak of its own: the flank toward
the neighbour is higher than the PSD at the pole. Used for modes a test must confirm before they
count (extra modes in the data, per-span group identifications).
"""
from __future__ import annotations

import math
from typing import Iterable

import numpy as np
from scipy.signal import welch


def spectral_peak(signals: Iterable[np.ndarray], fs_hz: float | Iterable[float], f_hz: float,
                  others_hz=()) -> tuple[float, float]:
    """(largest PSD within +-1 % of ``f_hz`` over the higher of its two flanks' median PSDs, 3-10 %
    below and above, best signal; the ratio a Welch estimate of K segments reaches by chance:
    1 + 3 / sqrt(K)). ``fs_hz``: one sampling rate or one per signal. With another identified mode
    (``others_hz``) closer than the flanks begin, the estimate cannot tell the two peaks apart and
    the mode is not confirmed (ratio 0)."""
    signals = list(signals)
    rates = list(fs_hz) if np.ndim(fs_hz) else [float(fs_hz)] * len(signals)
    best, needed = 0.0, np.inf
    for x, fs in zip(signals, rates):
        x = np.asarray(x, dtype=float)
        x = x - np.mean(x)
        nper = int(min(8192, max(256, x.size // 8)))
        f, p = welch(x, fs, nperseg=nper)
        df = f[1] - f[0]
        d = np.abs(f - f_hz)
        gap = max(0.03 * f_hz, 3 * df)
        if any(abs(g - f_hz) < gap for g in others_hz):
            continue                                   # another mode inside the gap: not resolved here
        near = d <= max(0.01 * f_hz, 2 * df)
        flank = (d >= gap) & (d <= max(0.1 * f_hz, 10 * df))
        left, right = flank & (f < f_hz), flank & (f > f_hz)
        if not near.any() or not left.any() or not right.any():
            continue
        level = max(float(np.median(p[left])), float(np.median(p[right])))
        if level <= 0:
            continue
        k = max(1, 2 * x.size // nper - 1)            # segments at 50 % overlap
        best = max(best, float(p[near].max() / level))
        needed = 1.0 + 3.0 / math.sqrt(k)
    return best, (needed if np.isfinite(needed) else 0.0)

