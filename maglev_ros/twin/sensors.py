"""Instrument chain of the simulated test line: gain/offset, anti-alias filter, decimation, noise.

A simulated channel is computed at an internal rate ``fs_internal_hz`` = ``oversample`` x the
recorded rate. :class:`InstrumentChain` turns it into what a data-acquisition system records:

1. ``y = gain * x + offset`` (per channel; sensor calibration error),
2. a causal anti-alias low-pass at the internal rate (``butterworth`` or ``bessel``, order 8,
   corner ``cutoff_frac`` x the recorded rate, default 0.4 fs; ``none`` disables it). The filter
   starts in its steady state for the first sample (the acquisition system was already running),
   so a signal with an offset (the 10 mm gap) does not ring at the start. The 8th-order
   Butterworth at 0.4 fs is > 60 dB down at 0.85 fs; a Bessel (linear phase) at the same corner is
   only ~22 dB down there: use a lower ``cutoff_frac`` (~0.2) with Bessel,
3. decimation: every ``oversample``-th filtered sample, at the same instants (the filter delay is
   kept, as in real hardware),
4. additive noise at the recorded rate: white (``noise_rms``, the RMS over the recorded band
   0..fs/2) plus optional 1/f noise (``pink_rms``, RMS of the 1/f part between ``pink_min_hz`` and
   fs/2), independent per channel.

Streaming: ``process(chunk)`` keeps the filter state, the decimation phase and the 1/f generator
state, so a long record can be made chunk by chunk with the same result as in one piece.
The 1/f noise is a sum of equal-variance first-order (Lorentzian) processes with corners one
octave apart: their summed spectrum is 1/f within about +-1 dB between the lowest corner and
fs/2 (a standard construction; written by hand because scipy has no coloured-noise generator).
Filters come from scipy.signal (``butter``/``bessel`` as second-order sections, ``sosfilt``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, asdict
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import signal

from maglev_ros.errors import UserError

__all__ = ["AntiAlias", "NoiseSpec", "InstrumentChain", "anti_alias_sos", "anti_alias_delay_s",
           "pink_noise_bank"]

FILTER_KINDS = ("butterworth", "bessel", "none")


@dataclass(frozen=True)
class AntiAlias:
    """Causal anti-alias low-pass applied at the internal rate before decimation."""
    kind: str = "butterworth"
    order: int = 8
    cutoff_frac: float = 0.4          # corner / recorded rate (0.4 -> 80 % of Nyquist)

    def __post_init__(self) -> None:
        if self.kind not in FILTER_KINDS:
            raise UserError(f"instrument.anti_alias.kind: expected one of {', '.join(FILTER_KINDS)}, "
                            f"got {self.kind!r}")
        if self.kind != "none":
            if not (isinstance(self.order, int) and 1 <= self.order <= 16):
                raise UserError(f"instrument.anti_alias.order: expected an integer 1..16, got {self.order!r}")
            if not (0.0 < self.cutoff_frac < 0.5):
                raise UserError(f"instrument.anti_alias.cutoff_frac: expected 0 < value < 0.5 "
                                f"(fraction of the recorded rate), got {self.cutoff_frac!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping | None, where: str = "instrument.anti_alias") -> "AntiAlias":
        if d is None:
            return cls()
        if isinstance(d, str):
            return cls(kind=d)
        if not isinstance(d, Mapping):
            raise UserError(f"{where}: expected a mapping or a filter kind, got {d!r}")
        unknown = set(d) - {"kind", "order", "cutoff_frac"}
        if unknown:
            raise UserError(f"{where}: unknown key(s) {sorted(unknown)} (expected kind, order, cutoff_frac)")
        return cls(kind=str(d.get("kind", "butterworth")), order=int(d.get("order", 8)),
                   cutoff_frac=float(d.get("cutoff_frac", 0.4)))


@dataclass(frozen=True)
class NoiseSpec:
    """Sensor noise and calibration of one sensor group (values in the channel's SI unit)."""
    noise_rms: float = 0.0            # white noise RMS over 0..fs/2 of the recorded signal
    pink_rms: float = 0.0             # 1/f noise RMS between pink_min_hz and fs/2
    pink_min_hz: float = 0.05
    gain: float = 1.0
    offset: float = 0.0
    channels: Mapping[str, Mapping[str, float]] = field(default_factory=dict)  # per-channel gain/offset

    def __post_init__(self) -> None:
        for k in ("noise_rms", "pink_rms"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise UserError(f"instrument.<group>.{k}: expected a number >= 0, got {v!r}")
        if not self.pink_min_hz > 0:
            raise UserError(f"instrument.<group>.pink_min_hz: expected > 0, got {self.pink_min_hz!r}")

    def gain_offset(self, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        g = np.full(len(channels), float(self.gain))
        o = np.full(len(channels), float(self.offset))
        for i, ch in enumerate(channels):
            c = self.channels.get(ch) or {}
            g[i] = float(c.get("gain", g[i]))
            o[i] = float(c.get("offset", o[i]))
        return g, o

    def to_dict(self) -> dict:
        d = asdict(self)
        d["channels"] = {k: dict(v) for k, v in self.channels.items()}
        return d

    @classmethod
    def from_dict(cls, d: Mapping | None, where: str) -> "NoiseSpec":
        if d is None:
            return cls()
        if not isinstance(d, Mapping):
            raise UserError(f"{where}: expected a mapping, got {d!r}")
        keys = {"noise_rms", "pink_rms", "pink_min_hz", "gain", "offset", "channels"}
        unknown = set(d) - keys
        if unknown:
            raise UserError(f"{where}: unknown key(s) {sorted(unknown)} (expected {', '.join(sorted(keys))})")
        kw: dict[str, Any] = {}
        for k in ("noise_rms", "pink_rms", "pink_min_hz", "gain", "offset"):
            if k in d:
                try:
                    kw[k] = float(d[k])
                except (TypeError, ValueError):
                    raise UserError(f"{where}.{k}: expected a number, got {d[k]!r}") from None
        ch = d.get("channels") or {}
        if not isinstance(ch, Mapping):
            raise UserError(f"{where}.channels: expected a mapping channel -> {{gain, offset}}, got {ch!r}")
        kw["channels"] = {str(k): dict(v) for k, v in ch.items()}
        try:
            return cls(**kw)
        except UserError as exc:
            raise UserError(str(exc).replace("instrument.<group>", where)) from None


def anti_alias_sos(spec: AntiAlias, fs_out_hz: float, fs_internal_hz: float) -> np.ndarray | None:
    """Second-order sections of the anti-alias low-pass at the internal rate (None: no filter)."""
    if spec.kind == "none":
        return None
    wn = spec.cutoff_frac * fs_out_hz
    if spec.kind == "butterworth":
        return signal.butter(spec.order, wn, btype="low", output="sos", fs=fs_internal_hz)
    # Bessel normalised so the -3 dB point is at the corner ("mag"), like a data sheet corner
    return signal.bessel(spec.order, wn, btype="low", output="sos", norm="mag", fs=fs_internal_hz)


def anti_alias_delay_s(spec: AntiAlias, fs_out_hz: float, fs_internal_hz: float) -> float:
    """Low-frequency group delay of the anti-alias filter [s] (0 without a filter): what a
    recording states as its acquisition delay (docs/contract-extensions.md)."""
    sos = anti_alias_sos(spec, fs_out_hz, fs_internal_hz)
    if sos is None:
        return 0.0
    b, a = signal.sos2tf(sos)
    _, gd = signal.group_delay((b, a), w=[1e-4 * fs_out_hz], fs=fs_internal_hz)
    return float(gd[0]) / fs_internal_hz


def pink_noise_bank(fs_hz: float, f_min_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Pole coefficients a_k and input gains b_k of the octave-spaced AR(1) bank whose summed
    output has a 1/f spectrum between f_min and fs/2 and unit total variance."""
    f_max = 0.5 * fs_hz
    if f_min_hz >= f_max:
        return np.array([0.0]), np.array([1.0])
    n = int(math.ceil(math.log2(f_max / f_min_hz))) + 1
    fc = f_min_hz * 2.0 ** np.arange(n)
    fc = fc[fc < f_max]
    a = np.exp(-2 * np.pi * fc / fs_hz)
    b = np.full(fc.size, 1.0 / math.sqrt(fc.size))    # unit-variance AR(1)s, summed to unit variance
    return a, b


class InstrumentChain:
    """Streaming instrument chain for one sensor group (see module docstring).

    ``InstrumentChain(channels, fs_out_hz, oversample, anti_alias, noise, rng)``;
    ``process(x_internal)`` with x (n, n_channels) at ``fs_out_hz * oversample`` returns the
    recorded samples (m, n_channels) at ``fs_out_hz``: internal samples with (global) index
    i = oversample - 1, 2 oversample - 1, ... of the whole stream, i.e. the instants
    (i + 1) / fs_internal when the first internal sample is at 1 / fs_internal.
    ``phase`` shifts which internal samples are kept (index i with (i - phase) % oversample == 0).
    """

    def __init__(self, channels: Sequence[str], fs_out_hz: float, oversample: int = 4,
                 anti_alias: AntiAlias | None = None, noise: NoiseSpec | None = None,
                 rng: np.random.Generator | int | None = None, phase: int | None = None):
        if not (isinstance(oversample, (int, np.integer)) and oversample >= 1):
            raise UserError(f"rates.oversample: expected an integer >= 1, got {oversample!r}")
        if not fs_out_hz > 0:
            raise UserError(f"sample rate: expected > 0 Hz, got {fs_out_hz!r}")
        self.channels = tuple(channels)
        self.fs_out_hz = float(fs_out_hz)
        self.oversample = int(oversample)
        self.fs_internal_hz = self.fs_out_hz * self.oversample
        self.anti_alias = anti_alias or AntiAlias()
        self.noise = noise or NoiseSpec()
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.gain, self.offset = self.noise.gain_offset(self.channels)
        self.sos = anti_alias_sos(self.anti_alias, self.fs_out_hz, self.fs_internal_hz)
        self._zi = None
        self._n_in = 0
        self._phase = self.oversample - 1 if phase is None else int(phase) % self.oversample
        nc = len(self.channels)
        self._pink_a, self._pink_b = pink_noise_bank(self.fs_out_hz, self.noise.pink_min_hz)
        self._pink_state = None
        if self.noise.pink_rms > 0:
            # start the 1/f bank in its stationary distribution
            self._pink_state = self.rng.standard_normal((self._pink_a.size, nc))

    def describe(self) -> dict:
        return {"fs_out_hz": self.fs_out_hz, "oversample": self.oversample,
                "fs_internal_hz": self.fs_internal_hz, "anti_alias": self.anti_alias.to_dict(),
                "noise": self.noise.to_dict()}

    def _filter(self, y: np.ndarray) -> np.ndarray:
        if self.sos is None:
            return y
        if self._zi is None:
            zi0 = signal.sosfilt_zi(self.sos)                  # (n_sections, 2) for unit step
            self._zi = zi0[:, :, None] * y[0][None, None, :]   # steady state at the first value
        out, self._zi = signal.sosfilt(self.sos, y, axis=0, zi=self._zi)
        return out

    def _pink(self, n: int) -> np.ndarray:
        nc = len(self.channels)
        out = np.zeros((n, nc))
        for k, (a, b) in enumerate(zip(self._pink_a, self._pink_b)):
            w = self.rng.standard_normal((n, nc)) * math.sqrt(1 - a * a)
            # x[n] = a x[n-1] + w[n], state carried across chunks (unit variance each)
            y, _ = signal.lfilter([1.0], [1.0, -a], w, axis=0, zi=(a * self._pink_state[k])[None, :])
            self._pink_state[k] = y[-1]
            out += y * b
        return out

    def process(self, x_internal: np.ndarray) -> np.ndarray:
        x = np.asarray(x_internal, dtype=float)
        if x.ndim == 1:
            x = x[:, None]
        if x.shape[1] != len(self.channels):
            raise UserError(f"instrument chain: {x.shape[1]} columns for {len(self.channels)} channels")
        y = x * self.gain[None, :] + self.offset[None, :]
        y = self._filter(y)
        n = y.shape[0]
        idx = np.arange(n) + self._n_in
        keep = (idx - self._phase) % self.oversample == 0
        self._n_in += n
        out = y[keep]
        m = out.shape[0]
        if m and self.noise.noise_rms > 0:
            out = out + self.noise.noise_rms * self.rng.standard_normal(out.shape)
        if m and self.noise.pink_rms > 0:
            out = out + self.noise.pink_rms * self._pink(m)
        return out
