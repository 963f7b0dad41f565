"""Measured vs modelled band powers: noise floor, ambient shape, residual vectors, NRMSE.

Model band power of a channel = twin (deterministic) + ambient (stochastic extension, if any) +
sensor noise floor, added as powers (independent parts). The noise floor is estimated once per
recording from quiet frames (the twin predicts almost nothing there: vehicle off the line) as a
smooth power law in frequency (Theil-Sen in log-log, robust to a few odd bands), with the bands
holding guideway modes left out for guideway channels: structural vibration (e.g. from adjacent
lines) shows as peaks at the modes and must not be absorbed into "noise".
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from .features import FrameGrid, band_powers, frame_grid, nrmse_amplitude, usable_bands
from .model import ModelSpec, guideway_modal, predict, reference_value
from .irregularity import vehicle_over_valid
from .recording import Recording

QUIET_REL = 1e-3


@dataclass(eq=False)
class RecData:
    rec: Recording
    grid: FrameGrid
    pm: dict                         # measured band powers
    masks: dict                      # usable bands per channel (bool, n_bands)
    noise: dict = field(default_factory=dict)    # (n_bands,) noise floor per channel
    quiet: dict = field(default_factory=dict)    # (n_frames,) quiet-frame mask per channel


def _modal_bands(grid: FrameGrid, freqs_hz: np.ndarray, rel: float = 0.12) -> np.ndarray:
    e = grid.edges_hz
    m = np.zeros(grid.n_bands, bool)
    for f in freqs_hz:
        m |= (e[1:] >= f * (1 - rel)) & (e[:-1] <= f * (1 + rel))
    return m


def fit_noise_floor(p_frames: np.ndarray, grid: FrameGrid, usable: np.ndarray, exclude: np.ndarray) -> np.ndarray:
    """Smooth power-law noise floor (n_bands,) from band powers of quiet frames."""
    mean = np.nanmean(p_frames, axis=0) if p_frames.shape[0] else np.full(grid.n_bands, np.nan)
    from .features import band_widths
    width = band_widths(grid)
    fc = np.maximum(grid.band_center_hz, 1.0)
    sel = usable & ~exclude & np.isfinite(mean) & (mean > 0)
    if sel.sum() < 3:
        sel = usable & np.isfinite(mean) & (mean > 0)
    if sel.sum() < 2:
        return np.where(np.isfinite(mean), mean, 0.0)
    slope, icpt, _, _ = stats.theilslopes(np.log(mean[sel] / width[sel]), np.log(fc[sel]))
    return width * np.exp(icpt + slope * np.log(fc))


def prepare(rec: Recording, base: ModelSpec) -> RecData:
    grid = frame_grid(rec)
    refs = {n: reference_value(rec, n) for n in rec.channels}
    pm, masks = {}, {}
    for n, ch in rec.channels.items():
        pm[n] = band_powers(ch.time_s, ch.values - refs[n], ch.sample_rate_hz, grid)
        masks[n] = usable_bands(grid, ch.sample_rate_hz)
    # vehicle channels: only frames with the whole vehicle over the valid irregularity (outside
    # it the twin input is zero); excluded frames are NaN and drop out of every measure
    if rec.irregularity_valid_m is not None:
        offs = base.config.vehicle.magnet_offsets_m
        t_lo = grid.t_center_s - grid.frame_s / 2
        t_hi = grid.t_center_s + grid.frame_s / 2
        ok = vehicle_over_valid(rec, t_lo, offs) & vehicle_over_valid(rec, t_hi, offs)
        for n, ch in rec.channels.items():
            if ch.on_vehicle:
                pm[n][~ok] = np.nan
    rd = RecData(rec, grid, pm, masks)
    # quiet frames and noise floor from the nominal twin
    pred = predict(base, rec)
    modal = guideway_modal(base)
    excl = _modal_bands(grid, modal.freq_hz[modal.freq_hz < 200])
    for n, ch in rec.channels.items():
        pt = band_powers(ch.time_s, pred[n] - refs[n], ch.sample_rate_hz, grid)
        tot = np.nansum(pt, axis=1)
        quiet = tot <= QUIET_REL * max(np.nanmax(tot), 1e-300) if np.nanmax(tot) > 0 else np.ones_like(tot, bool)
        quiet &= np.all(np.isfinite(pm[n]), axis=1)
        src = pm[n]
        if quiet.sum() < 2:
            # never quiet (vehicle channels on an irregular guideway): the floor comes from the
            # measured-minus-twin signal in its quietest fifth of the frames (an upper bound of the
            # noise, tighter than the measured signal itself)
            src = band_powers(ch.time_s, ch.values - pred[n], ch.sample_rate_hz, grid)
            src[~np.all(np.isfinite(pm[n]), axis=1)] = np.nan
            fin = np.flatnonzero(np.all(np.isfinite(src), axis=1))
            order = fin[np.argsort(np.sum(src[fin], axis=1))]
            quiet = np.zeros_like(quiet)
            quiet[order[:max(2, len(order) // 5)]] = True
        rd.quiet[n] = quiet
        ex = excl if ch.group.startswith("guideway") else np.zeros_like(excl)
        rd.noise[n] = fit_noise_floor(src[quiet], grid, masks[n], ex)
    return rd


_AMB_CACHE: dict = {}


def ambient_shape(spec: ModelSpec, rd: RecData) -> dict:
    """Band power per unit modal-force PSD (1 N^2/Hz per mass-normalised mode) at guideway sensors."""
    key = (spec.with_(sensor_error=(), ambient_log10_psd=None, ambient_slope=0.0, dropouts=()), id(rd))
    hit = _AMB_CACHE.get(key)
    if hit is not None and hit[0] is rd:
        return hit[1]
    out = _ambient_shape(spec, rd)
    if len(_AMB_CACHE) > 256:
        _AMB_CACHE.clear()
    _AMB_CACHE[key] = (rd, out)
    return out


def ambient_powers(spec: ModelSpec, rd: RecData) -> dict:
    """Ambient band powers of the guideway channels: 10^level * shape * (f_band / 20 Hz)^slope."""
    if spec.ambient_log10_psd is None:
        return {}
    fc = np.maximum(rd.grid.band_center_hz, 1.0)
    w = (10.0 ** spec.ambient_log10_psd) * (fc / 20.0) ** spec.ambient_slope
    return {n: v * w for n, v in ambient_shape(spec, rd).items()}


def _ambient_shape(spec: ModelSpec, rd: RecData) -> dict:
    modal = guideway_modal(spec)
    out = {}
    f = np.linspace(0.25, rd.grid.edges_hz[-1], 4000)
    df = f[1] - f[0]
    w = 2 * np.pi * f
    H2 = 1.0 / ((modal.omega_rad_s[None, :] ** 2 - w[:, None] ** 2) ** 2
                + (2 * modal.damping_ratio[None, :] * modal.omega_rad_s[None, :] * w[:, None]) ** 2)
    from .features import band_weights
    W = band_weights(rd.grid, f)
    for n, ch in rd.rec.channels.items():
        if not ch.group.startswith("guideway") or ch.position_m is None:
            continue
        phi2 = modal.shapes_at([ch.position_m])[0] ** 2
        psd = H2 @ phi2 * (w ** 4 if ch.group == "guideway_accel" else 1.0)
        out[n] = (W @ psd) * df
    return out


_PT_CACHE: dict = {}


def _twin_powers(spec: ModelSpec, rd: RecData) -> tuple[dict, dict]:
    """Band powers of the physics-only prediction (cached per physics spec and recording)."""
    phys = spec.with_(sensor_error=(), ambient_log10_psd=None, ambient_slope=0.0, dropouts=())
    key = (phys, id(rd))
    hit = _PT_CACHE.get(key)
    if hit is not None and hit[0] is rd:
        return hit[1], hit[2]
    pred = predict(phys, rd.rec)
    pt = {n: band_powers(ch.time_s, pred[n] - reference_value(rd.rec, n), ch.sample_rate_hz, rd.grid)
          for n, ch in rd.rec.channels.items()}
    if len(_PT_CACHE) > 512:
        _PT_CACHE.clear()
    _PT_CACHE[key] = (rd, pt, pred)
    return pt, pred


def model_powers(spec: ModelSpec, rd: RecData) -> dict:
    pt, pred_phys = _twin_powers(spec, rd)
    touched = {e[0] for e in spec.sensor_error} | {d[0] for d in spec.dropouts}
    pt = dict(pt)
    if touched & set(rd.rec.channels):
        pred = predict(spec, rd.rec)
        for n in touched & set(rd.rec.channels):
            ch = rd.rec.channels[n]
            pt[n] = band_powers(ch.time_s, pred[n] - reference_value(rd.rec, n), ch.sample_rate_hz, rd.grid)
    out = {}
    amb = ambient_powers(spec, rd)
    for n, ch in rd.rec.channels.items():
        p = pt[n] + rd.noise[n][None, :]
        if n in amb:
            p = p + amb[n][None, :]
        out[n] = p
    return out


def residual_vector(spec: ModelSpec, rds: list[RecData]) -> np.ndarray:
    parts = []
    nrec = len(rds)
    for rd in rds:
        mp = model_powers(spec, rd)
        nch = len(rd.rec.channels)
        for n in rd.rec.channels:
            am = np.sqrt(np.clip(rd.pm[n][:, rd.masks[n]], 0, None))
            at = np.sqrt(np.clip(mp[n][:, rd.masks[n]], 0, None))
            ok = np.isfinite(am) & np.isfinite(at)
            den = np.sqrt(np.sum(am[ok] ** 2)) or 1.0
            parts.append(((am - at)[ok] / den / math.sqrt(nch * nrec)).ravel())
    return np.concatenate(parts)


def fit_report(spec: ModelSpec, rds: list[RecData]) -> tuple[float, dict]:
    """Overall NRMSE (RMS over channels and recordings) and per-channel NRMSE (mean over recs)."""
    per: dict[str, list] = {}
    for rd in rds:
        mp = model_powers(spec, rd)
        for n in rd.rec.channels:
            per.setdefault(n, []).append(nrmse_amplitude(rd.pm[n], mp[n], rd.masks[n][None, :]))
    pc = {n: float(np.mean(v)) for n, v in per.items()}
    allv = [x for v in per.values() for x in v]
    return float(np.sqrt(np.mean(np.square(allv)))) if allv else 0.0, pc
