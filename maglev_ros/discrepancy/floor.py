"""What limits the calibrated twin's fit: the gap sensors' noise in the rail that drives it.

The twin is driven by the rail reconstructed from the magnets' gaps and accelerations, kept where
the magnets agree (the Wiener gain of the rail spectrum R and each magnet's own error spectrum N,
both measured on the pass, :mod:`maglev_ros.irregularity.denoise`). The gap sensors' noise leaves
an error of spectrum E(k) = R N_n / (R + N_n), N_n = N_w / n for n magnet profiles averaged, with
N_w the profiles' white error level (:func:`sensor_noise_psd`): the Wiener estimate's own mean-square
error. Driven through the twin, that error makes a misfit no calibration can remove: the short
waves the noise hides excite the magnets and, through them, the girder's higher modes.

It is estimated by Monte Carlo: the twin runs again on each pass with its rail plus a Gaussian
profile of spectrum E (random phases, a fixed seed: the report is reproducible), and the NRMSE
between the perturbed and the unperturbed predictions, on the items of the fit itself
(:func:`.evaluate._fit_items`) and normalised by the measured amplitudes as the fit is, is the
sensor-noise floor. The calibrated fit's remainder (in quadrature) is the rest: model error, the other
sensors' noise, ambient vibration and the rail's other errors. Written here: the estimate is the
twin's own response to a measured error spectrum; no library propagates it.

Why the white level and not the whole disagreement N: on the sample passes (a girder driven by
ambient vibration) the magnets disagree on the first mode's wavelength as much as the rail shows
there, and a floor drawn from that N (0.128) exceeded the whole calibrated misfit (0.050).
The floor is the misfit an independent draw of the noise would make; the calibrated fit can come out
at or just under it (a single pass whose calibration absorbed part of its own draw: the explanation then
says the fit is at the floor).
Measured: on a generated line at 8 and 10 m/s with a 5 um gap sensor the floor is 0.82 of the misfit
the noise makes against the same recordings without noise (0.66 at 22 and 30 m/s); on a foreign clean
case (two passes, 1 kHz, 5 um gaps) 0.034 of a calibrated 0.059, on the girder sensors off midspan
(their second mode, excited by the 6-10 cm waves the noise hides); the sample passes 0.002 of 0.050.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .evaluate import RecData, _fit_items, fit_mask, model_powers, per_group

# one draw per pass (two on a single pass): the estimate's spread between draws was 3-6 % of it
DRAWS_PER_PASS = 1
MIN_DRAWS = 2


def sensor_noise_psd(gain, k_max_cpm: float | None = None) -> float | None:
    """One magnet profile's white error level [m^2 / (cycle/m)]: the median of its error spectrum
    where the rail was not detected (R = 0: the profiles' disagreement is noise alone), over the
    waves the spectra resolve and below ``k_max_cpm`` (clear of the samples' Nyquist and the profile's
    band edge, above which the spectrum rolls off); the least resolved value when the rail shows everywhere.
    Why white: the gap sensors' noise is white per sample, so along a pass at one speed too; what the
    magnets disagree on beyond it (the girder vibrating under each magnet, a position error) is no
    estimate's noise and is left to the remainder."""
    k = np.asarray(gain.wavenumber_cpm, float)
    ok = (k * gain.segment_m >= 2.0) & (k <= (k_max_cpm or np.inf)) & np.isfinite(gain.noise_psd)
    pure = ok & (np.asarray(gain.rail_psd) <= 0.0)
    if pure.sum() >= 3:
        return float(np.median(gain.noise_psd[pure]))
    return float(np.min(gain.noise_psd[ok])) if ok.any() else None


def rail_error_psd(gain, wavenumber_cpm: np.ndarray, n_profiles: float | None = None,
                   max_wavelength_m: float | None = None, noise_psd: float | None = None) -> np.ndarray:
    """One-sided error spectrum [m^2 / (cycle/m)] of the rail estimated from ``n_profiles`` magnet
    profiles (default: all of the gain's) with the Wiener gain ``gain``
    (:class:`~maglev_ros.irregularity.denoise.RailGain`): R (N / n) / (R + N / n), inside the
    reconstruction's band (waves longer than ``max_wavelength_m`` are not in the twin's rail at all:
    that is no noise, and the fit's items are filtered the same way, :func:`.evaluate.rail_band_filters`).
    ``noise_psd``: a white error level N is capped at (:func:`sensor_noise_psd`)."""
    n = float(n_profiles or gain.n_magnets)
    k = np.asarray(wavenumber_cpm, float)
    R = np.interp(k, gain.wavenumber_cpm, gain.rail_psd, right=0.0)
    N = np.interp(k, gain.wavenumber_cpm, gain.noise_psd, right=float(gain.noise_psd[-1]))
    if noise_psd is not None:
        N = np.minimum(N, noise_psd)
    N = N / max(n, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        E = np.where(R + N > 0, R * N / (R + N), 0.0)
    # waves longer than half the spectra's segment are not resolved by them (their N is a few bins' mean)
    longest = min(max_wavelength_m or np.inf, 0.5 * gain.segment_m)
    E = np.where(k * longest >= 1.0, E, 0.0)
    return np.where(np.isfinite(E), E, 0.0)


def draw_rail_error(rng: np.random.Generator, n_points: int, spacing_m: float, gain,
                    max_wavelength_m: float | None = None, noise_psd: float | None = None) -> np.ndarray:
    """A Gaussian profile (n_points at spacing_m) with the spectrum :func:`rail_error_psd`:
    white noise of unit variance (one-sided spectrum 2 dx) shaped by sqrt(E / (2 dx))."""
    nfft = 1 << int(math.ceil(math.log2(max(n_points, 2))))
    k = np.fft.rfftfreq(nfft, spacing_m)
    shape = np.sqrt(rail_error_psd(gain, k, max_wavelength_m=max_wavelength_m, noise_psd=noise_psd)
                    / (2.0 * spacing_m))
    return np.fft.irfft(np.fft.rfft(rng.standard_normal(nfft)) * shape, nfft)[:n_points]


@dataclass(frozen=True)
class RailFloor:
    """The misfit the gap sensors' noise makes through the rail the twin is driven by, beside the
    calibrated fit (keys ``rail_uncertainty_*``: that part of the rail's uncertainty)."""
    nrmse: float                       # RMS over the fit's items and the draws (the fit's own measure)
    per_group: dict                    # channel group -> RMS over its channels (as fit_per_group)
    per_channel: dict                  # channel -> its NRMSE from the gap noise in the rail (as fit_before's)
    per_pass: dict                     # pass name -> nrmse
    calibrated_nrmse: float
    error_rms_m: float                 # RMS of the rail error the draws carry
    half_gain_wavelength_m: float | None   # where the reconstruction keeps half the rail (all profiles)
    n_draws: int
    channels_most: list = field(default_factory=list)   # channels the floor weighs most on

    @property
    def remainder_nrmse(self) -> float:
        """sqrt(calibrated^2 - floor^2): model error, the other sensors' noise, ambient, other rail errors."""
        return math.sqrt(max(self.calibrated_nrmse ** 2 - self.nrmse ** 2, 0.0))

    def to_dict(self) -> dict:
        return {"rail_uncertainty_nrmse": self.nrmse, "rail_uncertainty_per_group": self.per_group,
                "rail_uncertainty_per_channel": self.per_channel,
                "rail_uncertainty_per_pass": self.per_pass, "calibrated_nrmse": self.calibrated_nrmse,
                "remainder_nrmse": self.remainder_nrmse, "rail_error_rms_m": self.error_rms_m,
                "half_gain_wavelength_m": self.half_gain_wavelength_m, "n_draws": self.n_draws,
                "channels_most": self.channels_most, "explanation": self.explanation()}

    def explanation(self) -> str:
        share = self.nrmse ** 2 / self.calibrated_nrmse ** 2 if self.calibrated_nrmse > 0 else 0.0
        where = (f"; waves shorter than about {100 * self.half_gain_wavelength_m:.0f} cm are mostly noise"
                 if self.half_gain_wavelength_m else "")
        most = f", most on {', '.join(self.channels_most)}" if self.channels_most else ""
        head = (f"The rail the twin is driven by is rebuilt from the magnets' gaps and accelerations; the gap "
                f"sensors' noise blurs its short waves (rail error {1e6 * self.error_rms_m:.1f} um RMS{where}). "
                f"Through the twin another draw of that noise would change the fit by {self.nrmse:.3f}{most}")
        if share >= 0.8:
            # the estimate scatters by ~10 % between draws: this close, the fit is at the floor
            return (f"{head}: about the calibrated fit's {self.calibrated_nrmse:.3f} itself, so the twin fits these "
                    f"recordings as well as their gap noise allows; quieter gap sensors, more instrumented magnets "
                    f"or more passes over the line would lower it, no calibration can.")
        return (f"{head}: {100 * share:.0f} % of the calibrated fit's {self.calibrated_nrmse:.3f} in mean square, "
                f"which no calibration can remove (quieter gap sensors, more instrumented magnets or more passes "
                f"can). The rest ({self.remainder_nrmse:.3f}) is what else the twin misses: model error, the other "
                f"sensors' noise, ambient vibration and the rail's other errors.")


def rail_floor(spec, rds: list[RecData], calibrated_nrmse: float, seed: int = 0) -> RailFloor | None:
    """:class:`RailFloor` of the twin ``spec`` on the passes ``rds`` (as that twin sees them: their
    rails carry the reconstruction's ``rail_gain``); None when no pass has a measured error spectrum
    (one magnet, or no rail, or no reconstructed stretch)."""
    usable = [rd for rd in rds if rd.rec.irregularity is not None
              and (rd.rec.irregularity_info or {}).get("rail_gain") is not None]
    if not usable:
        return None
    rng = np.random.default_rng(seed)
    draws = max(DRAWS_PER_PASS, math.ceil(MIN_DRAWS / len(usable)))
    items_all: list[float] = []
    per_pass: dict[str, float] = {}
    per_chan: dict[str, list] = {}
    err_ms: list[float] = []
    for rd in usable:
        items, chans, ms = _pass_misfits(spec, rd, rng, draws)
        items_all += items
        err_ms += ms
        for n, v in chans.items():
            per_chan.setdefault(n, []).extend(v)
        if items:
            per_pass[rd.rec.name] = float(np.sqrt(np.mean(np.square(items))))
    if not items_all:
        return None
    nrmse = float(np.sqrt(np.mean(np.square(items_all))))
    chan = {n: float(np.sqrt(np.mean(np.square(v)))) for n, v in per_chan.items()}
    groups = per_group(chan, {n: c.group for rd in usable for n, c in rd.rec.channels.items()})
    fitted = {n for rd in usable for n in rd.rec.channels if fit_mask(rd, n).any()}
    ranked = sorted((n for n in chan if n in fitted), key=lambda n: -chan[n])
    most = [n for n in ranked if chan[n] >= 0.8 * chan[ranked[0]]][:4] if ranked else []
    g0 = usable[0].rec.irregularity_info["rail_gain"]
    return RailFloor(nrmse, groups, chan, per_pass, float(calibrated_nrmse), float(math.sqrt(np.mean(err_ms))), g0.cut_wavelength_m(g0.n_magnets), len(err_ms), most)


def _pass_misfits(spec, rd: RecData, rng: np.random.Generator, draws: int):
    """One pass's misfits between the twin on its rail and on that rail plus drawn errors: per fit item
    (the overall measure's), per channel (fit_report's: every usable band) and the drawn errors' mean
    squares."""
    info = rd.rec.irregularity_info
    gain, longest = info["rail_gain"], (info.get("band") or {}).get("max_wavelength_m")
    x, r = (np.asarray(a, float) for a in rd.rec.irregularity)
    white = sensor_noise_psd(gain, _noise_band_top_cpm(rd.rec))
    inside = _valid_window(x, rd.rec)
    if not np.any(inside > 0):                # no reconstructed stretch inside its margins: nothing to perturb
        return [], {}, []
    mp0 = model_powers(spec, rd)
    base_items = _fit_items(spec, rd, mp=mp0)
    items: list[float] = []
    chans: dict[str, list] = {}
    err_ms: list[float] = []
    for _ in range(draws):
        e = draw_rail_error(rng, x.size, float(np.median(np.diff(x))), gain, longest, white) * inside
        err_ms.append(float(np.mean(e[inside > 0] ** 2)))
        rd_e = replace(rd, rec=replace(rd.rec, irregularity=(x, r + e)))
        mp1 = model_powers(spec, rd_e)
        items += [float(np.sqrt(np.sum((b[1] - p[1]) ** 2))) / b[2]
                  for b, p in zip(base_items, _fit_items(spec, rd_e, mp=mp1))]
        for n in rd.rec.channels:
            am = np.sqrt(np.clip(rd.pm[n], 0, None))
            a0, a1 = (np.sqrt(np.clip(p[n], 0, None)) for p in (mp0, mp1))
            ok = np.isfinite(am) & np.isfinite(a0) & np.isfinite(a1) & rd.masks[n][None, :]
            den = float(np.sqrt(np.sum(am[ok] ** 2)))
            if den > 0:
                chans.setdefault(n, []).append(float(np.sqrt(np.sum((a1[ok] - a0[ok]) ** 2))) / den)
    return items, chans, err_ms


def _noise_band_top_cpm(rec) -> float | None:
    """The shortest wave [cycles/m] a profile's error spectrum is read to: 0.8 of the lower of the gap
    samples' Nyquist at the pass's top speed and the profile's own band edge (its ``min_wavelength_m``),
    clear of the roll-off above either (the noise there is filtered, not white)."""
    tops = []
    rates = [c.sample_rate_hz for c in rec.channels.values() if c.group == "gap"]
    v = float(np.nanmax(np.abs(rec.speed_mps))) if rec.speed_mps is not None and np.size(rec.speed_mps) else 0.0
    if rates and v > 0:
        tops.append(0.5 * min(rates) / v)
    shortest = ((rec.irregularity_info or {}).get("band") or {}).get("min_wavelength_m")
    if shortest:
        tops.append(1.0 / float(shortest))
    return 0.8 * min(tops) if tops else None


def _valid_window(x_m: np.ndarray, rec) -> np.ndarray:
    """1 on the stretch where the rail was reconstructed (``irregularity_valid_m``), 0 outside, with a
    raised-cosine ramp over the margin inside each end: outside it the twin's rail is zero and carries
    no reconstruction error to perturb."""
    if rec.irregularity_valid_m is None:
        return np.ones(x_m.size)
    lo, hi = (float(v) for v in rec.irregularity_valid_m)
    ramp = max(float(rec.irregularity_margin_m or 0.0), 1e-9)
    d = np.minimum(x_m - lo, hi - x_m)
    return np.where(d <= 0, 0.0, np.where(d >= ramp, 1.0, 0.5 - 0.5 * np.cos(np.pi * np.clip(d / ramp, 0, 1))))
