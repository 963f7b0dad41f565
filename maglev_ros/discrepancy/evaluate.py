"""Measured vs modelled band powers: noise floor, ambient shape, residual vectors, NRMSE.

Model band power of a channel = twin (deterministic) + ambient (stochastic extension, if any) +
sensor noise floor, added as powers (independent parts). The noise floor is estimated once per
recording from quiet frames (the twin predicts almost nothing there: vehicle off the line) as a
smooth power law in frequency (Theil-Sen in log-log, robust to a few odd bands), with the bands
holding guideway modes left out for guideway channels: structural vibration (e.g. from adjacent
lines) shows as peaks at the modes and must not be absorbed into "noise".

The vehicle side is compared through features the reconstructed irregularity cannot rule: each
magnet's gap-to-rail transmissibility (:func:`.features.rail_transmissibility`, the levitation
loop's |S(f)|^2) and its gap's frame means (sensor offsets and drifts), besides the magnet
accelerations' band amplitudes; the gap's own band amplitudes are shown but not fitted
(:func:`fit_mask`). Car-body accelerometers (optional topic) enter through their body-to-magnet
transmissibility (:func:`body_transmissibility`) above ``BODY_MIN_HZ``: on a clean case the twin
driven by the reconstructed rail under-predicted every vehicle channel by ~30 % alike (magnet
accel 6-10 Hz: measured/twin 1.35, car body 1.31), which the ratio cancels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from maglev_ros.irregularity.integration import DEFAULT_FILTER_ORDER

from .features import (S_MIN_HZ, FrameGrid, band_powers, frame_grid, frame_means, nrmse_amplitude, rail_transmissibility,
                       usable_bands, without_long_waves)
from .model import ModelSpec, guideway_modal, predict, reference_value
from .irregularity import vehicle_over_valid
from .recording import Recording

QUIET_REL = 1e-3
MIN_QUIET_FRAMES = 4          # ~1.25 s of 0.5 s frames at a 0.25 s hop: a background measured, not one frame
RAIL_SNR = 10.0      # rail band power over its noise below which a transmissibility cell is not used
BODY_MIN_HZ = 3.0    # car-body bands below this are ruled by waves longer than the reconstruction
                     # (clean case, 0-3 Hz: body/magnet ratio measured 5.8, twin 1.4)


@dataclass(frozen=True)
class Selection:
    """Which fitted items (:func:`_fit_items`) a measure uses: those built from any of ``channels``,
    or (``own``) only from them; ``levels``: with the gaps' frame means. A plain set of channel
    names means ``Selection(channels)``."""
    channels: frozenset
    own: bool = False
    levels: bool = True
    # ((recording source, frame mask), ...): only those frames of those recordings (others whole)
    frames: tuple = ()

    def takes(self, kind: str, names: tuple) -> bool:
        if kind == "level" and not self.levels:
            return False
        return set(names) <= self.channels if self.own else bool(set(names) & self.channels)

    def frame_mask(self, rd: "RecData") -> np.ndarray | None:
        for src, m in self.frames:
            if src == rd.rec.source:
                return np.asarray(m, bool)
        return None

    def on_frames(self, rd: "RecData", mask) -> "Selection":
        """This selection on the frames ``mask`` of ``rd`` only."""
        keep = tuple((s, m) for s, m in self.frames if s != rd.rec.source)
        return replace(self, frames=keep + ((rd.rec.source, tuple(bool(x) for x in mask)),))


def levitation_items(channels) -> Selection:
    """The items levitation physics (control, magnetic force) is fitted and judged on: the magnets'
    acceleration bands and gap-to-rail transmissibilities. Not the car-body-to-magnet ratios (their
    ~17 % model error is the suspension's; a 1.2 x current saturation left them unchanged, 0.087 with and
    without, and diluted its signature 30-50 % -> 3 %) nor the gaps' frame means (ruled by waves
    longer than the reconstructed rail keeps: 0.19-0.21 on the slower pass with the reconstructed rail,
    0.005-0.008 with the true one)."""
    return Selection(frozenset(channels), own=True, levels=False)


def _selection(channels) -> Selection | None:
    if channels is None or isinstance(channels, Selection):
        return channels
    return Selection(frozenset(channels)) if channels else None


@dataclass(eq=False)
class RecData:
    rec: Recording
    grid: FrameGrid
    pm: dict                         # measured band powers
    masks: dict                      # usable bands per channel (bool, n_bands)
    noise: dict = field(default_factory=dict)    # (n_bands,) noise floor per channel
    quiet: dict = field(default_factory=dict)    # (n_frames,) quiet-frame mask per channel
    # (n_bands,) per guideway channel: its quiet frames' mean band power above the noise floor from half
    # the twin's lowest mode up (the line ringing with the vehicle away: ambient excitation, if any)
    background: dict = field(default_factory=dict)
    # per magnet with an accel and a gap channel: key -> (accel, gap) names, measured squared
    # gap-to-rail transmissibility (n_frames, n_bands) and its usable bands
    sens_pairs: dict = field(default_factory=dict)
    sens: dict = field(default_factory=dict)
    sens_masks: dict = field(default_factory=dict)
    # per such gap channel: measured frame means minus the rest value (n_frames,) and the gap's
    # whole amplitude over the compared frames (their scale)
    level: dict = field(default_factory=dict)
    level_den: dict = field(default_factory=dict)
    # per car-body channel: the magnet accel channels it is compared with, its measured squared
    # body-to-magnet transmissibility (n_frames, n_bands) and the bands used
    body_pairs: dict = field(default_factory=dict)
    body: dict = field(default_factory=dict)
    body_masks: dict = field(default_factory=dict)


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


def rail_band_filters(rec: Recording) -> tuple[tuple[float, int], ...] | None:
    """The filters (time corner [Hz], Butterworth order) through which the twin's rail of this pass
    holds the rail's long waves: the reconstruction's time high-pass and its spatial band edge seen
    at the pass's speed (both zero-phase, :mod:`maglev_ros.irregularity.profile`). None when the
    twin runs without a reconstructed rail."""
    if rec.irregularity is None:
        return None
    info = rec.irregularity_info or {}
    band = info.get("band") or {}
    hp = band.get("highpass_hz")
    if not hp:
        return None
    order = int(((band.get("filter") or {}).get("order")) or DEFAULT_FILTER_ORDER)
    out = [(float(hp), order)]
    wl = band.get("max_wavelength_m")
    v = float(np.nanmean(np.abs(rec.speed_mps))) if rec.speed_mps is not None and rec.speed_mps.size else 0.0
    if wl and v > 0:
        out.append((v / float(wl), order))
    return tuple(out)


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
    # where the line can ring: from half its lowest mode up (below it a girder moves quasi-statically,
    # and a sensor's own offset or drift lives in the lowest bands)
    ringing = grid.edges_hz[:-1] >= 0.5 * float(modal.freq_hz.min()) if modal.freq_hz.size else excl
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
        floor = fit_noise_floor(src[quiet], grid, masks[n], ex)
        # a power law extrapolated into bands where the quiet frames hold far less would call
        # "noise" more than the channel measures at all (a gap floor fitted above 3 Hz put 10x the
        # measured amplitude into the 0-3 Hz band; a magnet accelerometer's floor from frames of a
        # slow pass put 4x it there): noise is part of what is measured, so in every band the
        # floor never exceeds the mean measured power of the frames it was estimated from (nor,
        # for the residual's floor, the residual's own mean power there)
        with np.errstate(invalid="ignore"):
            cap = np.nanmean(pm[n][quiet], axis=0) if quiet.any() else np.full(grid.n_bands, np.nan)
            if src is not pm[n]:
                cap = np.fmin(np.nanmean(src[quiet], axis=0), cap)
        floor = np.where(np.isfinite(cap), np.minimum(floor, cap), floor)
        rd.noise[n] = floor
        if src is pm[n] and ch.group.startswith("guideway") and quiet.sum() >= MIN_QUIET_FRAMES:
            rd.background[n] = np.where(masks[n] & ringing & np.isfinite(cap), np.clip(cap - floor, 0.0, None), 0.0)
    for key, (a, g) in transmissibility_pairs(rec).items():
        ca, cg = rec.channels[a], rec.channels[g]
        s, py = rail_transmissibility(ca.time_s, ca.values, np.interp(ca.time_s, cg.time_s, cg.values),
                                      ca.sample_rate_hz, grid, with_rail_power=True)
        s[~np.all(np.isfinite(pm[g]), axis=1)] = np.nan
        # only where the rail under the magnet is measured well above the sensors' noise (on a
        # smooth guideway the ratio is one of noises: NRMSE 0.5 against a twin without noise)
        noise_y = rd.noise[g] + rd.noise[a] / (2 * np.pi * np.maximum(grid.band_center_hz, S_MIN_HZ)) ** 4
        with np.errstate(invalid="ignore"):
            s[~(py > RAIL_SNR * noise_y[None, :])] = np.nan
        m = masks[a] & masks[g] & np.any(np.isfinite(s), axis=0)
        if m.any():
            rd.sens_pairs[key], rd.sens[key], rd.sens_masks[key] = (a, g), s, m
            lv = frame_means(cg.time_s, without_long_waves(cg.values - refs[g], cg.sample_rate_hz, rail_band_filters(rec)),
                             cg.sample_rate_hz, grid)
            lv[~np.all(np.isfinite(pm[g]), axis=1)] = np.nan
            # scale: the gap's whole signal over those frames (frame means and dynamics), so that a
            # smooth guideway (tiny gap dynamics) does not blow the level misfit up
            dyn = pm[g][:, masks[g] & (grid.edges_hz[:-1] >= 3.0)]
            rd.level[g], rd.level_den[g] = lv, float(np.sqrt(np.nansum(dyn) + np.nansum(lv ** 2))) or 1.0
    mags = [n for n, c in rec.channels.items() if c.group == "vehicle_accel"]
    for b in rec.names("body_accel") if mags else []:
        ratio = body_transmissibility(pm[b], [pm[m] for m in mags])
        ok = (pm[b] > RAIL_SNR * rd.noise[b][None, :]) & np.all(
            [pm[m] > RAIL_SNR * rd.noise[m][None, :] for m in mags], axis=0)
        ratio[~ok] = np.nan
        m = masks[b] & (grid.edges_hz[:-1] >= BODY_MIN_HZ) & np.any(np.isfinite(ratio), axis=0)
        if m.any():
            rd.body_pairs[b], rd.body[b], rd.body_masks[b] = tuple(mags), ratio, m
    return rd


def body_transmissibility(p_body: np.ndarray, p_magnets: list) -> np.ndarray:
    """Squared body-to-magnet transmissibility per frame and band: the car-body channel's band power
    over the mean band power of the magnet accelerations (the air-spring path's |T(f)|^2 seen
    through the magnets that drive it; the rail's amplitude cancels)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return p_body / np.mean(p_magnets, axis=0)


_AMB_CACHE: dict = {}


def ambient_shape(spec: ModelSpec, rd: RecData) -> dict:
    """Band power per unit modal-force PSD (1 N^2/Hz per mass-normalised mode) at guideway sensors."""
    key = (spec.physics_only(), id(rd))
    hit = _AMB_CACHE.get(key)
    if hit is not None and hit[0] is rd:
        return hit[1]
    out = _ambient_shape(spec, rd)
    if len(_AMB_CACHE) > 256:
        _AMB_CACHE.clear()
    _AMB_CACHE[key] = (rd, out)
    return out


def ambient_powers(spec: ModelSpec, rd: RecData) -> dict:
    """Ambient band powers of the guideway channels: 10^level * shape * (f_band / 20 Hz)^slope, or
    with a measured background (``spec.ambient_background``: the channels it names, as measured on
    the pass it was fitted on) 10^level times the background of ``rd``'s own quiet stretches where
    it has them (ambient vibration from traffic and ground changes between recordings; each pass
    measures its own), else that pass's."""
    if spec.ambient_log10_psd is None:
        return {}
    if spec.ambient_background:
        lvl = 10.0 ** spec.ambient_log10_psd
        own = {n: bg for n, bg in rd.background.items() if len(bg) == rd.grid.n_bands}
        return {n: lvl * np.asarray(own.get(n, bg)) for n, bg in spec.ambient_background
                if n in rd.rec.channels and len(own.get(n, bg)) == rd.grid.n_bands}
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


def transmissibility_pairs(rec: Recording) -> dict:
    """Magnets with both an acceleration and a gap channel: {"M<k> gap/rail": (accel, gap)}."""
    acc = {c.magnet: n for n, c in rec.channels.items() if c.group == "vehicle_accel" and c.magnet is not None}
    gap = {c.magnet: n for n, c in rec.channels.items() if c.group == "gap" and c.magnet is not None}
    return {f"M{k} gap/rail": (acc[k], gap[k]) for k in sorted(set(acc) & set(gap))}


def _sens_of(rd: RecData, pred: dict) -> dict:
    out = {}
    for key, (a, g) in rd.sens_pairs.items():
        ca = rd.rec.channels[a]
        out[key] = rail_transmissibility(ca.time_s, pred[a], np.interp(ca.time_s, rd.rec.channels[g].time_s, pred[g]),
                                         ca.sample_rate_hz, rd.grid)
    return out


def _levels_of(rd: RecData, pred: dict) -> dict:
    out = {}
    for g in rd.level:
        ch = rd.rec.channels[g]
        y = without_long_waves(pred[g] - reference_value(rd.rec, g), ch.sample_rate_hz, rail_band_filters(rd.rec))
        out[g] = frame_means(ch.time_s, y, ch.sample_rate_hz, rd.grid)
    return out


def _twin_powers(spec: ModelSpec, rd: RecData) -> tuple[dict, dict]:
    """Band powers and rail transmissibilities of the physics-only prediction (cached per physics
    spec and recording; the prediction itself is not kept: a few MB per entry, hundreds of
    entries in a diagnosis)."""
    phys = spec.physics_only()
    key = (phys, id(rd))
    hit = _PT_CACHE.get(key)
    if hit is not None and hit[0] is rd:
        return hit[1], hit[2]
    pred = predict(phys, rd.rec)
    pt = {n: band_powers(ch.time_s, pred[n] - reference_value(rd.rec, n), ch.sample_rate_hz, rd.grid)
          for n, ch in rd.rec.channels.items()}
    st = _sens_of(rd, pred)
    st.update(_levels_of(rd, pred))
    if len(_PT_CACHE) > 512:
        _PT_CACHE.clear()
    _PT_CACHE[key] = (rd, pt, st)
    return pt, st


def model_transmissibility(spec: ModelSpec, rd: RecData) -> dict:
    """The twin's squared gap-to-rail transmissibility per magnet pair of ``rd`` and its gap frame
    means (keyed by the gap channel), with the spec's sensor errors and dropouts when they touch
    those channels."""
    _, st = _twin_powers(spec, rd)
    touched = {e[0] for e in spec.sensor_error} | {d[0] for d in spec.dropouts}
    if any(set(p) & touched for p in rd.sens_pairs.values()):
        pred = predict(spec, rd.rec)
        st = dict(st)
        st.update({k: v for k, v in _sens_of(rd, pred).items() if set(rd.sens_pairs[k]) & touched})
        st.update({k: v for k, v in _levels_of(rd, pred).items() if k in touched})
    return st


def model_powers(spec: ModelSpec, rd: RecData) -> dict:
    pt, _ = _twin_powers(spec, rd)
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


def fit_mask(rd: RecData, name: str) -> np.ndarray:
    """Bands of a channel that enter the fit measures (residual vector, overall NRMSE). A gap
    channel of a magnet with a rail transmissibility enters through that feature only: its band
    amplitudes are ruled by the reconstructed irregularity that drives the twin (measured on a
    clean case: gap NRMSE 0.24-0.36 with the reconstructed rail, 0.014 with the true one; kept in
    the 0-3 Hz band, the low-frequency tracking of waves longer than the reconstruction's band
    pulled kp and kv 25-30 % off), while the transmissibility carries the levitation physics. A
    car-body channel with magnet accelerations beside it enters through its body-to-magnet
    transmissibility alike."""
    m = rd.masks[name]
    if name in rd.body_pairs or any(g == name for _, g in rd.sens_pairs.values()):
        return np.zeros_like(m)
    return m


def _fit_items(spec: ModelSpec, rd: RecData, only=None, mp: dict | None = None,
               names_out: list | None = None) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """(measured, modelled, scale) of every fitted channel/feature of one recording: band
    amplitudes of the channels (over :func:`fit_mask`), each magnet's gap-to-rail transmissibility
    and the frame means of its gap (its mean, an offset of the gap sensor, and its slow variation
    above the rail reconstruction's corner, :func:`.features.without_long_waves`; scaled by the
    gap's whole amplitude over those frames).
    ``only``: a set of channel names (then only those channels and the features built from them) or
    a :class:`Selection`. ``mp``: the model band powers when the caller has them. ``names_out`` (a
    list) receives (kind, channel names, frame of each row) of each item: kind is "bands",
    "transmissibility", "level" or "body"."""
    mp = model_powers(spec, rd) if mp is None else mp
    ms = model_transmissibility(spec, rd) if rd.sens else {}
    out = []
    sel = _selection(only)
    fm = sel.frame_mask(rd) if sel is not None else None

    def use(kind, *names):
        return sel is None or sel.takes(kind, names)

    def add(am, at, den=None, names=(), kind="bands"):
        fr = np.broadcast_to(np.arange(am.shape[0]).reshape((-1,) + (1,) * (am.ndim - 1)), am.shape)
        ok = np.isfinite(am) & np.isfinite(at)
        if fm is not None:
            ok &= fm[fr]
        if names_out is not None:
            names_out.append((kind, tuple(names), fr[ok]))
        am, at = am[ok], at[ok]
        out.append((am, at, den if den is not None else (float(np.sqrt(np.sum(am ** 2))) or 1.0)))

    def amp(meas, mod, m, names, kind):   # band powers -> amplitudes over the bands m
        add(np.sqrt(np.clip(meas[:, m], 0, None)), np.sqrt(np.clip(mod[:, m], 0, None)), names=names, kind=kind)
    for n in rd.rec.channels:
        m = fit_mask(rd, n)
        if m.any() and use("bands", n):
            amp(rd.pm[n], mp[n], m, (n,), "bands")
    for k in rd.sens:
        if use("transmissibility", *rd.sens_pairs[k]):
            amp(rd.sens[k], ms[k], rd.sens_masks[k], rd.sens_pairs[k], "transmissibility")
    for g in rd.level:
        if use("level", g):
            add(rd.level[g], ms[g], rd.level_den[g], (g,), "level")
    for b, mags in rd.body_pairs.items():
        if use("body", b, *mags):
            amp(rd.body[b], body_transmissibility(mp[b], [mp[m] for m in mags]), rd.body_masks[b], (b, *mags), "body")
    return out


def residual_vector(spec: ModelSpec, rds: list[RecData], channels=None) -> np.ndarray:
    """Normalised residuals of every fitted channel/feature (:func:`_fit_items`), each weighted
    equally within a recording. ``channels``: only those channels and the features built from them
    (or a :class:`Selection`)."""
    parts = []
    nrec = len(rds)
    only = _selection(channels)
    for rd in rds:
        items = _fit_items(spec, rd, only)
        for am, at, den in items:
            parts.append((am - at) / den / math.sqrt(len(items) * nrec))
    return np.concatenate(parts)


def residual_rows(spec: ModelSpec, rds: list[RecData], channels) -> np.ndarray:
    """Mask over :func:`residual_vector` (all channels): True on the rows of the items built from
    ``channels`` (or a :class:`Selection`; the restricted vector keeps those rows, only scaled otherwise)."""
    sel = _selection(channels) or Selection(frozenset())
    rows = []
    for rd in rds:
        names: list = []
        _fit_items(spec, rd, names_out=names)
        fm = sel.frame_mask(rd)
        rows += [(fm[fr] if fm is not None else np.ones(fr.size, bool)) & sel.takes(kind, nm)
                 for kind, nm, fr in names]
    return np.concatenate(rows) if rows else np.zeros(0, bool)


def split_frames(spec: ModelSpec, rd: RecData, select: Selection, min_frames: int = 3):
    """(first, second): masks over ``rd``'s frames that carry items of ``select``, its first and its
    second half in time, apart by at least one frame length (no sample in both); None when either
    half would hold fewer than ``min_frames`` frames."""
    names: list = []
    _fit_items(spec, rd, select, names_out=names)
    fr = np.unique(np.concatenate([f for _, _, f in names])) if names else np.zeros(0, int)
    if fr.size < 2 * min_frames:
        return None
    t = rd.grid.t_center_s
    first = np.zeros(rd.grid.n_frames, bool)
    first[fr[:fr.size // 2]] = True
    t_end = t[first].max() + rd.grid.frame_s / 2
    second = np.zeros_like(first)
    later = fr[t[fr] - rd.grid.frame_s / 2 >= t_end - 1e-9]
    second[later] = True
    if later.size < min_frames:
        return None
    return first, second


def fit_report(spec: ModelSpec, rds: list[RecData], channels=None) -> tuple[float, dict]:
    """Overall NRMSE (RMS over the recordings' fitted channels and features, :func:`_fit_items`:
    the measure every fit and acceptance uses) and per-channel NRMSE of every measured channel
    over all its usable bands (mean over recordings; a gap channel judged through its magnet's
    transmissibility and frame means shows here for information only, see :func:`fit_mask`).
    ``channels``: restrict the overall NRMSE to those channels and their features (or a
    :class:`Selection`; all if None or if none of them is fitted)."""
    only = _selection(channels)
    per: dict[str, list] = {}
    allv: list[float] = []
    for rd in rds:
        mp = model_powers(spec, rd)
        for n in rd.rec.channels:
            per.setdefault(n, []).append(nrmse_amplitude(rd.pm[n], mp[n], rd.masks[n][None, :]))
        items = (_fit_items(spec, rd, only, mp) if only else []) or _fit_items(spec, rd, mp=mp)
        allv += [float(np.sqrt(np.sum((am - at) ** 2))) / den for am, at, den in items]
    pc = {n: float(np.mean(v)) for n, v in per.items()}
    return float(np.sqrt(np.mean(np.square(allv)))) if allv else 0.0, pc


def per_group(per_channel: dict, groups: dict) -> dict:
    """RMS of the per-channel NRMSE within each channel group (``groups``: channel -> group)."""
    out: dict[str, list] = {}
    for n, v in per_channel.items():
        out.setdefault(groups.get(n, "other"), []).append(v)
    return {g: float(np.sqrt(np.mean(np.square(v)))) for g, v in out.items()}
