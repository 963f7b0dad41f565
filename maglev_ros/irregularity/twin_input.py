"""Unloaded guideway irregularity for the twin, reconstructed from one pass (inertial reference).

``profile_for_twin`` turns a pass's magnet accelerations, gaps and position into the rail
irregularity r(x) that, fed to the coupled twin (``twin.coupling``), reproduces that pass:

1. **Loaded profile.** The inertial reference method (:class:`.profile.InertialProfiler`) gives
   y_k = z_m,k + (g_k - g0) = r + w_k at every magnet k: the irregularity PLUS the girder
   deflection w_k under the loaded guideway at that magnet and time.
2. **Loaded -> unloaded iteration.** The twin adds its own deflection, so feeding it y would count
   the deflection twice. The twin is therefore driven along the measured positions with the
   current profile r_i; its girder deflection under each magnet, w_k(t) = g_k - g0 + z_m,k - r_i
   (the twin's own gap identity), is handed to the profiler as ``deflection`` (subtracted from the
   gap change before the shared high-pass), giving r_(i+1). Start: r_0 = loaded profile. The
   deflection depends on r only through the dynamic magnet forces, so this fixed point converges
   in 2-3 passes; it stops when the RMS change of the profile falls below ``tol`` of its RMS.
3. **Band for the twin.** The twin's magnets are point forces: the magnet accelerations come
   from the SHORT waves (at 25 km/h a 0.5 m wave is 14 Hz). So ``magnet_length_m`` is 0 here and
   the shortest wavelength is set by sampling and grid only:
   ``min_wavelength_m = max(4 * spacing_m, 4 * v_max / fs)``. The grid follows the data
   (``spacing_m`` None): one sample step at the top speed, ``v_max / fs``, or the twin's travel per
   step when that is finer, at most ``DEFAULT_SPACING_M`` (2 cm), when two or more magnets measure
   (their difference measures the noise that the twin input's gain then removes,
   :meth:`TwinIrregularity.denoised_twin_input`); 2 cm with one. Samples farther apart than the
   grid (a slow-sampled or fast pass) are first interpolated band-limited to it (:func:`upsampled`),
   so the band reaches the recording's Nyquist rather than 4 samples per wave. (A fixed 2 cm grid
   cut the band at 8 cm: 86 Hz at 6.9 m/s, 52 Hz at 4.2 m/s, where a foreign simulator's rail
   still had its stator-pack waves; the twin's magnet misfit there grew from 0.06 at 18 Hz to 0.65
   at 88 Hz.) Override with ``spacing_m`` / ``min_wavelength_m``.
   The twin samples its input once per step by linear interpolation: the denoised input is handed
   over resampled (band-limited, FFT) to a grid no coarser than the twin's travel per step
   (:func:`fine_twin_input`; a 500 Hz recording's grid is two steps of the 1 ms twin).
   Because the reconstruction uses the same point-sensor convention as the twin, the result is
   the *effective* irregularity the twin needs (as is the geometry product of
   :class:`InertialProfiler`, also point sensors by default, on its coarser grid). The long end
   ``max_wavelength_m = v_band / (2 f_c)`` comes from the time high-pass (default ``highpass_hz``
   0.8 Hz: the double-integrated noise of a 0.02 m/s^2 accelerometer stays below ~10 um there;
   waves that long are followed by the levitation control and barely accelerate the magnets -- the
   twin sees them as absent).
   The result states the band; outside it the profile is zero and ``valid`` is False.

   Speed (checked 15-60 m/s, tests/test_irregularity_speed.py): everything that is cut scales with
   time, not distance. The time edges (``edge_s`` = 1.5 / f_c = 1.9 s at 0.8 Hz at both ends of a
   clean stretch) and the spatial trim (one ``max_wavelength_m`` = v / (2 f_c), i.e. 1 / (2 f_c) =
   0.63 s of travel) are what the two filters need, so a pass of given duration keeps the same
   valid fraction at any speed: valid length = travelled - 2 v (edge_s + 1 / (2 f_c)). (Measured on
   synthetic passes with a 0.02 m/s^2-noise accelerometer: a spatial trim of 0.5 wavelength raises
   the error in the first/last 20 m from 1-5 % to 4-24 % of the band RMS, so the trim stays at 1;
   ``edge_s`` = 0.6 / f_c gives similar edge errors and ~2.25 s x v more profile, but changed the
   twin fits on the discrepancy cases by -0.01..+0.07 NRMSE, so the default stays 1.5 / f_c; pass
   ``edge_s`` to trade.) The failure "no valid irregularity left for the twin" above ~30 m/s at
   500 Hz was NOT the band or the edges but the position grid: a magnet then moves more than
   3 grid bins (0.02 m) per sample and the profiler bridged only 2-bin holes, so the profile fell
   apart into fragments shorter than the band-pass needs; holes up to one sample step are now
   bridged (see :mod:`.profile`, "Grid and sample step").
4. **Magnets.** Every magnet's profile is high-passed in time by the one shared filter (gap part
   and acceleration part together, :func:`.integration.double_integrate` ``plus_highpassed``),
   band-passed in space, then averaged; with the deflection removed the magnets agree to the
   noise level, so the average leaves no steps where the set of covering magnets changes.
5. **Sensor latency.** ``sensor_delay_s`` is the (known) delay of the accelerometer and gap
   channels relative to the position channel, e.g. the group delay of the acquisition
   system's anti-alias filter. It is removed from the position mapping (the profile sits at its
   true positions); :func:`simulate_recorded_pass` delays the twin's output by the same amount so
   prediction and recording line up. With 0 the profile is shifted by speed x delay (harmless for
   the twin, wrong for geometry).

Outside the valid stretch the twin input is zero, reached by a half-cosine taper of ``taper_m``
inside the valid stretch. :func:`accel_nrmse` compares measured and predicted magnet
accelerations only while every magnet of the vehicle is over the valid stretch (past the tapers)
and at least one is on the line, in a stated band (see its docstring).

Why by hand: the loop couples our own profiler and twin; no library does either.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from types import SimpleNamespace
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import signal

from maglev_ros.errors import UserError
from maglev_ros.irregularity.integration import DataWarning, _runs
from maglev_ros.irregularity.profile import InertialProfiler, IrregularityResult, _rate, magnet_channel_pairs

__all__ = ["TwinIrregularity", "profile_for_twin", "simulate_recorded_pass", "accel_nrmse",
           "twin_deflection", "twin_spacing_m", "fine_twin_input", "DEFAULT_SPACING_M", "SharedRail",
           "shared_twin_inputs", "upsampled", "upsample_factor"]

DEFAULT_SPACING_M = 0.02       # the twin input's grid with one magnet, and its coarsest


@dataclass(frozen=True, eq=False)
class TwinIrregularity:
    """Unloaded irregularity ready for the twin (``as_twin_input()`` -> (x, r) for
    ``coupling.simulate_pass`` / ``TwinStepper``)."""
    position_m: np.ndarray                 # regular grid
    irregularity_m: np.ndarray             # unloaded, band-limited; 0 outside ``valid``
    valid: np.ndarray                      # bool: inside the measured stretch (before tapering)
    min_wavelength_m: float
    max_wavelength_m: float
    highpass_hz: float
    band_speed_mps: float
    spacing_m: float
    filter_order: int
    sensor_delay_s: float
    taper_m: float
    iterations: int                        # twin runs used for the deflection
    converged: bool
    change_history: tuple[float, ...]      # RMS(r_(i+1) - r_i) / RMS(r_(i+1)) per iteration
    deflection_rms_m: float                # RMS of the twin's girder deflection removed (valid part)
    loaded_minus_unloaded_rms_m: float
    result: IrregularityResult             # the last (unloaded) profiler result
    warnings: tuple[DataWarning, ...] = field(default_factory=tuple)
    twin_step_m: float = 0.0               # the twin's travel per step at the top speed (0: not known)

    def as_twin_input(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, r) on the reconstruction's grid, not denoised (the magnets' raw mean: its short waves
        carry the gap noise); the twin is driven by :meth:`denoised_twin_input`."""
        return self.position_m, self.irregularity_m

    def denoised_twin_input(self):
        """:meth:`_denoised` on the grid the twin reads accurately (:func:`fine_twin_input`)."""
        x, r, g = self._denoised()
        return (*fine_twin_input(x, r, self.twin_step_m), g)

    def _denoised(self):
        """(x, r, gain): the twin input with the Wiener gain of the spectra measured on this pass
        (:func:`maglev_ros.irregularity.denoise.rail_gain`: the rail's, and each magnet's own error
        from the magnets' difference), for the number of magnets averaged at each point (one where
        a single magnet measured). ``gain`` is None with one magnet or too short a common stretch;
        r is then band-limited at the shortest wave of the default grid (4 x ``DEFAULT_SPACING_M``).
        The diagnosis and the model updating (offline and online) drive the twin with this: the raw
        mean carries short waves the magnets do not agree on (gap noise), which the twin turned into
        magnet accelerations 10-1000x the measured ones at 60-110 Hz."""
        from .denoise import apply_rail_gain, magnets_averaged, rail_gain
        res = self.result
        g = rail_gain(res.magnet_profiles_m, self.spacing_m)
        if g is None:
            return self.position_m, self._lowpassed(4 * DEFAULT_SPACING_M), None
        ramp = max(1, int(round(0.25 * res.max_wavelength_m / self.spacing_m)))   # the profiler's blend
        n_eff = np.ones(self.position_m.size)
        i0 = int(round((res.position_m[0] - self.position_m[0]) / self.spacing_m))
        n_eff[i0:i0 + res.position_m.size] = magnets_averaged(res.magnet_profiles_m, ramp)
        return self.position_m, apply_rail_gain(self.irregularity_m, self.spacing_m, g, n_eff), g

    def _lowpassed(self, min_wavelength_m: float) -> np.ndarray:
        if min_wavelength_m <= self.min_wavelength_m * (1 + 1e-9):
            return self.irregularity_m
        sos = signal.butter(self.filter_order, 1.0 / min_wavelength_m, fs=1.0 / self.spacing_m, output="sos")
        return signal.sosfiltfilt(sos, self.irregularity_m)

    @property
    def valid_range_m(self) -> tuple[float, float]:
        x = self.position_m[self.valid]
        return float(x.min()), float(x.max())

    def band(self) -> dict:
        return {"min_wavelength_m": self.min_wavelength_m, "max_wavelength_m": self.max_wavelength_m,
                "highpass_hz": self.highpass_hz, "band_speed_mps": self.band_speed_mps,
                "filter": self.result.band_filter(),
                "note": "point-magnet (twin) band: shortest wavelength from sampling/grid, no magnet "
                        "length; outside the band and outside the valid stretch the profile is 0"}

    def to_dict(self, include_profile: bool = False) -> dict:
        lo, hi = self.valid_range_m
        d = {"kind": "unloaded", "spacing_m": self.spacing_m, "band": self.band(),
             "valid_from_m": lo, "valid_to_m": hi, "taper_m": self.taper_m,
             "sensor_delay_s": self.sensor_delay_s,
             "iterations": self.iterations, "converged": self.converged,
             "change_history": [float(c) for c in self.change_history],
             "deflection_rms_m": self.deflection_rms_m,
             "loaded_minus_unloaded_rms_m": self.loaded_minus_unloaded_rms_m,
             "rms_m": float(np.sqrt(np.mean(self.irregularity_m[self.valid] ** 2))),
             "agreement": [{"a": a, "b": b, "correlation": c if math.isfinite(c) else None}
                           for a, b, c in self.result.agreement],
             "warnings": [w.to_dict() for w in self.warnings]}
        if include_profile:
            d["position_m"] = self.position_m.tolist()
            d["irregularity_m"] = self.irregularity_m.tolist()
            d["valid"] = self.valid.astype(int).tolist()
        return d


