"""Guideway irregularity profile by the inertial reference method (batch and streaming).

For every electromagnet k with vertical acceleration a_k(t) and gap g_k(t) (contract signs: z up,
gap = pole face to rail underside, a rise r of the rail and z_m of the magnet change the gap by
r - z_m):

    r(x_ref(t) + offset_k) = z_m,k(t) + (g_k(t) - g0) [- w_k(t)]

with z_m,k the band-limited double integral of a_k (see :mod:`.integration`), the gap change
high-passed by exactly the same zero-phase filter H(f) (corner ``highpass_hz``), and w_k the
girder deflection under magnet k predicted by a twin, when supplied (result kind ``unloaded``;
without it the profile includes the deflection under the vehicle: kind ``loaded``).

Band (choices, stated in every result):

* The time high-pass removes wavelengths longer than about ``v / f_c``; the band therefore depends
  on speed. The profile is binned onto a regular position grid (``spacing_m``) and then band-passed
  in wavenumber by a zero-phase Butterworth band-pass (order ``filter_order``, run forward and
  backward) with corners ``1/max_wavelength_m`` and ``1/min_wavelength_m``. With order 4 the time
  filter's gain is > 0.996 wherever the spatial filter's gain exceeds 0.004 if
  ``max_wavelength_m = v_band / (2 f_c)`` (``band_factor = 2``): the result is then one stated
  band everywhere. ``v_band`` is ``band_speed_mps`` or, by default, the 5th percentile of speed
  over the distance travelled above ``stop_speed_mps``, judged on the speed averaged over
  ``1/f_c`` (:meth:`InertialProfiler.band_speed_series`: the filter responds to that, not to the
  speed channel's noise); positions passed slower than ``0.89 v_band`` (where the time filter
  still passes 99 % of the longest wave, :meth:`InertialProfiler.slow_speed_mps`) are dropped
  (reported as ``slow_section``). Samples below ``stop_speed_mps`` never map to
  positions, so a stop never divides by zero.
* The corner follows the recording unless given (``highpass_hz=None``, :func:`auto_highpass_hz`).
  Every clean stretch loses its settling time to the filters: ``edge_s = 0.6/f_c`` of the double
  integral at each end, and one longest wave (``trim_wavelengths * max_wavelength_m``, i.e.
  ``1/(band_factor f_c)`` s) of the band-pass at each end, together ``2.2/f_c`` s at the defaults.
  The corner is the lowest at which that settling takes at most ``settle_fraction`` (half) of the
  longest clean moving stretch ``T``: ``f_c = 2.2 / (0.5 T) = 4.4 / T`` (0.35 Hz for 12.7 s,
  0.22 Hz for 20 s), never below ``min_highpass_hz`` = 0.2 Hz (the double-integrated white noise
  of a 0.02 m/s^2 accelerometer at 1 kHz is ~0.15 mm rms above 0.2 Hz and ~0.4 mm above 0.1 Hz,
  growing as f_c^-1.5: the size of a good line's 1-50 m irregularity). A shorter pass thus gets a
  higher corner, and a slower one a shorter longest wave; the result states the corner, the
  stretch and the rule (:class:`CornerChoice`).
* ``min_wavelength_m = max(magnet_length_m, 4 * spacing_m, 4 * v_max / fs)``. ``magnet_length_m``
  defaults to 0: the gap sensor and the accelerometer measure at a point, so the magnet's length
  (about 3 m) filters its force, not what its sensors see (measured on simulated point sensors:
  docs/irregularity.md); set it for sensors that average over a length. The 4x grid / sampling
  factor keeps the bin average (boxcar, gain ``sinc(spacing / wavelength)``) at >= 0.90 in the
  band.
* Band corners are the -6 dB (half-amplitude) points of the stated zero-phase filter; a caller
  that wants to compare with a known profile applies the same filter to it (``band_filter`` in
  :meth:`IrregularityResult.to_dict`).

Grid and sample step: samples are bin-averaged onto the grid. Above ``spacing_m * fs`` (20 m/s
for 0.02 m at 1 kHz, 10 m/s at 500 Hz) consecutive samples of one magnet lie more than one bin
apart, so the grid has empty bins between filled ones although nothing is missing. Such holes up
to ``ceil(v_max / fs / spacing_m) + 1`` bins long (one sample step, at least 2 bins) are filled by
linear interpolation between the neighbouring bins; longer holes are real gaps (dropouts, slow
sections, ends) and stay NaN. (Before this rule holes were filled only up to 2 bins, so at 500 Hz
with 0.02 m any pass above 30 m/s fell apart into fragments shorter than the band-pass needs and
the profile came out empty.) Linear interpolation of samples 4 per ``min_wavelength_m`` apart is
accurate to the band: ``min_wavelength_m >= 4 v_max / fs`` already.

Magnets are combined by averaging on the common grid; ``std_m`` is the standard error of that
mean from the spread between magnets (NaN where fewer than two magnets cover a point); agreement
between magnets is reported as pairwise correlation of their band-passed profiles. Where the set of
magnets covering a point changes (the ends of each magnet's stretch: the rear magnet starts its
stretch one vehicle length later) each magnet's weight ramps in and out over a quarter of the
longest wavelength (raised cosine, :func:`_coverage_weights`; ``blend_coverage``, on by default): the plain mean
jumped there by half
the magnets' long-wave difference (240 um at 20 m behind the start of the stretch, on a simulated
pass), and every twin magnet crossing that step drew a 3 A current spike.

Streaming: :class:`IncrementalProfiler` processes overlapping time windows as blocks arrive, keeps
only the window (bounded memory for the signals) and accumulates per-magnet bin sums; its
``result()`` band-passes the accumulated grid.

Why by hand: the method is a short composition of numpy/scipy pieces (FFT, sosfiltfilt,
bincount); no maintained library implements the inertial reference method.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
import warnings as _w
from typing import Callable, Sequence

import numpy as np
from scipy import signal

from maglev_ros.errors import UserError
from maglev_ros.irregularity.integration import (
    DEFAULT_FILTER_ORDER, DataWarning, detect_dropouts, double_integrate, _runs)

__all__ = ["InertialProfiler", "IncrementalProfiler", "IrregularityResult", "CornerChoice",
           "auto_highpass_hz", "settle_periods", "band_filter_sos"]

EDGE_PER_CORNER = 0.6          # edge_s * f_c: just longer than the integrator's 0.5/f_c taper
MIN_HIGHPASS_HZ = 0.2          # noise floor of the automatic corner (module docstring)


def _nan_list(a) -> list:
    a = np.asarray(a, dtype=float)
    return [None if not math.isfinite(v) else float(v) for v in a.tolist()]


def band_filter_sos(min_wavelength_m: float, max_wavelength_m: float, spacing_m: float,
                    order: int = DEFAULT_FILTER_ORDER) -> np.ndarray:
    """The spatial band-pass of the result: Butterworth band-pass in wavenumber, SOS form
    (apply with ``scipy.signal.sosfiltfilt``)."""
    return signal.butter(order, [1.0 / max_wavelength_m, 1.0 / min_wavelength_m], btype="band",
                         fs=1.0 / spacing_m, output="sos")


def settle_periods(band_factor: float = 2.0, trim_wavelengths: float = 1.0,
                   edge_per_corner: float = EDGE_PER_CORNER) -> float:
    """Settling time of one clean stretch in periods of the corner (x 1/f_c): two integrator edges
    plus two band-pass trims (one longest wave, ``1/(band_factor f_c)`` s, per
    ``trim_wavelengths``)."""
    return 2.0 * edge_per_corner + 2.0 * trim_wavelengths / band_factor


def auto_highpass_hz(usable_s: float, band_factor: float = 2.0, trim_wavelengths: float = 1.0,
                     edge_per_corner: float = EDGE_PER_CORNER, settle_fraction: float = 0.5,
                     min_highpass_hz: float = MIN_HIGHPASS_HZ) -> float:
    """Time high-pass corner for a clean moving stretch of ``usable_s`` seconds: the lowest at
    which the filters' settling takes at most ``settle_fraction`` of it, never below
    ``min_highpass_hz``."""
    if not (usable_s > 0 and math.isfinite(usable_s)):
        raise UserError(f"usable stretch: expected > 0 s of clean moving data, got {usable_s:g} s")
    # settling = periods / f_c must fit in settle_fraction of the stretch
    periods = settle_periods(band_factor, trim_wavelengths, edge_per_corner)
    fc = periods / (settle_fraction * usable_s)
    # the integrator itself needs 2 edges + 2/f_c per stretch (integration.double_integrate)
    fc = max(fc, 1.01 * (2.0 * edge_per_corner + 2.0) / usable_s)
    return max(fc, float(min_highpass_hz))


@dataclass(frozen=True)
class CornerChoice:
    """How the time high-pass corner was set: ``rule`` "given" (by the caller), "auto"
    (:func:`auto_highpass_hz` from the longest clean moving stretch ``usable_s``) or "floor" (a
    stream of unknown length: the automatic corner's noise floor)."""
    highpass_hz: float
    rule: str
    usable_s: float | None = None
    settle_s: float | None = None               # filter settling per stretch at this corner
    settle_fraction: float | None = None
    min_highpass_hz: float | None = None

    def describe(self) -> str:
        if self.rule == "given":
            return f"{self.highpass_hz:.3g} Hz (given)"
        if self.rule == "floor":
            return f"{self.highpass_hz:.3g} Hz (noise floor; stream length unknown)"
        floor = (f", raised to the {self.min_highpass_hz:g} Hz noise floor"
                 if self.highpass_hz <= self.min_highpass_hz * (1 + 1e-9) else "")
        return (f"{self.highpass_hz:.3g} Hz (auto: filter settling {self.settle_s:.3g} s of the "
                f"{self.usable_s:.3g} s clean moving stretch, at most {self.settle_fraction:.0%}"
                f"{floor})")

    def to_dict(self) -> dict:
        return {"highpass_hz": self.highpass_hz, "rule": self.rule, "usable_s": self.usable_s,
                "settle_s": self.settle_s, "settle_fraction": self.settle_fraction,
                "min_highpass_hz": self.min_highpass_hz, "text": self.describe()}


@dataclass(frozen=True, eq=False)
class IrregularityResult:
    """Irregularity profile on a regular position grid; NaN where nothing valid was measured."""
    position_m: np.ndarray
    irregularity_m: np.ndarray
    std_m: np.ndarray
    n_magnets: np.ndarray                       # magnets contributing at each point
    magnet_profiles_m: np.ndarray               # (n_used_magnets, n_points)
    magnet_names: tuple[str, ...]
    magnet_offsets_m: tuple[float, ...]
    spacing_m: float
    min_wavelength_m: float
    max_wavelength_m: float
    highpass_hz: float
    filter_order: int
    band_speed_mps: float
    kind: str                                   # "loaded" | "unloaded"
    agreement: tuple[tuple[str, str, float], ...]
    bias_mps2: tuple[float, ...]
    warnings: tuple[DataWarning, ...] = field(default_factory=tuple)
    corner: CornerChoice | None = None

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.irregularity_m)

    def band(self) -> dict:
        return {"min_wavelength_m": self.min_wavelength_m,
                "max_wavelength_m": self.max_wavelength_m,
                "highpass_hz": self.highpass_hz, "band_speed_mps": self.band_speed_mps}

    def band_filter(self) -> dict:
        return {"type": "butterworth_bandpass_zero_phase", "order": self.filter_order,
                "applied": "sosfiltfilt (forward-backward) in wavenumber",
                "low_cut_cycles_per_m": 1.0 / self.max_wavelength_m,
                "high_cut_cycles_per_m": 1.0 / self.min_wavelength_m,
                "time_highpass": {"corner_hz": self.highpass_hz,
                                  "gain": f"(f/fc)^{2 * self.filter_order} / "
                                          f"(1 + (f/fc)^{2 * self.filter_order})"}}

    def to_dict(self, include_profile: bool = True) -> dict:
        v = self.valid
        d = {
            "kind": self.kind, "spacing_m": self.spacing_m, **self.band(),
            "band_filter": self.band_filter(),
            "corner": (self.corner or CornerChoice(self.highpass_hz, "given")).to_dict(),
            "magnets": [{"name": n, "offset_m": o, "bias_mps2": b}
                        for n, o, b in zip(self.magnet_names, self.magnet_offsets_m,
                                           self.bias_mps2)],
            "agreement": [{"a": a, "b": b, "correlation": c} for a, b, c in self.agreement],
            "n_points": int(self.position_m.size), "n_valid": int(v.sum()),
            "rms_m": float(np.sqrt(np.mean(self.irregularity_m[v] ** 2))) if v.any() else None,
            "warnings": [w.to_dict() for w in self.warnings],
        }
        if include_profile:
            d["position_m"] = _nan_list(self.position_m)
            d["irregularity_m"] = _nan_list(self.irregularity_m)
            d["std_m"] = _nan_list(self.std_m)
        return d


