"""Delay of the vehicle sensors behind the position channel, measured between passes at different speeds.

A causal anti-alias filter (or any acquisition latency) delays the magnet accelerations and gaps by
tau against the position samples. The inertial method maps the sample stamped t to the position at
t, but it describes the rail where the magnet was tau earlier: the profile of a pass at speed v is
the rail shifted by v tau along the line. Two passes over one rail at speeds v_a < v_b therefore
see it shifted by (v_b - v_a) tau against each other, which measures tau with no model.

Choices (each for a physical reason):
- The shift is read on the shortest waves both passes measured alike (magnitude-squared coherence
  >= ``min_coherence``, up to the profiles' own shortest wavelength), a band of two octaves: the long
  waves carry the girder's deflection under the vehicle, which stays where the girder is and pulls
  the shift towards zero (a 3-span line with a 3 ms filter: 2-8 m waves gave 1.1 ms, 0.5-2 m 3.0 ms).
- The common stretch is cut into ``n_segments`` segments; the median of their shifts is the
  estimate and their spread (MAD) its standard error, so the data say how well tau is known.
- The shift is found coarse to fine: on the whole stretch with waves 16x and 4x longer, then per
  segment within half the band's shortest wave of that (a cross-correlation peak is ambiguous by
  whole waves, so a 12 cm shift read on 10 cm waves alone came out 10 cm).
- The delay is worth applying only where it is ``sigmas`` standard errors from zero and positive
  (sensors behind the position: a causal filter). A negative delay (the position channel behind
  the sensors) is reported, not applied: the twin starts at the first position sample.

Written here: no library measures an acquisition delay from two inertial profiles; the pieces
(coherence, correlation, Butterworth) are scipy.signal's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import signal

from .profile import InertialProfiler


@dataclass(frozen=True)
class PassProfile:
    """A pass's loaded rail profile (inertial method, no delay applied) and what it was measured with."""
    source: str
    speed_mps: float                    # mean speed of the pass
    position_m: np.ndarray
    irregularity_m: np.ndarray          # NaN where not measured
    min_wavelength_m: float             # the profile's shortest resolved wave


@dataclass(frozen=True)
class PairShift:
    source_a: str
    source_b: str
    speed_a_mps: float
    speed_b_mps: float
    band_m: tuple[float, float]         # wavelengths the shift was read on
    shifts_m: tuple[float, ...]         # per segment, profile b against profile a
    delay_s: float
    std_s: float

    def to_dict(self) -> dict:
        return {"passes": [self.source_a, self.source_b], "speeds_mps": [self.speed_a_mps, self.speed_b_mps],
                "band_m": list(self.band_m), "segment_shifts_m": list(self.shifts_m),
                "delay_s": self.delay_s, "std_s": self.std_s}


@dataclass(frozen=True)
class SensorDelayEstimate:
    """``delay_s`` (None: not measurable, see ``reason``) and its standard error ``std_s``."""
    delay_s: float | None
    std_s: float | None
    pairs: tuple[PairShift, ...]
    sigmas: float
    reason: str

    @property
    def significant(self) -> bool:
        return self.delay_s is not None and self.std_s is not None and abs(self.delay_s) > self.sigmas * self.std_s

    @property
    def applicable(self) -> bool:
        """Significant and positive (the sensors behind the position), so the twin can run behind the
        stamps; every caller applies such a delay (``applied`` in :meth:`to_dict`)."""
        return self.significant and self.delay_s > 0

    def to_dict(self) -> dict:
        return {"delay_s": self.delay_s, "std_s": self.std_s, "significant": self.significant,
                "applied": self.applicable, "reason": self.reason,
                "pairs": [p.to_dict() for p in self.pairs]}


def stated_sensor_delay_s(metadata) -> float | None:
    """The delay of the vehicle accel topic behind the position topic that a contract ``Metadata``
    states (``acquisition.<topic>.delay_s``, docs/contract-extensions.md; >= 0), None if it states none."""
    from maglev_ros.contract import TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_POSITION
    acq = metadata.raw.get("acquisition") or {}
    topics = (TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_POSITION)
    if not (isinstance(acq, dict) and any(isinstance(acq.get(t), dict) and "delay_s" in acq[t] for t in topics)):
        return None
    d = metadata.acquisition_delay_s(TOPIC_VEHICLE_ACCEL) - metadata.acquisition_delay_s(TOPIC_VEHICLE_POSITION)
    return max(0.0, d)