# ----------------------------------------------------------------------------------------------
def _resolve_vehicle(metadata_or_offsets, accel, gap, nominal_gap_m, channel_pairs):
    """(offsets, g0, channel_pairs) from a contract Metadata, a metadata dict or plain offsets."""
    md = metadata_or_offsets
    if isinstance(md, Mapping):
        from maglev_ros.contract import metadata_from_dict
        md = metadata_from_dict(dict(md), "<metadata>")
    if hasattr(md, "magnet_offsets_m") and hasattr(md, "sensors"):
        offs = tuple(md.magnet_offsets_m)
        if not offs:
            raise UserError("metadata vehicle.magnet_offsets_m: missing or empty (needed to place the magnets)")
        g0 = md.nominal_gap_m if nominal_gap_m is None else nominal_gap_m
        if channel_pairs is None:
            channel_pairs = magnet_channel_pairs(md, tuple(accel.channels), tuple(gap.channels))
    else:
        try:
            offs = tuple(float(o) for o in md)
        except TypeError:
            raise UserError("metadata_or_offsets: expected contract metadata or a list of magnet "
                            f"offsets in m, got {type(md).__name__}") from None
        g0 = nominal_gap_m
    return offs, (0.010 if g0 is None else float(g0)), channel_pairs


def _cd(time_s, data, channels, fs=None):
    return SimpleNamespace(time_s=np.asarray(time_s, float), data=np.asarray(data, float),
                           channels=tuple(channels), sample_rate_hz=fs)