def _channel(cd, name: str, what: str) -> np.ndarray:
    chans = tuple(cd.channels)
    if name not in chans:
        raise UserError(f"{what}: channel '{name}' not found (channels: {', '.join(chans)})")
    return np.asarray(cd.data, dtype=float)[:, chans.index(name)]


def _rate(cd) -> float:
    fs = getattr(cd, "sample_rate_hz", None)
    if fs:
        return float(fs)
    t = np.asarray(cd.time_s, float)
    return float(1.0 / np.median(np.diff(t)))


@dataclass
class _MagnetSpec:
    name: str
    accel_channel: str
    gap_channel: str
    offset_m: float
    index: int


class InertialProfiler:
    """Inertial reference method, batch form.

    Parameters
    ----------
    highpass_hz : corner f_c of the time-domain high-pass [Hz]; None (default): chosen per
        recording by :func:`auto_highpass_hz` (see the module docstring), stated in the result.
    spacing_m : position grid spacing [m] (0.25 m, the EN 13848 sampling distance).
    magnets : 1-based magnet numbers to use (default: all).
    magnet_length_m : shortest trusted wavelength from a sensor that averages over a length
        (default 0: point gap sensors and accelerometers; see module docstring).
    band_factor : ``max_wavelength_m = band_speed / (band_factor * f_c)``.
    band_speed_mps, max_wavelength_m : fix the band instead of deriving it from the speed
        (``max_wavelength_m`` sets ``band_speed = band_factor * f_c * max_wavelength_m``).
    stop_speed_mps : samples slower than this are never mapped to positions.
    filter_order : Butterworth order of the time and spatial filters.
    edge_s : seconds dropped at both ends of each clean segment (default 0.6/f_c, just
        longer than the 0.5/f_c taper).
    trim_wavelengths : profile dropped at both ends of each spatial stretch, in units of
        ``max_wavelength_m`` (the band-pass's edge transient decays over about that length).
    blend_coverage : ramp each magnet's weight in and out where the set of magnets covering a
        point changes (see the module notes); False gives the plain mean (for comparison only).
    settle_fraction, min_highpass_hz : the automatic corner's share of each stretch given to
        filter settling and its noise floor (used only when ``highpass_hz`` is None).
    """

    def __init__(self, highpass_hz: float | None = None, spacing_m: float = 0.25,
                 magnets: Sequence[int] | None = None, magnet_length_m: float = 0.0,
                 band_factor: float = 2.0, band_speed_mps: float | None = None,
                 max_wavelength_m: float | None = None, min_wavelength_m: float | None = None,
                 stop_speed_mps: float = 1.0, filter_order: int = DEFAULT_FILTER_ORDER,
                 edge_s: float | None = None, speed_percentile: float = 5.0,
                 bias_sigma: float = 5.0, bias_floor_mps2: float = 2e-3,
                 trim_wavelengths: float = 1.0, blend_coverage: bool = True,
                 settle_fraction: float = 0.5, min_highpass_hz: float = MIN_HIGHPASS_HZ):
        if highpass_hz is not None and not highpass_hz > 0:
            raise UserError(f"highpass_hz: expected > 0 Hz, got {highpass_hz}")
        if not spacing_m > 0:
            raise UserError(f"spacing_m: expected > 0 m, got {spacing_m}")
        if not 0 < settle_fraction < 1:
            raise UserError(f"settle_fraction: expected between 0 and 1, got {settle_fraction}")
        self.highpass_hz = None if highpass_hz is None else float(highpass_hz)
        self.spacing_m = float(spacing_m)
        self.magnets = None if magnets is None else [int(m) for m in magnets]
        self.magnet_length_m = float(magnet_length_m)
        self.band_factor = float(band_factor)
        self.band_speed_mps = band_speed_mps
        self.max_wavelength_m = max_wavelength_m
        self.min_wavelength_m = min_wavelength_m
        self.stop_speed_mps = float(stop_speed_mps)
        self.filter_order = int(filter_order)
        self.edge_s_given = None if edge_s is None else float(edge_s)
        self.edge_s = (None if self.highpass_hz is None else
                       EDGE_PER_CORNER / self.highpass_hz if edge_s is None else float(edge_s))
        self.speed_percentile = float(speed_percentile)
        self.bias_sigma = float(bias_sigma)
        self.bias_floor_mps2 = float(bias_floor_mps2)
        self.trim_wavelengths = float(trim_wavelengths)
        self.blend_coverage = bool(blend_coverage)
        self.settle_fraction = float(settle_fraction)
        self.min_highpass_hz = float(min_highpass_hz)
        self.corner = None if self.highpass_hz is None else CornerChoice(self.highpass_hz, "given")

    # -- the corner ------------------------------------------------------------------------
    def corner_for(self, usable_s: float) -> CornerChoice:
        """The automatic corner for a clean moving stretch of ``usable_s`` seconds."""
        if self.edge_s_given is None:
            fc = auto_highpass_hz(usable_s, self.band_factor, self.trim_wavelengths,
                                  EDGE_PER_CORNER, self.settle_fraction, self.min_highpass_hz)
        else:
            # fixed edges: settling = 2 edge_s + trims/f_c must fit in the stretch's share
            room_s = self.settle_fraction * usable_s - 2.0 * self.edge_s_given
            if not room_s > 0:
                raise UserError(f"edge_s: {self.edge_s_given:g} s at both ends leaves nothing of "
                                f"the {usable_s:.3g} s clean moving stretch")
            fc = max(2.0 * self.trim_wavelengths / self.band_factor / room_s,
                     1.01 * 2.0 / (usable_s - 2.0 * self.edge_s_given), self.min_highpass_hz)
        edge = EDGE_PER_CORNER / fc if self.edge_s_given is None else self.edge_s_given
        settle = 2.0 * edge + 2.0 * self.trim_wavelengths / (self.band_factor * fc)
        return CornerChoice(float(fc), "auto", float(usable_s), float(settle),
                            self.settle_fraction, self.min_highpass_hz)

    def with_corner(self, corner: CornerChoice) -> "InertialProfiler":
        """A copy of this profiler with its time high-pass fixed at ``corner``."""
        import copy
        c = copy.copy(self)
        c.highpass_hz = float(corner.highpass_hz)
        c.edge_s = (EDGE_PER_CORNER / c.highpass_hz if self.edge_s_given is None
                    else self.edge_s_given)
        c.corner = corner
        return c

    def usable_s(self, accel, gap, position, magnet_offsets_m, channel_pairs=None) -> float:
        """Longest stretch [s] over which some magnet's accel and gap are clean (no dropout) and
        the vehicle moves faster than ``stop_speed_mps``: what the filters have to work with."""
        specs = self._specs(accel, gap, magnet_offsets_m, channel_pairs)
        t, fs, _, v, tg, same = self._timebase(accel, gap, position)
        moving = np.isfinite(v) & (v >= self.stop_speed_mps)
        best = 0
        for spec in specs:
            a = _channel(accel, spec.accel_channel, "/testline/vehicle/accel")
            g = self._gap_on(t, tg, same, _channel(gap, spec.gap_channel, "/testline/vehicle/gap"))
            abad, _ = detect_dropouts(t, a, fs, spec.accel_channel)
            gbad, _ = detect_dropouts(t, g, fs, spec.gap_channel)
            for i0, i1 in _runs(moving & ~abad & ~gbad):
                best = max(best, i1 - i0)
        if best == 0:
            raise UserError("/testline/vehicle/position: no clean stretch where the vehicle moves "
                            f"faster than stop_speed_mps={self.stop_speed_mps:g} m/s")
        return best / fs

    def resolve(self, accel, gap, position, magnet_offsets_m,
                channel_pairs=None) -> "InertialProfiler":
        """This profiler with its corner fixed for the recording (itself when it is given)."""
        if self.highpass_hz is not None:
            return self
        return self.with_corner(self.corner_for(
            self.usable_s(accel, gap, position, magnet_offsets_m, channel_pairs)))

    # -- configuration helpers -------------------------------------------------------------
    def _specs(self, accel, gap, magnet_offsets_m, channel_pairs) -> list[_MagnetSpec]:
        offs = [float(o) for o in magnet_offsets_m]
        if channel_pairs is None:
            na, ng = len(accel.channels), len(gap.channels)
            n = min(na, ng, len(offs))
            if n == 0:
                raise UserError("vehicle accel/gap: no magnet channels to pair "
                                f"(accel {na}, gap {ng}, magnet_offsets_m {len(offs)})")
            channel_pairs = {k + 1: (accel.channels[k], gap.channels[k]) for k in range(n)}
        specs = []
        for mag, (ca, cg) in sorted(channel_pairs.items()):
            if self.magnets is not None and mag not in self.magnets:
                continue
            if not 1 <= mag <= len(offs):
                raise UserError(f"vehicle.magnet_offsets_m: no offset for magnet {mag} "
                                f"({len(offs)} offsets given)")
            specs.append(_MagnetSpec(f"M{mag}", ca, cg, offs[mag - 1], mag))
        if not specs:
            raise UserError(f"magnets: none of {self.magnets} has accel and gap channels")
        return specs

    def _band(self, speed_kept: np.ndarray, step_m: np.ndarray, fs_hz: float) -> tuple[float, float, float]:
        fc = self.highpass_hz
        if self.max_wavelength_m is not None:
            v_band = self.band_factor * fc * float(self.max_wavelength_m)
        elif self.band_speed_mps is not None:
            v_band = float(self.band_speed_mps)
        else:
            if speed_kept.size == 0:
                raise UserError("/testline/vehicle/position: vehicle never moves faster than "
                                f"stop_speed_mps={self.stop_speed_mps}")
            order = np.argsort(speed_kept)
            cum = np.cumsum(step_m[order])
            i = np.searchsorted(cum, cum[-1] * self.speed_percentile / 100.0)
            v_band = float(speed_kept[order][min(i, order.size - 1)])
        v_band = max(v_band, self.stop_speed_mps)
        v_max = float(speed_kept.max()) if speed_kept.size else v_band
        return v_band, self.shortest_wavelength_m(v_max, fs_hz), self.longest_wavelength_m(v_band)

    def slow_speed_mps(self, band_speed_mps: float) -> float:
        """Slowest speed whose samples are kept: there the time high-pass still passes 99 % of the
        longest stated wave (0.89 x the band speed at band_factor 2, order 4). Below band factor 2
        the longest wave is already attenuated at the band speed itself and the rule would keep
        nothing slower than it (a pass whose speed wanders by 0.5 % lost 5 % of its distance in
        holes and fell apart into pieces too short for the band-pass): slow is then judged as at
        band factor 2."""
        return band_speed_mps * min(1.0, 99.0 ** (1.0 / (2 * self.filter_order)) / max(self.band_factor, 2.0))

    def longest_wavelength_m(self, band_speed_mps: float) -> float:
        """Longest trusted wave: the time high-pass passes > 0.996 of it at ``band_factor`` 2."""
        return band_speed_mps / (self.band_factor * self.highpass_hz)

    def shortest_wavelength_m(self, max_speed_mps: float, fs_hz: float) -> float:
        """Shortest trusted wave: 4 grid steps, 4 sample steps at the top speed, or the stated
        sensor length / minimum when longer."""
        lam = max(self.magnet_length_m, 4 * self.spacing_m, 4 * max_speed_mps / fs_hz)
        return lam if self.min_wavelength_m is None else max(lam, float(self.min_wavelength_m))

    # -- time domain -> samples at positions -------------------------------------------------
    def _magnet_samples(self, t, a, g, xref, spd, spec, g0, fs, defl_k, segment_means=None, report_bias=True):
        """Return (x_m, r_m, warnings, bias) for the valid samples of one magnet (time order)."""
        warns = []
        gbad, gw = detect_dropouts(t, g, fs, spec.gap_channel)
        warns += gw
        dg = g - g0
        if defl_k is not None:
            dg = dg - defl_k
        res = double_integrate(t, a, fs, self.highpass_hz, order=self.filter_order,
                               edge_s=self.edge_s, bad=gbad, channel=spec.accel_channel,
                               bias_sigma=self.bias_sigma, bias_floor_mps2=self.bias_floor_mps2,
                               plus_highpassed=np.where(gbad, np.nan, dg),
                               segment_means=segment_means, report_bias=report_bias)
        warns += list(res.warnings)
        r = res.displacement_m
        x = xref + spec.offset_m
        return x, r, warns, (float(np.mean(res.bias_mps2)) if res.bias_mps2 else 0.0)

    def _timebase(self, accel, gap, position):
        t = np.asarray(accel.time_s, float)
        if t.size < 4:
            raise UserError("/testline/vehicle/accel: fewer than 4 samples")
        fs = _rate(accel)
        xref, v = self.reference_motion(t, position)
        tg = np.asarray(gap.time_s, float)
        same = tg.size == t.size and np.allclose(tg, t, atol=0.25 / fs)
        return t, fs, xref, v, tg, same

    def reference_motion(self, t, position):
        """(x, |speed|) of the reference point at times ``t`` from the position channels; speed
        NaN where ``t`` is more than 1.5 position samples outside the position record."""
        tp = np.asarray(position.time_s, float)
        pos = _channel(position, "position_m", "/testline/vehicle/position")
        spd = _channel(position, "speed_mps", "/testline/vehicle/position")
        ok = np.isfinite(pos) & np.isfinite(spd)
        if ok.sum() < 2:
            raise UserError("/testline/vehicle/position: fewer than 2 finite samples")
        tp, pos, spd = tp[ok], pos[ok], spd[ok]
        dtp = float(np.median(np.diff(tp))) if tp.size > 1 else 0.0
        outside = (t < tp[0] - 1.5 * dtp) | (t > tp[-1] + 1.5 * dtp)
        # linear extrapolation over at most 1.5 position samples (the last accel samples of a
        # block usually lie after the last position sample); beyond that: no position
        xref = np.interp(t, tp, pos)
        v = np.abs(np.interp(t, tp, spd))
        xref = xref + np.where(t > tp[-1], (t - tp[-1]) * spd[-1], 0.0) \
            + np.where(t < tp[0], (t - tp[0]) * spd[0], 0.0)
        v[outside] = np.nan              # never map samples without a position
        return xref, v

    def _gap_on(self, t, tg, same, gcol, step_s=None, span_s=None):
        """The gap channel at the accel times ``t``. ``step_s`` (the gap's median sample step)
        and ``span_s`` (its first and last time) default to those of ``tg``: a caller holding a
        piece of the gap record gives the whole record's."""
        if same:
            return gcol
        gi = np.interp(t, tg, gcol)
        # mark samples whose nearest gap samples are far away (gap dropout in time)
        j = np.clip(np.searchsorted(tg, t), 1, tg.size - 1)
        dist = np.minimum(np.abs(tg[j] - t), np.abs(t - tg[j - 1]))
        fsg = 1.0 / (np.median(np.diff(tg)) if step_s is None else step_s)
        gi[dist > 1.5 / fsg] = np.nan
        lo, hi = (tg[0], tg[-1]) if span_s is None else span_s
        gi[(t < lo) | (t > hi)] = np.nan
        return gi

    def _deflection(self, deflection, t, xm, spec, k):
        if deflection is None:
            return None
        if callable(deflection):
            w = np.asarray(deflection(t, xm, spec.index), float)
        else:
            arr = np.asarray(deflection, float)
            if arr.ndim == 1:
                arr = arr[:, None]
            if arr.shape[0] != t.size:
                raise UserError(f"deflection: expected {t.size} rows (one per accel sample), "
                                f"got {arr.shape[0]}")
            w = arr[:, k if arr.shape[1] > 1 else 0]
        if w.shape != t.shape:
            raise UserError(f"deflection: expected shape {t.shape} for magnet {spec.index}, "
                            f"got {w.shape}")
        return w

    def band_speed_series(self, speed_mps: np.ndarray, fs_hz: float) -> np.ndarray:
        """Speed averaged over 1/f_c (centred): the high-pass acts on the mean speed over its own
        time scale, not on the speed channel's noise, so noise must not drop samples as slow.
        Below ``stop_speed_mps`` the raw speed stays, so a stop never maps."""
        v = np.asarray(speed_mps, float)
        n = max(1, int(round(fs_hz / self.highpass_hz)))
        if n <= 1 or v.size < 3:
            return v
        ok = np.isfinite(v)
        csum = np.concatenate([[0.0], np.cumsum(np.where(ok, v, 0.0))])
        ccnt = np.concatenate([[0], np.cumsum(ok)])
        i = np.arange(v.size)
        lo, hi = np.clip(i - n // 2, 0, v.size), np.clip(i + n - n // 2, 0, v.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            vs = (csum[hi] - csum[lo]) / (ccnt[hi] - ccnt[lo])
        vs = np.where(ok, vs, np.nan)
        return np.where(v < self.stop_speed_mps, v, vs)

    def samples(self, accel, gap, position, magnet_offsets_m, nominal_gap_m,
                deflection=None, channel_pairs=None, segment_means=None, report_bias: bool = True):
        """Per-magnet position samples before binning (used by fit and the streaming class).

        Returns (specs, list of (x_m, r_m, speed_mps) per magnet, warnings, biases, fs); the speed
        is the one the band is judged by (:meth:`band_speed_series`). Needs a fixed corner (see
        :meth:`resolve`). ``segment_means``: per magnet, the ``segment_means`` hook of
        :func:`~maglev_ros.irregularity.integration.double_integrate` (a piece of a record);
        ``report_bias`` False: no accelerometer-bias warnings (for callers that discard them)."""
        if self.highpass_hz is None:
            raise UserError("highpass_hz: samples() needs a fixed corner (resolve() sets it)")
        specs = self._specs(accel, gap, magnet_offsets_m, channel_pairs)
        t, fs, xref, v_raw, tg, same = self._timebase(accel, gap, position)
        v = self.band_speed_series(v_raw, fs)
        out, warns, biases = [], [], []
        for k, spec in enumerate(specs):
            a = _channel(accel, spec.accel_channel, "/testline/vehicle/accel")
            g = self._gap_on(t, tg, same, _channel(gap, spec.gap_channel, "/testline/vehicle/gap"))
            w = self._deflection(deflection, t, xref + spec.offset_m, spec, k)
            x, r, wk, b = self._magnet_samples(t, a, g, xref, v, spec, float(nominal_gap_m), fs, w,
                                               None if segment_means is None else segment_means[k],
                                               report_bias)
            out.append((x, r, v))
            warns += wk
            biases.append(b)
        return specs, out, warns, biases, fs, t

    def fit(self, accel, gap, position, magnet_offsets_m: Sequence[float],
            nominal_gap_m: float = 0.010,
            deflection: Callable | np.ndarray | None = None,
            channel_pairs: dict | None = None) -> IrregularityResult:
        """Profile from whole-pass channel data (ChannelData-like: time_s, data, channels).

        ``position`` has channels ``position_m`` and ``speed_mps`` of the reference point.
        ``magnet_offsets_m[k-1]`` is the x of magnet k relative to it. ``channel_pairs`` maps a
        1-based magnet number to (accel channel, gap channel); default: k-th channels pair with
        magnet k. ``deflection`` is the twin's predicted girder deflection under each magnet
        (up positive): a callable ``f(time_s, x_m, magnet) -> array`` or an array
        (n_accel_samples, n_magnets); when given, the result is the unloaded profile.
        """
        if self.highpass_hz is None:
            return self.resolve(accel, gap, position, magnet_offsets_m, channel_pairs).fit(
                accel, gap, position, magnet_offsets_m, nominal_gap_m, deflection, channel_pairs)
        specs, samp, warns, biases, fs, t = self.samples(
            accel, gap, position, magnet_offsets_m, nominal_gap_m, deflection, channel_pairs)
        v = samp[0][2]
        moving = v >= self.stop_speed_mps
        dt = 1.0 / fs
        v_band, lam_min, lam_max = self._band(v[moving], v[moving] * dt, fs)
        acc = _BinAccumulator(self.spacing_m)
        for k, (x, r, vv) in enumerate(samp):
            keep = np.isfinite(r) & (vv >= self.slow_speed_mps(v_band))
            acc.add(k, x[keep], r[keep])
        warns += _slow_warnings(t, v, self.slow_speed_mps(v_band), self.stop_speed_mps, dt)
        nopos = ~np.isfinite(v)
        if nopos.any():
            warns.append(DataWarning(
                "position_coverage", "/testline/vehicle/position",
                f"{int(nopos.sum())} accel samples lie outside the position record; not mapped",
                float(t[nopos][0]), float(t[nopos][-1])))
        v_mov = v[moving & np.isfinite(v)]
        step_m = float(v_mov.max()) / fs if v_mov.size else 0.0
        return _finish(acc, specs, warns, biases, self, v_band, lam_min, lam_max,
                       kind="unloaded" if deflection is not None else "loaded",
                       sample_step_m=step_m)


def _slow_warnings(t, v, slow_mps, stop, dt) -> list[DataWarning]:
    slow = v < slow_mps
    if not slow.any():
        return []
    out = []
    for i0, i1 in _runs(slow):
        if i1 - i0 < 2:
            continue
        dist = float(np.sum(v[i0:i1]) * dt)
        out.append(DataWarning(
            "slow_section", "/testline/vehicle/position",
            f"speed below {slow_mps:.3g} m/s (the band's slowest) for {(i1 - i0) * dt:.3g} s "
            f"({dist:.3g} m travelled, stops below {stop:g} m/s); those positions are dropped",
            float(t[i0]), float(t[i1 - 1]), dist))
    return out


class _BinAccumulator:
    """Per-magnet sums and counts on a global grid x_j = j * spacing (grows as needed)."""

    def __init__(self, spacing_m: float, max_points: int | None = None):
        self.dx = spacing_m
        self.j0 = None
        self.sum: dict[int, np.ndarray] = {}
        self.cnt: dict[int, np.ndarray] = {}
        self.n = 0
        self.max_points = max_points

    def _grow(self, jmin, jmax):
        if self.j0 is None:
            self.j0, self.n = jmin, jmax - jmin + 1
            for k in self.sum:
                self.sum[k] = np.zeros(self.n)
                self.cnt[k] = np.zeros(self.n)
            return
        lo = min(jmin, self.j0)
        hi = max(jmax, self.j0 + self.n - 1)
        if lo == self.j0 and hi == self.j0 + self.n - 1:
            return
        n2 = hi - lo + 1
        s = self.j0 - lo
        for k in list(self.sum):
            a = np.zeros(n2)
            a[s:s + self.n] = self.sum[k]
            c = np.zeros(n2)
            c[s:s + self.n] = self.cnt[k]
            self.sum[k], self.cnt[k] = a, c
        self.j0, self.n = lo, n2

    def add(self, k, x, r):
        if k not in self.sum:
            self.sum[k] = np.zeros(self.n)
            self.cnt[k] = np.zeros(self.n)
        if x.size == 0:
            return
        j = np.rint(x / self.dx).astype(np.int64)
        self._grow(int(j.min()), int(j.max()))
        idx = j - self.j0
        self.sum[k] += np.bincount(idx, weights=r, minlength=self.n)
        self.cnt[k] += np.bincount(idx, minlength=self.n)
        if self.max_points is not None and self.n > self.max_points:
            cut = self.n - self.max_points
            for kk in self.sum:
                self.sum[kk] = self.sum[kk][cut:]
                self.cnt[kk] = self.cnt[kk][cut:]
            self.j0 += cut
            self.n -= cut

    def mean(self, k) -> np.ndarray:
        c = self.cnt.get(k, np.zeros(self.n))
        with np.errstate(invalid="ignore", divide="ignore"):
            m = self.sum.get(k, np.zeros(self.n)) / c
        m[c == 0] = np.nan
        return m


def _fill_small_holes(y: np.ndarray, max_hole: int = 2) -> np.ndarray:
    y = y.copy()
    bad = ~np.isfinite(y)
    if not bad.any() or bad.all():
        return y
    idx = np.arange(y.size)
    for i0, i1 in _runs(bad):
        if i1 - i0 <= max_hole and i0 > 0 and i1 < y.size:
            y[i0:i1] = np.interp(idx[i0:i1], [i0 - 1, i1], [y[i0 - 1], y[i1]])
    return y


def _bandpass_segments(y, sos, min_len, trim) -> tuple[np.ndarray, int]:
    out = np.full(y.shape, np.nan)
    dropped = 0
    for i0, i1 in _runs(np.isfinite(y)):
        if i1 - i0 < max(min_len, 2 * trim + 8):
            dropped += i1 - i0
            continue
        seg = y[i0:i1]
        f = signal.sosfiltfilt(sos, seg - seg.mean(), padtype="odd",
                               padlen=min(max(2 * trim, 3 * (2 * sos.shape[0] + 1)), seg.size - 1))
        if trim:
            f[:trim] = np.nan
            f[-trim:] = np.nan
        out[i0:i1] = f
    return out, dropped


def _max_hole_bins(sample_step_m: float, spacing_m: float) -> int:
    """Longest run of empty grid bins that is only the sample step, not missing data."""
    if not (sample_step_m > 0 and math.isfinite(sample_step_m)):
        return 2
    return max(2, int(math.ceil(sample_step_m / spacing_m)) + 1)


def _coverage_weights(finite: np.ndarray, ramp_bins: int) -> np.ndarray:
    """Per magnet (rows) and grid point: 0 where it has no profile, else a raised-cosine ramp from
    each end of each of its stretches over ``ramp_bins`` (at most half the stretch), 1 inside.
    Strictly positive wherever the magnet covers, so a point covered by one magnet only is that
    magnet's profile."""
    W = np.zeros(finite.shape)
    for k in range(finite.shape[0]):
        for i0, i1 in _runs(finite[k]):
            n = i1 - i0
            m = max(1, min(ramp_bins, n // 2))
            j = np.arange(n)
            d = np.minimum(j, n - 1 - j) + 0.5           # distance from the nearer end, in bins
            W[k, i0:i1] = np.where(d < m, 0.5 - 0.5 * np.cos(np.pi * np.minimum(d / m, 1.0)), 1.0)
    return W


def _finish(acc: _BinAccumulator, specs, warns, biases, cfg, v_band, lam_min, lam_max,
            kind, sample_step_m: float = 0.0) -> IrregularityResult:
    dx = cfg.spacing_m
    if acc.j0 is None or acc.n == 0:
        fc = cfg.highpass_hz
        raise UserError("vehicle recording: no valid magnet samples left (dropouts, stops or "
                        f"clean stretches shorter than the ~{2 * cfg.edge_s + 2 / fc:.0f} s that a "
                        f"{fc:.3g} Hz high-pass needs; a higher --highpass-hz shortens it)")
    pos = (acc.j0 + np.arange(acc.n)) * dx
    warns = list(warns)
    if lam_max <= lam_min * 1.5:
        warns.append(DataWarning(
            "band", "", f"valid band {lam_min:.3g}-{lam_max:.3g} m is empty or too narrow: "
            f"speed {v_band:.3g} m/s is too slow for f_c={cfg.highpass_hz:g} Hz"))
        lam_max = lam_min * 1.5
    sos = band_filter_sos(lam_min, lam_max, dx, cfg.filter_order)
    trim = int(round(cfg.trim_wavelengths * lam_max / dx))
    min_len = int(math.ceil(2 * lam_max / dx))
    profs = []
    for k, _ in enumerate(specs):
        y = _fill_small_holes(acc.mean(k), _max_hole_bins(sample_step_m, dx))
        f, dropped = _bandpass_segments(y, sos, min_len, trim)
        if dropped:
            warns.append(DataWarning(
                "short_segment", specs[k].name,
                f"{specs[k].name}: {dropped * dx:.3g} m of profile in stretches shorter than "
                f"{min_len * dx:.3g} m (2 x max wavelength) left out"))
        profs.append(f)
    P = np.vstack(profs)
    nmag = np.sum(np.isfinite(P), axis=0)
    W = (_coverage_weights(np.isfinite(P), max(1, int(round(0.25 * lam_max / dx))))
         if cfg.blend_coverage else np.isfinite(P).astype(float))
    with _w.catch_warnings():
        _w.simplefilter("ignore", RuntimeWarning)
        mean = np.sum(W * np.nan_to_num(P), axis=0) / np.sum(W, axis=0)
        sd = np.nanstd(P, axis=0, ddof=1)
    se = np.where(nmag >= 2, sd / np.sqrt(np.maximum(nmag, 1)), np.nan)
    mean[nmag == 0] = np.nan
    agree = []
    for i in range(len(specs)):
        for j in range(i + 1, len(specs)):
            m = np.isfinite(P[i]) & np.isfinite(P[j])
            if m.sum() > 10 and np.std(P[i][m]) > 0 and np.std(P[j][m]) > 0:
                c = float(np.corrcoef(P[i][m], P[j][m])[0, 1])
            else:
                c = float("nan")
            agree.append((specs[i].name, specs[j].name, c))
    # de-duplicate repeated warnings (streaming windows) by (kind, channel, message)
    seen, uniq = set(), []
    for w in warns:
        key = (w.kind, w.channel, w.message)
        if key not in seen:
            seen.add(key)
            uniq.append(w)
    return IrregularityResult(
        position_m=pos, irregularity_m=mean, std_m=se, n_magnets=nmag, magnet_profiles_m=P,
        magnet_names=tuple(s.name for s in specs),
        magnet_offsets_m=tuple(s.offset_m for s in specs), spacing_m=dx,
        min_wavelength_m=float(lam_min), max_wavelength_m=float(lam_max),
        highpass_hz=cfg.highpass_hz, filter_order=cfg.filter_order, band_speed_mps=float(v_band),
        kind=kind, agreement=tuple(agree), bias_mps2=tuple(biases), warnings=tuple(uniq),
        corner=cfg.corner)


class _Stream:
    """Time-ordered buffer of one topic's blocks (time_s, data) with channel names. Blocks are kept
    as a list and joined only when read (``t``/``d``): appending one block per message to a
    30-60 s buffer by concatenation copied the whole buffer every block."""

    def __init__(self):
        self._t = [np.zeros(0)]
        self._d: list = []
        self.channels = None
        self.fs = None
        self._last = -math.inf
        self._first = None

    def _join(self):
        if len(self._t) > 1:
            self._t = [np.concatenate(self._t)]
            self._d = [np.vstack(self._d)]

    @property
    def t(self) -> np.ndarray:
        self._join()
        return self._t[0]

    @property
    def d(self):
        if self.channels is None:
            return None
        self._join()
        return self._d[0]

    def append(self, cd, what: str):
        t = np.asarray(cd.time_s, float)
        d = np.asarray(cd.data, float)
        if d.ndim == 1:
            d = d[:, None]
        ch = tuple(cd.channels)
        if self.channels is None:
            self.channels = ch
            self._d = [np.zeros((0, d.shape[1]))]
        elif ch != self.channels:
            raise UserError(f"{what}: channels changed from {self.channels} to {ch} mid-stream")
        if t.size == 0:
            return
        fs = getattr(cd, "sample_rate_hz", None)
        if fs:
            self.fs = float(fs)
        if t[0] <= self._last:
            keep = t > self._last           # drop repeated / out-of-order samples
            t, d = t[keep], d[keep]
            if t.size == 0:
                return
        self._t.append(t)
        self._d.append(d)
        self._last = float(t[-1])
        if self._first is None:
            self._first = float(t[0])

    @property
    def size(self) -> int:
        return int(sum(x.size for x in self._t))

    def first(self) -> float | None:
        return self._first

    def last(self) -> float:
        return self._last

    def drop_before(self, t0: float):
        t = self.t
        i = int(np.searchsorted(t, t0))
        if i > 0:
            self._t = [t[i:]]
            self._d = [self.d[i:]]
            self._first = float(t[i]) if i < t.size else None

    def view(self):
        from types import SimpleNamespace
        return SimpleNamespace(time_s=self.t, data=self.d, channels=self.channels,
                               sample_rate_hz=self.fs)


class IncrementalProfiler:
    """Streaming inertial profiler for the node: feed blocks with :meth:`partial_fit`, read the
    growing profile with :meth:`result`.

    The band must be fixed up front (``max_wavelength_m``, or ``band_speed_mps`` with default
    4.17 m/s = 15 km/h), and so must the corner: ``highpass_hz``, or, when None, the batch rule
    (:func:`auto_highpass_hz`) for ``expected_pass_s`` seconds of clean moving data, or, without
    it, the rule's noise floor ``min_highpass_hz`` for the windows; until the first window is
    committed (``hop_s + margin_s``, 33 s at 0.2 Hz) the whole stream is still buffered, and
    :meth:`result` then applies the batch rule to it. Either way, with the same corner and band
    speed the batch fit gives the same profile. Signals are processed in overlapping time
    windows: each run covers the buffer from ``margin_s`` before the last committed time to the
    newest sample present on all three topics, and commits samples up to ``margin_s`` before its end
    (``margin_s = edge_s + 2 / f_c``), so every committed sample had at least ``margin_s`` of
    context on both sides, as in the batch fit. Memory: the signal buffers hold at most
    ``2 * margin_s + hop_s`` plus one block; the profile grid grows with distance and is capped
    at ``max_profile_m`` (oldest points dropped) when given.
    """

    def __init__(self, magnet_offsets_m: Sequence[float], nominal_gap_m: float = 0.010,
                 channel_pairs: dict | None = None, hop_s: float | None = None,
                 max_profile_m: float | None = None, band_speed_mps: float | None = None,
                 max_wavelength_m: float | None = None, expected_pass_s: float | None = None,
                 **profiler_kwargs):
        if band_speed_mps is None and max_wavelength_m is None:
            band_speed_mps = 15.0 / 3.6
        cfg = InertialProfiler(band_speed_mps=band_speed_mps,
                               max_wavelength_m=max_wavelength_m, **profiler_kwargs)
        # corner from the buffered stream while nothing is committed (see the class docstring)
        self._rule_cfg = cfg if cfg.highpass_hz is None and expected_pass_s is None else None
        if cfg.highpass_hz is None:
            cfg = cfg.with_corner(
                cfg.corner_for(float(expected_pass_s)) if expected_pass_s is not None
                else CornerChoice(cfg.min_highpass_hz, "floor",
                                  min_highpass_hz=cfg.min_highpass_hz))
        self.cfg = cfg
        self.offsets = [float(o) for o in magnet_offsets_m]
        self.g0 = float(nominal_gap_m)
        self.pairs = channel_pairs
        fc = self.cfg.highpass_hz
        self.margin_s = self.cfg.edge_s + 2.0 / fc
        self.hop_s = 4.0 / fc if hop_s is None else float(hop_s)
        self.acc = _BinAccumulator(self.cfg.spacing_m,
                                   None if max_profile_m is None
                                   else int(max_profile_m / self.cfg.spacing_m))
        self.streams = {"accel": _Stream(), "gap": _Stream(), "position": _Stream()}
        self.t_committed: float | None = None
        self.warnings: list[DataWarning] = []
        self._seen: set = set()
        self.biases: dict[int, list[float]] = {}
        self.specs = None
        self.v_max = 0.0
        self.slow_s = 0.0
        self.slow_m = 0.0
        self.max_buffer_samples = 0

    def partial_fit(self, accel=None, gap=None, position=None) -> "IncrementalProfiler":
        """Add blocks (ChannelData/Block-like: time_s, data, channels) of any of the topics."""
        for name, cd, what in (("accel", accel, "/testline/vehicle/accel"),
                               ("gap", gap, "/testline/vehicle/gap"),
                               ("position", position, "/testline/vehicle/position")):
            if cd is not None:
                if not hasattr(cd, "time_s") and hasattr(cd, "times_s"):
                    from types import SimpleNamespace
                    cd = SimpleNamespace(time_s=cd.times_s(), data=cd.data, channels=cd.channels,
                                         sample_rate_hz=cd.sample_rate_hz)
                self.streams[name].append(cd, what)
        t_avail = min(s.last() for s in self.streams.values())
        t0 = self.streams["accel"].first()
        if t0 is None or not math.isfinite(t_avail):
            return self
        start = self.t_committed if self.t_committed is not None else t0
        if t_avail - start >= self.hop_s + self.margin_s:
            self._process(t_avail - self.margin_s, final=False)
        self.max_buffer_samples = max(self.max_buffer_samples, self.streams["accel"].size)
        return self

    def _process(self, t_commit_end: float, final: bool, acc=None, cfg=None):
        acc = self.acc if acc is None else acc
        cfg = self.cfg if cfg is None else cfg
        s = self.streams
        t_end = min(x.last() for x in s.values())
        a_v, g_v, p_v = s["accel"].view(), s["gap"].view(), s["position"].view()
        sel = a_v.time_s <= t_end
        from types import SimpleNamespace
        a_v = SimpleNamespace(time_s=a_v.time_s[sel], data=a_v.data[sel], channels=a_v.channels,
                              sample_rate_hz=a_v.sample_rate_hz)
        if a_v.time_s.size < 16:
            return
        # the tail processed for a live result is processed again when committed: its warnings then
        specs, samp, warns, biases, fs, t = cfg.samples(
            a_v, g_v, p_v, self.offsets, self.g0, None, self.pairs, report_bias=not final)
        self.specs = specs
        lo = -math.inf if self.t_committed is None else self.t_committed
        hi = math.inf if final else t_commit_end
        win = (t >= lo) & (t < hi)
        v = samp[0][2]
        v_band = self._v_band(cfg)
        for k, (x, r, vv) in enumerate(samp):
            keep = win & np.isfinite(r) & (vv >= cfg.slow_speed_mps(v_band))
            acc.add(k, x[keep], r[keep])
            if not final:
                self.biases.setdefault(k, []).append(biases[k])
        if not final:
            mv = win & np.isfinite(v)
            if mv.any():
                self.v_max = max(self.v_max, float(v[mv].max()))
            slow = mv & (v < cfg.slow_speed_mps(v_band))
            self.slow_s += slow.sum() / fs
            self.slow_m += float(v[slow].sum() / fs)
            for w in warns:
                key = (w.kind, w.channel) if w.kind == "accel_bias" else (w.kind, w.channel, w.start_s)
                if key not in self._seen:
                    self._seen.add(key)
                    self.warnings.append(w)
            self.t_committed = t_commit_end
            keep_from = t_commit_end - self.margin_s
            for st in s.values():
                st.drop_before(keep_from - 1.0)   # 1 s spare for the slower position stream

    def longest_wavelength_m(self) -> float:
        """The longest wavelength of the growing profile's band (fixed up front)."""
        return self.cfg.longest_wavelength_m(self._v_band())

    def _v_band(self, cfg=None) -> float:
        c = self.cfg if cfg is None else cfg
        if c.max_wavelength_m is not None:
            return max(c.band_factor * c.highpass_hz * float(c.max_wavelength_m), c.stop_speed_mps)
        return max(float(c.band_speed_mps), c.stop_speed_mps)

    def _buffered_max_speed(self, cfg) -> float:
        """Top band-test speed in the buffer (the uncommitted tail counts too, as in the batch)."""
        st = self.streams["position"]
        if not st.t.size or "speed_mps" not in (st.channels or ()):
            return 0.0
        fs_pos = st.fs or (1.0 / float(np.median(np.diff(st.t))) if st.t.size > 1 else 1.0)
        v = cfg.band_speed_series(np.abs(st.d[:, st.channels.index("speed_mps")]), fs_pos)
        v = v[np.isfinite(v) & (v >= cfg.stop_speed_mps)]
        return float(v.max()) if v.size else 0.0

    def _buffered_corner(self):
        """The batch rule's profiler for the buffered stream, or None (corner fixed up front, a
        window already committed, or no clean moving stretch yet)."""
        if self._rule_cfg is None or self.t_committed is not None:
            return None
        s = self.streams
        try:
            base = self._rule_cfg
            usable = base.usable_s(s["accel"].view(), s["gap"].view(), s["position"].view(),
                                   self.offsets, self.pairs)
            return base.with_corner(base.corner_for(usable))
        except UserError:
            return None

    def result(self) -> IrregularityResult:
        """The profile so far, including the not yet committed tail (processed on a copy)."""
        import copy
        acc = copy.deepcopy(self.acc)
        have = self.streams["accel"].t.size and min(st.t.size for st in self.streams.values())
        c = (self._buffered_corner() if have else None) or self.cfg
        if have:
            self._process(math.inf, final=True, acc=acc, cfg=c)
        if self.specs is None:
            raise UserError("irregularity stream: no complete accel/gap/position data yet")
        v_band = self._v_band(c)
        fs = self.streams["accel"].fs or 1000.0
        v_max = max(self.v_max, self._buffered_max_speed(c))
        lam_max = c.longest_wavelength_m(v_band)
        lam_min = c.shortest_wavelength_m(v_max, fs)
        warns = list(self.warnings)
        if self.slow_s > 0:
            warns.append(DataWarning(
                "slow_section", "/testline/vehicle/position",
                f"speed below {c.slow_speed_mps(v_band):.3g} m/s (the band's slowest) for "
                f"{self.slow_s:.3g} s ({self.slow_m:.3g} m travelled); those positions are dropped",
                value=self.slow_m))
        biases = [float(np.mean(self.biases.get(k, [0.0]))) for k in range(len(self.specs))]
        return _finish(acc, self.specs, warns, biases, c, v_band, lam_min, lam_max, "loaded",
                       sample_step_m=v_max / fs)


def magnet_channel_pairs(metadata, accel_channels=None, gap_channels=None) -> dict | None:
    """magnet number -> (accel channel, gap channel) from the recording metadata's sensors.

    A sensor pairs when it names a ``magnet`` and sits on /testline/vehicle/accel (vertical) or
    /testline/vehicle/gap; when channel lists are given, only channels present there count.
    None when no magnet has both (the profiler then pairs channels by order).
    """
    from maglev_ros.contract import TOPIC_VEHICLE_ACCEL, TOPIC_VEHICLE_GAP
    pairs_a, pairs_g = {}, {}
    for sid, s in metadata.sensors.items():
        if s.magnet is None:
            continue
        if (s.topic == TOPIC_VEHICLE_ACCEL and (accel_channels is None or sid in accel_channels)
                and s.direction in (None, "vertical")):
            pairs_a.setdefault(s.magnet, sid)
        if s.topic == TOPIC_VEHICLE_GAP and (gap_channels is None or sid in gap_channels):
            pairs_g.setdefault(s.magnet, sid)
    both = sorted(set(pairs_a) & set(pairs_g))
    if not both:
        return None
    return {m: (pairs_a[m], pairs_g[m]) for m in both}