def pass_profile(accel, gap, position, metadata, *, highpass_hz: float = 0.8, spacing_m: float,
                 channel_pairs: dict | None = None, nominal_gap_m: float | None = None,
                 source: str = "") -> PassProfile:
    """The loaded profile of one pass with no delay applied (ChannelData-like inputs as for
    :func:`~maglev_ros.irregularity.twin_input.profile_for_twin`, whose profiler settings it uses;
    ``metadata``: the contract metadata or the magnet offsets)."""
    from .twin_input import _resolve_vehicle
    offs, g0, pairs = _resolve_vehicle(metadata, accel, gap, nominal_gap_m, channel_pairs)
    prof = InertialProfiler(highpass_hz=highpass_hz, spacing_m=spacing_m, magnet_length_m=0.0,
                            edge_s=1.5 / highpass_hz)
    res = prof.fit(accel, gap, position, magnet_offsets_m=offs, nominal_gap_m=g0, channel_pairs=pairs)
    spd = np.abs(np.asarray(position.data, float)[:, list(position.channels).index("speed_mps")])
    moving = spd > prof.stop_speed_mps
    return PassProfile(source, float(np.mean(spd[moving])) if moving.any() else 0.0, res.position_m,
                       res.irregularity_m, float(res.min_wavelength_m))


def measure_sensor_delay(passes: Sequence[tuple], highpass_hz: float = 0.8) -> SensorDelayEstimate:
    """The delay measured between passes given as (accel, gap, position, metadata or magnet offsets,
    channel pairs, nominal gap [m] or None, source) on one grid: the finest any of them resolves
    (:func:`~maglev_ros.irregularity.twin_input.twin_spacing_m`). A pass the profiler cannot read is
    left out (it has no rail to compare)."""
    from maglev_ros.errors import UserError
    from .twin_input import twin_spacing_m
    if len(passes) < 2:
        return SensorDelayEstimator()([])
    spacing = min(twin_spacing_m(acc, pos, len(pairs or ())) for acc, _, pos, _, pairs, _, _ in passes)
    profiles = []
    for acc, gap, pos, md, pairs, g0, source in passes:
        try:
            profiles.append(pass_profile(acc, gap, pos, md, highpass_hz=highpass_hz, spacing_m=spacing,
                                         channel_pairs=pairs, nominal_gap_m=g0, source=source))
        except (UserError, ValueError):
            continue
    return SensorDelayEstimator()(profiles)