def _position_arrays(position):
    chans = tuple(position.channels)
    for c in ("position_m", "speed_mps"):
        if c not in chans:
            raise UserError(f"/testline/vehicle/position: channel '{c}' not found (channels: {', '.join(chans)})")
    d = np.asarray(position.data, float)
    t = np.asarray(position.time_s, float)
    p, v = d[:, chans.index("position_m")], d[:, chans.index("speed_mps")]
    ok = np.isfinite(t) & np.isfinite(p) & np.isfinite(v)
    if ok.sum() < 2:
        raise UserError("/testline/vehicle/position: fewer than 2 finite samples")
    return t[ok], p[ok], v[ok]


def simulate_recorded_pass(config, line, position, irregularity, time_s, *,
                           sensor_delay_s: float = 0.0, method: str = "newmark",
                           dt_max_s: float | None = None, sensors: Any = None,
                           block_s: float = 0.1, customize: Any = None):
    """Drive the twin along a recording's position channel; outputs on ``time_s`` (the recorded
    accel sample times, evenly spaced).

    The twin starts in static equilibrium one sample before ``time_s[0] - sensor_delay_s`` at the
    measured position and advances in ``block_s`` steps with the measured speed (linear ramps in
    between); its outputs are labelled ``t + sensor_delay_s`` so they line up with the delayed
    recorded channels. Returns ``(PassResult, drift_m, stepper)``: the twin's outputs (its
    ``position_m`` is the reference position at the un-delayed instant), the maximal |twin
    position - measured position| and the ``TwinStepper`` (vehicle model, magnet offsets).
    ``customize``: a callable that takes the new stepper and returns it with what its config and
    line do not hold (a damaged span, an attachment, ...), applied before the static start.
    """
    from maglev_ros.twin.coupling import PassResult, TwinStepper
    from maglev_ros.twin.trajectory import MeasuredTrajectory, drive
    t = np.asarray(time_s, float)
    if t.size < 2:
        raise UserError("vehicle accel: fewer than 2 samples to predict")
    fs = 1.0 / float(np.median(np.diff(t)))
    traj = MeasuredTrajectory.from_samples(*_position_arrays(position))
    tau = float(sensor_delay_s)
    t_start = t[0] - tau - 1.0 / fs
    t_end = t[-1] - tau
    st = TwinStepper(config, line, sensors=sensors, irregularity=irregularity, fs_out_hz=fs,
                     start_position_m=float(traj.position_at(t_start)),
                     start_speed_mps=float(traj.speed_at(t_start)), t0_s=t_start,
                     method=method, dt_max_s=dt_max_s, init="rest")
    if customize is not None:
        st = customize(st)
    st._init_static()
    res = PassResult.concat(drive(st, traj, t_end + 0.5 / fs, block_s))
    drift = float(np.max(np.abs(res.position_m - traj.position_at(res.time_s)))) if res.n_samples else 0.0
    from dataclasses import replace
    res = replace(res, time_s=res.time_s + tau)
    return res, drift, st


def twin_deflection(res, stepper, irregularity) -> np.ndarray:
    """Girder deflection under every magnet of a twin run, (n, n_magnets), up positive:
    w = gap - g0 + z_m - r(x) (the twin's gap identity, gap = g0 + r + w - z_m)."""
    from maglev_ros.twin.coupling import as_irregularity
    irr = as_irregularity(irregularity)
    Bm = stepper.vehicle.model.magnet_input
    zm = res.vehicle_disp_m @ Bm
    X = res.position_m[:, None] + stepper.magnet_offsets_m[None, :]
    r = irr.elevation(X.ravel()).reshape(X.shape)
    g0 = float(stepper.vehicle.levitation.nominal_gap_m)
    return res.magnet_gap_m - g0 + zm - r


def _twin_profile(res: IrregularityResult, taper_m: float, pad_m: float):
    """Grid, zero-filled tapered profile and valid mask from a profiler result."""
    dx = res.spacing_m
    ok = res.valid
    if not ok.any():
        raise UserError("vehicle recording: no valid irregularity left for the twin")
    npad = int(math.ceil(pad_m / dx))
    j0 = int(round(res.position_m[0] / dx)) - npad
    n = res.position_m.size + 2 * npad
    x = (j0 + np.arange(n)) * dx
    r = np.zeros(n)
    valid = np.zeros(n, bool)
    valid[npad:npad + ok.size] = ok
    r[npad:npad + ok.size] = np.where(ok, res.irregularity_m, 0.0)
    return x, r * _taper_weights(valid, int(round(taper_m / dx))), valid