class SensorDelayEstimator:
    """Configuration in the constructor; ``__call__(profiles)`` with two or more :class:`PassProfile`."""

    def __init__(self, n_segments: int = 8, min_coherence: float = 0.5, sigmas: float = 3.0):
        if n_segments < 3:
            raise ValueError(f"n_segments: expected >= 3 (a spread needs segments), got {n_segments}")
        self.n_segments = int(n_segments)
        self.min_coherence = float(min_coherence)
        self.sigmas = float(sigmas)

    def __call__(self, profiles: Sequence[PassProfile]) -> SensorDelayEstimate:
        profs = [p for p in profiles if np.isfinite(p.speed_mps) and p.speed_mps > 0]
        if len(profs) < 2:
            return self._none((), "one pass: the delay of the sensors behind the position needs two passes at "
                                  "different speeds")
        pairs, why = [], []
        for i in range(len(profs)):
            for j in range(i + 1, len(profs)):
                a, b = sorted((profs[i], profs[j]), key=lambda p: p.speed_mps)
                got = self._pair(a, b)
                if isinstance(got, str):
                    why.append(f"{a.source} / {b.source}: {got}")
                else:
                    pairs.append(got)
        if not pairs:
            return self._none((), "; ".join(why) or "no pair of passes to compare")
        w = np.array([1.0 / p.std_s ** 2 for p in pairs])
        d = float(np.sum(w * np.array([p.delay_s for p in pairs])) / np.sum(w))
        s = float(1.0 / math.sqrt(np.sum(w)))
        est = SensorDelayEstimate(d, s, tuple(pairs), self.sigmas, "")
        if est.applicable:
            reason = (f"the passes' rails are shifted against each other by their speed difference times "
                      f"{d * 1e3:.2f} +- {s * 1e3:.2f} ms: the vehicle sensors lag the position by that")
        elif est.significant:
            reason = (f"the position channel lags the vehicle sensors by {-d * 1e3:.2f} +- {s * 1e3:.2f} ms "
                      "(not applied: the twin runs from the first position sample)")
        else:
            reason = f"no delay measurable ({d * 1e3:.2f} +- {s * 1e3:.2f} ms)"
        return SensorDelayEstimate(d, s, tuple(pairs), self.sigmas, reason)

    def _none(self, pairs, reason: str) -> SensorDelayEstimate:
        return SensorDelayEstimate(None, None, tuple(pairs), self.sigmas, reason)

    def _pair(self, a: PassProfile, b: PassProfile) -> PairShift | str:
        dv = b.speed_mps - a.speed_mps
        dx = float(min(np.median(np.diff(a.position_m)), np.median(np.diff(b.position_m))))
        lo, hi = max(a.position_m[0], b.position_m[0]), min(a.position_m[-1], b.position_m[-1])
        if not (dv > 0 and dx > 0 and hi > lo):
            return "equal speeds or no common stretch"
        x = np.arange(lo, hi, dx)
        ra = np.interp(x, a.position_m, a.irregularity_m)
        rb = np.interp(x, b.position_m, b.irregularity_m)
        ok = np.isfinite(ra) & np.isfinite(rb)
        ra, rb = ra[ok] - np.mean(ra[ok]), rb[ok] - np.mean(rb[ok])
        f_top = 1.0 / max(a.min_wavelength_m, b.min_wavelength_m)
        # coherence resolved to 1/16 of the shortest wave's wavenumber
        nper = min(ra.size // 4, int(round(16.0 / (dx * f_top))))
        if nper < 16 or ra.size < self.n_segments * nper // 2:
            return "too short a common stretch"
        f, coh = signal.coherence(ra, rb, fs=1.0 / dx, nperseg=nper)
        # the shortest wave up to which the two passes agree, from the longest down
        k = 1
        while k < f.size and f[k] <= f_top and coh[k] >= self.min_coherence:
            k += 1
        f_hi = float(f[k - 1])
        if k < 3 or not f_hi > 0:
            return f"the passes' rails do not agree (coherence < {self.min_coherence:g}) on any short wave"
        f_hi = min(f_hi, 0.999 * 0.5 / dx)
        # coarse to fine: the whole stretch's lag on waves 16x and 4x longer first, so that a shift
        # longer than half the shortest wave is not taken for a neighbouring peak
        lag = 0.0
        for scale in (16.0, 4.0):
            fa, fb = _band(ra, rb, f_hi / scale, dx)
            lag = _peak_lag(fa, fb, lag, max(1.0, 0.5 * scale / f_hi / dx))
        fa, fb = _band(ra, rb, f_hi, dx)
        n = fa.size // self.n_segments
        half = max(1.0, 0.5 / f_hi / dx)
        shifts = [_peak_lag(fa[s * n:(s + 1) * n], fb[s * n:(s + 1) * n], lag, half) * dx
                  for s in range(self.n_segments)]
        t = np.array(shifts) / dv
        med = float(np.median(t))
        # standard error of the median from the MAD (normal-consistent), never below the grid's own
        mad = 1.4826 * float(np.median(np.abs(t - med)))
        std = max(mad, dx / dv / math.sqrt(12.0)) / math.sqrt(len(t))
        return PairShift(a.source, b.source, a.speed_mps, b.speed_mps, (1.0 / f_hi, 4.0 / f_hi),
                         tuple(float(s) for s in shifts), med, std)


def _band(a: np.ndarray, b: np.ndarray, f_hi: float, dx: float) -> tuple[np.ndarray, np.ndarray]:
    """Both profiles band-passed to two octaves of waves below 1/f_hi (zero phase)."""
    f_hi = min(f_hi, 0.999 * 0.5 / dx)
    sos = signal.butter(4, [f_hi / 4, f_hi], btype="band", fs=1.0 / dx, output="sos")
    return signal.sosfiltfilt(sos, a), signal.sosfiltfilt(sos, b)


def _peak_lag(a: np.ndarray, b: np.ndarray, around: float, half_width: float) -> float:
    """Lag [samples] of b behind a at the cross-correlation's peak within ``around`` +- ``half_width``,
    parabola-refined."""
    c = signal.correlate(b, a, mode="full")
    lags = signal.correlation_lags(b.size, a.size, mode="full")
    m = np.abs(lags - around) <= half_width
    if not m.any():
        return float(around)
    c, lags = c[m], lags[m]
    j = int(np.argmax(c))
    if 0 < j < c.size - 1:
        den = c[j - 1] - 2 * c[j] + c[j + 1]
        return float(lags[j] + (0.5 * (c[j - 1] - c[j + 1]) / den if den < 0 else 0.0))
    return float(lags[j])