def _taper_weights(valid: np.ndarray, nt: int) -> np.ndarray:
    """1 inside each valid stretch, a half-cosine ramp over its first and last ``nt`` points, 0 outside."""
    w = valid.astype(float)
    if nt > 1:
        m = np.concatenate([[False], valid, [False]])
        d = np.diff(m.astype(np.int8))
        for i0, i1 in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
            k = min(nt, (i1 - i0) // 2)
            if k > 1:
                ramp = 0.5 * (1.0 - np.cos(np.pi * (np.arange(k) + 0.5) / k))
                w[i0:i0 + k] *= ramp
                w[i1 - k:i1] *= ramp[::-1]
    return w


def twin_spacing_m(accel, position, n_magnets: int, twin_dt_s: float | None = None) -> float:
    """Grid of the twin input [m]: one sample step at the top speed when two or more magnets measure
    (the finest the data resolve; their noise is then measured and removed), or the twin's travel per
    step (``twin_dt_s``) when that is finer (the samples are then interpolated band-limited to it,
    :func:`upsampled`); never coarser than ``DEFAULT_SPACING_M``; that with one magnet."""
    if n_magnets < 2:
        return DEFAULT_SPACING_M
    _, _, spd = _position_arrays(position)
    step_s = 1.0 / _rate(accel)
    if twin_dt_s is not None and twin_dt_s > 0:
        step_s = min(step_s, float(twin_dt_s))
    v_top = float(np.max(np.abs(spd)))
    return DEFAULT_SPACING_M if not v_top > 0 else min(DEFAULT_SPACING_M, v_top * step_s)


def upsample_factor(accel, position, spacing_m: float) -> int:
    """How many times the vehicle channels are upsampled so that their samples at the top speed lie no
    farther apart than ``spacing_m`` (1: they already do; a grid within 5 % of the step is the step)."""
    _, _, spd = _position_arrays(position)
    step_m = float(np.max(np.abs(spd))) / _rate(accel)
    return max(1, int(math.ceil(step_m / float(spacing_m) - 0.05))) if spacing_m > 0 else 1


def upsampled(cd, factor: int):
    """ChannelData-like ``cd`` interpolated band-limited to ``factor`` x its rate (scipy's polyphase
    resampler on each finite run of each channel; NaN stays NaN). Why: bin-averaged onto a grid of one
    sample step, a wave at 0.35 x the sample rate kept 0.81 of its amplitude (the boxcar and the
    position rounding) and linear interpolation between samples 4 per wave as little; a 250 Hz
    recording's rail then lost 20-75 % of the 0.10-0.2 m waves that drive the magnets' 40-90 Hz bands
    (1 kHz: 1-5 %)."""
    L = int(factor)
    t = np.asarray(cd.time_s, float)
    if L <= 1 or t.size < 2:
        return cd
    d = np.asarray(cd.data, float)
    d2 = d[:, None] if d.ndim == 1 else d
    n_up = (t.size - 1) * L + 1             # the last sample closes the record: nothing extrapolated
    out = np.full((n_up, d2.shape[1]), np.nan)
    for j in range(d2.shape[1]):
        for i0, i1 in _runs(np.isfinite(d2[:, j])):
            seg = d2[i0:i1, j]
            if seg.size >= 8:
                up = signal.resample_poly(seg, L, 1, padtype="line")[:(seg.size - 1) * L + 1]
            else:
                up = np.interp(np.arange((seg.size - 1) * L + 1) / L, np.arange(seg.size), seg)
            out[i0 * L:i0 * L + up.size, j] = up
    t_up = np.interp(np.arange(n_up) / L, np.arange(t.size), t)
    fs = getattr(cd, "sample_rate_hz", None)
    return _cd(t_up, out if d.ndim > 1 else out[:, 0], cd.channels, None if fs is None else float(fs) * L)


def profile_for_twin(accel, gap, position, metadata_or_offsets, config, line=None, *,
                     highpass_hz: float | None = 0.8, spacing_m: float | None = None,
                     min_wavelength_m: float | None = None, max_wavelength_m: float | None = None,
                     band_speed_mps: float | None = None, magnets: Sequence[int] | None = None,
                     channel_pairs: dict | None = None, nominal_gap_m: float | None = None,
                     sensor_delay_s: float = 0.0, max_iterations: int = 4, tol: float = 0.01,
                     taper_m: float = 1.0, edge_s: float | None = None, method: str = "newmark",
                     dt_max_s: float | None = None, customize_stepper: Any = None,
                     **profiler_kwargs) -> TwinIrregularity:
    """Unloaded irregularity of one pass, ready to drive the twin (see module docstring).

    ``accel``, ``gap``, ``position``: ChannelData-like (time_s, data, channels[, sample_rate_hz])
    of /testline/vehicle/accel, /gap and /position. ``metadata_or_offsets``: the recording's
    contract ``Metadata`` (or its dict; magnet offsets, nominal gap and the magnet channel pairs
    come from it) or a plain list of magnet offsets [m]. ``config``/``line``: the twin
    (``TwinConfig`` and the metadata ``line`` block / spans) whose deflection is removed.
    ``max_iterations``: twin runs at most (0 returns the loaded profile, tagged as such in the
    warnings). ``highpass_hz`` None: the corner follows the pass as the irregularity verb chooses it
    (:meth:`InertialProfiler.corner_for`), with its edges unless ``edge_s`` is given. ``spacing_m``
    None: the grid follows the data (:func:`twin_spacing_m`). Extra keyword arguments go to
    :class:`InertialProfiler`. ``customize_stepper``: passed to :func:`simulate_recorded_pass`
    (the twin whose deflection is removed must be the twin that is then driven by the result).
    """
    offs, g0, pairs = _resolve_vehicle(metadata_or_offsets, accel, gap, nominal_gap_m, channel_pairs)
    if highpass_hz is not None and not highpass_hz > 0:
        raise UserError(f"highpass_hz: expected > 0 Hz or None (follow the pass), got {highpass_hz}")
    if not (max_iterations >= 0):
        raise UserError(f"max_iterations: expected >= 0, got {max_iterations}")
    tau = float(sensor_delay_s)
    if spacing_m is None:
        n_mag = len([m for m in (pairs or {}) if magnets is None or m in magnets]) if pairs else \
            min(len(accel.channels), len(gap.channels), len(offs))
        spacing_m = twin_spacing_m(accel, position, n_mag, dt_max_s or config.numerics.dt_max_s)
    up = upsample_factor(accel, position, spacing_m)
    if up > 1:
        accel, gap = upsampled(accel, up), upsampled(gap, up)
    pos_sh = _cd(np.asarray(position.time_s, float) + tau, position.data, position.channels,
                 getattr(position, "sample_rate_hz", None))
    prof = InertialProfiler(highpass_hz=highpass_hz, spacing_m=spacing_m, magnets=magnets,
                            magnet_length_m=0.0, min_wavelength_m=min_wavelength_m,
                            max_wavelength_m=max_wavelength_m, band_speed_mps=band_speed_mps,
                            edge_s=(1.5 / highpass_hz) if edge_s is None and highpass_hz is not None else edge_s,
                            **profiler_kwargs)
    fit_kw = dict(magnet_offsets_m=offs, nominal_gap_m=g0, channel_pairs=pairs)
    loaded = prof.fit(accel, gap, pos_sh, **fit_kw)
    # pad: the twin input must cover every magnet of the vehicle, sensored or not
    pad = float(np.ptp(np.asarray(config.vehicle.magnet_offsets_m, float))) + 5.0
    x, r, valid = _twin_profile(loaded, taper_m, pad)
    t_acc = np.asarray(accel.time_s, float)
    cur = loaded
    history: list[float] = []
    converged = max_iterations == 0
    defl_rms = 0.0
    warns = list(loaded.warnings)
    it = 0
    for it in range(1, int(max_iterations) + 1):
        res, drift, st = simulate_recorded_pass(config, line, position, (x, r), t_acc,
                                                sensor_delay_s=tau, method=method, dt_max_s=dt_max_s,
                                                customize=customize_stepper)
        w = twin_deflection(res, st, (x, r))
        tw = res.time_s

        def defl(t, _x, magnet, _tw=tw, _w=w):
            return np.interp(t, _tw, _w[:, magnet - 1])

        cur = prof.fit(accel, gap, pos_sh, deflection=defl, **fit_kw)
        x2, r2, valid2 = _twin_profile(cur, taper_m, pad)
        both = np.interp(x, x2, r2, left=np.nan, right=np.nan)
        m = valid & np.isfinite(both)
        rms_new = float(np.sqrt(np.mean(both[m] ** 2))) if m.any() else 0.0
        change = float(np.sqrt(np.mean((both[m] - r[m]) ** 2)) / rms_new) if rms_new > 0 else 0.0
        history.append(change)
        xs = res.position_m[:, None] + st.magnet_offsets_m[None, :]
        inside = (xs >= x2[valid2].min()) & (xs <= x2[valid2].max())
        defl_rms = float(np.sqrt(np.mean((w - w.mean())[inside] ** 2))) if inside.any() else 0.0
        x, r, valid = x2, r2, valid2
        if drift > 0.05:
            warns.append(DataWarning("position_drift", "/testline/vehicle/position",
                                     f"twin position drifted {drift:.3g} m from the measured one "
                                     "(speed channel inconsistent with position)", value=drift))
        if change < tol:
            converged = True
            break
    if max_iterations == 0:
        warns.append(DataWarning("band", "", "max_iterations=0: loaded profile (girder deflection "
                                 "under the vehicle not removed)"))
    elif not converged:
        warns.append(DataWarning("not_converged", "", f"loaded->unloaded iteration still changed "
                                 f"the profile by {history[-1]:.3g} of its RMS after {it} twin runs"))
    lu = np.interp(cur.position_m, loaded.position_m, loaded.irregularity_m)
    m = cur.valid & np.isfinite(lu)
    lmu = float(np.sqrt(np.mean((lu[m] - cur.irregularity_m[m]) ** 2))) if m.any() else 0.0
    seen, uniq = set(), []
    for wn in warns + list(cur.warnings):
        key = (wn.kind, wn.channel, wn.message)
        if key not in seen:
            seen.add(key)
            uniq.append(wn)
    return TwinIrregularity(
        position_m=x, irregularity_m=r, valid=valid, min_wavelength_m=cur.min_wavelength_m,
        max_wavelength_m=cur.max_wavelength_m, highpass_hz=cur.highpass_hz,
        band_speed_mps=cur.band_speed_mps, spacing_m=cur.spacing_m, filter_order=cur.filter_order,
        sensor_delay_s=tau, taper_m=float(taper_m), iterations=it if max_iterations else 0,
        converged=converged, change_history=tuple(history), deflection_rms_m=defl_rms,
        loaded_minus_unloaded_rms_m=lmu, result=cur, warnings=tuple(uniq),
        twin_step_m=float(np.max(np.abs(_position_arrays(position)[2])))
        * float(dt_max_s or config.numerics.dt_max_s))


# ----------------------------------------------------------------------------------------------
def accel_nrmse(accel, prediction, twin_irregularity: TwinIrregularity, config, line=None, *,
                channel_pairs: dict | None = None, magnets: Sequence[int] | None = None,
                band_hz: tuple[float, float] | None = None, margin_m: float = 1.0) -> dict:
    """NRMSE = rms(measured - predicted) / rms(measured) of the magnet accelerations.

    ``prediction``: the ``PassResult`` of :func:`simulate_recorded_pass` on the accel sample times.
    Compared: the channels of ``channel_pairs`` (magnet -> (accel, gap) channel; default: accel
    channel k is magnet k), only while (a) every magnet of the vehicle is over the valid stretch of
    ``twin_irregularity`` at least ``taper_m + margin_m`` from its ends and (b) at least one magnet
    is on a span of the line. Both signals are band-passed by the same zero-phase Butterworth
    (order 4, forward-backward) from ``highpass_hz`` of the profile to v_max / min_wavelength
    (capped at 0.45 fs): the band the twin input carries; ``band_hz`` overrides it.
    Returns {"nrmse", "per_channel", "band_hz", "window_s", "n_samples"}.
    """
    from maglev_ros.twin.design import line_spans
    t = np.asarray(accel.time_s, float)
    fs = 1.0 / float(np.median(np.diff(t)))
    chans = tuple(accel.channels)
    data = np.asarray(accel.data, float)
    if channel_pairs is None:
        channel_pairs = {k + 1: (c, None) for k, c in enumerate(chans)}
    mags = sorted(m for m in channel_pairs if magnets is None or m in magnets)
    if prediction.n_samples != t.size:
        pt = np.asarray(prediction.time_s, float)
        pred_all = np.column_stack([np.interp(t, pt, prediction.magnet_accel_mps2[:, k])
                                    for k in range(prediction.magnet_accel_mps2.shape[1])])
        xref = np.interp(t, pt, prediction.position_m)
    else:
        pred_all = prediction.magnet_accel_mps2
        xref = prediction.position_m
    offs = np.asarray(config.vehicle.magnet_offsets_m, float)
    X = xref[:, None] + offs[None, :]
    lo, hi = twin_irregularity.valid_range_m
    mg = twin_irregularity.taper_m + margin_m
    over = (X.min(axis=1) >= lo + mg) & (X.max(axis=1) <= hi - mg)
    spans = line_spans(line, config)
    on = np.zeros(t.size, bool)
    for s in spans:
        on |= np.any((X >= s.start_m) & (X <= s.end_m), axis=1)
    win = over & on
    if win.sum() < 16:
        raise UserError("magnet accel comparison: no time with the whole vehicle over the valid "
                        "profile and on the line")
    if band_hz is None:
        v_max = float(np.max(np.abs(np.gradient(xref, t))[win]))
        f_hi = min(0.45 * fs, v_max / twin_irregularity.min_wavelength_m)
        band_hz = (twin_irregularity.highpass_hz, f_hi)
    sos = signal.butter(4, list(band_hz), btype="band", fs=fs, output="sos")
    meas, pred = [], []
    for m in mags:
        ca = channel_pairs[m][0]
        if ca not in chans:
            raise UserError(f"/testline/vehicle/accel: channel '{ca}' not found")
        a = data[:, chans.index(ca)]
        p = pred_all[:, m - 1]
        meas.append(signal.sosfiltfilt(sos, a - np.mean(a))[win])
        pred.append(signal.sosfiltfilt(sos, p - np.mean(p))[win])
    M, Pm = np.column_stack(meas), np.column_stack(pred)
    per = {f"M{m}": float(np.sqrt(np.mean((M[:, i] - Pm[:, i]) ** 2)) / np.sqrt(np.mean(M[:, i] ** 2)))
           for i, m in enumerate(mags)}
    tot = float(np.sqrt(np.mean((M - Pm) ** 2)) / np.sqrt(np.mean(M ** 2)))
    return {"nrmse": tot, "per_channel": per, "band_hz": [float(band_hz[0]), float(band_hz[1])],
            "filter": "butterworth order 4 band-pass, zero-phase (sosfiltfilt), on both signals",
            "window_s": float(win.sum() / fs), "n_samples": int(win.sum())}


# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SharedRail:
    """How the passes over one line shared their short waves (:func:`shared_twin_inputs`)."""
    used: bool
    reason: str
    n_passes: int
    n_profiles: int                      # magnet profiles of every pass that were averaged
    split_wavelength_m: float | None     # shorter waves from every pass, longer from each pass itself
    noise_ratio: float | None            # error spectrum between / within passes, median where shared
    noise_ratio_limit: float | None
    gain: Any = None                     # the RailGain of all profiles

    def to_dict(self) -> dict:
        return {"used": self.used, "reason": self.reason, "n_passes": self.n_passes,
                "n_profiles": self.n_profiles, "split_wavelength_m": self.split_wavelength_m,
                "noise_ratio_between_passes": self.noise_ratio, "noise_ratio_limit": self.noise_ratio_limit,
                "gain": None if self.gain is None else self.gain.to_dict()}


def fine_twin_input(x_m: np.ndarray, r_m: np.ndarray, twin_step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, r) resampled band-limited (FFT) to a grid no coarser than ``twin_step_m``, the twin's
    travel per step at the top speed. The twin samples its input once per step, by linear
    interpolation: on a grid coarser than its travel per step that flattens the short waves its step
    would sample (a 500 Hz recording's grid is two steps of a 1 ms twin: the magnet bands' fit 0.105 ->
    0.078, the whole truth twin's 0.118 -> 0.098 held-out). Not finer: the short waves beyond what the
    twin's step integrates then only add error (a 1 kHz recording read at 16 points per shortest wave:
    training fit 0.074 -> 0.080, held-out unchanged). r is band-limited and tapered to 0 at both ends,
    so the FFT's periodic extension adds nothing. Unchanged with ``twin_step_m`` 0."""
    x = np.asarray(x_m, float)
    r = np.asarray(r_m, float)
    if x.size < 8 or not twin_step_m > 0:
        return x, r
    dx = float(x[1] - x[0])
    # a grid within 5 % of the step is the step (a 999.9 Hz recording is not resampled 2x)
    u = int(math.ceil(dx / float(twin_step_m) - 0.05))
    if u <= 1:
        return x, r
    return x[0] + np.arange(x.size * u) * (dx / u), signal.resample(r, x.size * u)


def _complement_lowpass(r: np.ndarray, spacing_m: float, wavelength_m: float) -> np.ndarray:
    """Zero-phase low-pass with gain 1 / (1 + (k wavelength)^8) (r minus it: the matching high-pass)."""
    n = 1 << int(np.ceil(np.log2(2 * r.size)))
    k = np.fft.rfftfreq(n, spacing_m)
    return np.fft.irfft(np.fft.rfft(r, n) / (1.0 + (k * wavelength_m) ** 8), n)[:r.size]


def shared_twin_inputs(tis: Sequence[TwinIrregularity]) -> tuple[list[tuple[np.ndarray, np.ndarray]], SharedRail]:
    """The twin inputs of several passes over ONE line, each with its short waves measured by every
    pass's magnets: the same rail seen by twice the magnets carries half the noise.

    Each pass keeps its own denoised input (:meth:`TwinIrregularity.denoised_twin_input`) for waves
    longer than ``split``, the longest wave every pass keeps at full gain (the passes' bands differ
    at their long ends: their corners and speeds); shorter waves come from the mean of every pass's magnet profiles on their common grid, with the
    Wiener gain of all of them, inside the pass's own valid stretch (its tapers, valid range and long
    waves unchanged). A wave is shared only where the passes measured the same rail at the same
    positions: where the error spectrum between two passes' magnets exceeds the one within a pass by
    less than the error the wider mean removes (a shift in position, or a rail that changed, shows as
    a larger difference between the passes where the rail is strong). Elsewhere each pass keeps its own."""
    from .denoise import _smooth_relative, _welch_runs, apply_rail_gain, magnets_averaged, rail_gain
    own = [ti._denoised()[:2] for ti in tis]
    steps = [ti.twin_step_m for ti in tis]

    def keep(reason, **kw):
        return ([fine_twin_input(x, r, st) for (x, r), st in zip(own, steps)],
                SharedRail(False, reason, len(tis), 0, kw.get("split"), kw.get("ratio"), kw.get("limit")))
    if len(tis) < 2:
        return keep("one pass")
    dx = tis[0].spacing_m
    if any(abs(ti.spacing_m - dx) > 1e-9 * dx for ti in tis):
        return keep("the passes' grids differ")
    n_own = [ti.result.magnet_profiles_m.shape[0] for ti in tis]
    if min(n_own) < 2:
        return keep("a pass with one magnet: its own error spectrum is not measured")
    # the split: the longest wave every pass keeps at full gain, v / (2 f_c), half its stated longest
    # at band factor 1 (the passes' bands differ at their long ends only: their corners and speeds)
    split = min(ti.band_speed_mps / (2.0 * ti.highpass_hz) for ti in tis)
    j = [int(round(ti.result.position_m[0] / dx)) for ti in tis]
    j0 = min(j)
    n = max(jj + ti.result.position_m.size for jj, ti in zip(j, tis)) - j0
    rows, owner = [], []
    for p, (jj, ti) in enumerate(zip(j, tis)):
        for prof in ti.result.magnet_profiles_m:
            row = np.full(n, np.nan)
            row[jj - j0:jj - j0 + prof.size] = prof
            rows.append(row)
            owner.append(p)
    rows = np.array(rows)
    nps = 256
    within = [rows[a] - rows[b] for a in range(len(rows)) for b in range(a + 1, len(rows)) if owner[a] == owner[b]]
    between = [rows[a] - rows[b] for a in range(len(rows)) for b in range(a + 1, len(rows)) if owner[a] != owner[b]]
    k, w_psd, nw = _welch_runs(within, 1.0 / dx, nps)
    _, b_psd, nb = _welch_runs(between, 1.0 / dx, nps)
    # a wave is shared where the passes' disagreement Delta = 2 (b - w) (b, w: the error spectra between
    # and within passes) adds less error to the shared mean, f^2 Delta with f the other passes' share
    # of it, than the wider mean removes, w (1 / n_own - 1 / n_all): b / w below the limit
    n_min, n_all = min(n_own), len(rows)
    f = 1.0 - n_min / n_all
    limit = 1.0 + (1.0 / n_min - 1.0 / n_all) / (2.0 * f * f)
    if k is None or b_psd is None:
        return keep("the passes measured no common stretch long enough to compare", split=split, limit=limit)
    w_s, cnt = _smooth_relative(k, w_psd, 0.25)
    b_s, _ = _smooth_relative(k, b_psd, 0.25)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio_k = b_s / w_s
    # the ratio must clear the limit by two of its standard errors (Welch averages of nb, nw segments)
    se_k = ratio_k * np.sqrt(1.0 / (nb * cnt) + 1.0 / (nw * cnt))
    short = (k >= 1.0 / split) & np.isfinite(ratio_k)
    shared_k = short & (ratio_k + 2.0 * se_k <= limit)
    if not shared_k.any():
        return keep(f"the passes differ by more than their noise at every wave shorter than {split:.3g} m "
                    f"(between / within a pass {np.nanmin(ratio_k[short]) if short.any() else np.nan:.2f} "
                    f"or more, limit {limit:.2f}): not one rail at one position", split=split, limit=limit)
    ratio = float(np.median(ratio_k[shared_k]))
    g = rail_gain(rows, dx)
    if g is None:
        return keep("no error spectrum measured", split=split, ratio=ratio, limit=limit)
    from .profile import _coverage_weights
    ramp = max(1, int(round(0.25 * min(ti.result.max_wavelength_m for ti in tis) / dx)))
    W = _coverage_weights(np.isfinite(rows), ramp)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_all = np.sum(W * np.nan_to_num(rows), axis=0) / np.sum(W, axis=0)
    n_all = magnets_averaged(rows, ramp)
    out = []
    for jj, ti, (x, r_own) in zip(j, tis, own):
        res = ti.result
        sl = slice(jj - j0, jj - j0 + res.position_m.size)
        nt = int(round(ti.taper_m / dx))
        # every pass's mean where this pass measured (its own ramps at the ends), with the gain of all
        # the profiles; only its waves shorter than the split replace the pass's own: those of the
        # difference, which is small and tapered like the pass's input (no step for the filter to ring on)
        m = np.where(res.valid & np.isfinite(mean_all[sl]), mean_all[sl], res.irregularity_m)
        i0 = int(round((res.position_m[0] - x[0]) / dx))
        r_all = np.zeros(x.size)
        r_all[i0:i0 + m.size] = np.where(res.valid, m, 0.0)
        n_eff = np.ones(x.size)
        n_eff[i0:i0 + m.size] = np.where(res.valid, n_all[sl], 1.0)
        diff = apply_rail_gain(r_all * _taper_weights(ti.valid, nt), dx, g, n_eff) - r_own
        nfft = 1 << int(np.ceil(np.log2(2 * diff.size)))
        kf = np.fft.rfftfreq(nfft, dx)
        H = (1.0 - 1.0 / (1.0 + (kf * split) ** 8)) * np.interp(kf, k, shared_k.astype(float))
        out.append((x, r_own + np.fft.irfft(np.fft.rfft(diff, nfft) * H, nfft)[:diff.size]))
    lam = 1.0 / k[shared_k]
    out = [fine_twin_input(x, r, st) for (x, r), st in zip(out, steps)]
    return out, SharedRail(True, f"one rail: the passes differ by their noise only at {lam.min():.3g}-{lam.max():.3g} m "
                                 f"({shared_k.sum()} of {short.sum()} wavenumbers shorter than the split)",
                           len(tis), len(rows), split, ratio, limit, g)
