"""Where twin and recording differ: per channel, time (-> position along the line), band, group.

For every channel, frame and band the measured band power Pm is compared with the model's
Pmod = twin + noise floor (+ stochastic extensions). A cell is a mismatch only if BOTH
- the amplitude differs by more than the estimation scatter of a band power (relative error of
  sqrt(P) above max(0.3, 3 / sqrt(dof)), dof = 2 x periodogram bins in the band), and
- the residual power exceeds 3 x the noise floor of that band,
so sensor noise (and the random scatter of its band powers) is never called a mismatch.

Noise floor (:func:`local_noise_floor`): the model's smooth power-law floor (from
:mod:`.evaluate`) is a good summary but can fall below the real sensor noise in some bands (1/f
or brown noise piles up in the lowest band, anti-alias filters bend the top). So the floor used
here is, per channel and band, never below what the recording itself shows where the twin
predicts (almost) nothing: the quiet cells (frame, band) with twin power <= ``QUIET_TWIN_REL`` x the
model floor (guideway sensors: vehicle off their span; vehicle sensors: only bands where the twin
is quiet in every frame, e.g. above the vehicle's response, since a vehicle is never at rest). Their level is a clipped
mean (cells above the 99 % point of the fitted Gamma scatter, at least 4 x the median, dropped: robust to a minority of frames holding a real effect,
nearly unbiased for chi-square-scattered noise). In bands that hold a guideway mode (+-12 %, from
the nominal design in the recording's metadata) a guideway channel's floor is interpolated in
log-log from the neighbouring mode-free bands instead, so structural vibration before/after the
vehicle (adjacent lines, ground vibration) stays a mismatch and is not absorbed into "noise".
Cells are grouped per channel group into connected regions (scipy.ndimage.label over
frames x bands); each region becomes a ``Mismatch`` with its channels, time, the span of the line
the vehicle covered meanwhile (guideway sensors' own positions when no vehicle is on the line),
band and severity (mean residual power over the noise floor). Hand-written statistics (a clipped
mean and a log-log interpolation): no library offers a band-power noise floor of this kind.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.stats import gamma as gamma_dist

from .evaluate import RecData, fit_mask
from .recording import GROUPS


@dataclass(frozen=True)
class Mismatch:
    channels: tuple[str, ...]
    time_s: tuple[float, float]
    position_m: tuple[float, float] | None
    frequency_hz: tuple[float, float] | None
    severity: float
    group: str = ""
    recording: str = ""
    peer_amplitude_ratio: float | None = None     # persistent misfits: amplitude ratio to the peers'
    explanation: str = ""                         # what it means, where the band alone does not say it

    def to_dict(self) -> dict:
        return {"channels": list(self.channels), "time_s": [float(self.time_s[0]), float(self.time_s[1])],
                "position_m": None if self.position_m is None else [float(x) for x in self.position_m],
                "frequency_hz": None if self.frequency_hz is None else [float(x) for x in self.frequency_hz],
                "severity": float(self.severity), **({"explanation": self.explanation} if self.explanation else {})}


@dataclass
class ResidualMap:
    """Per channel (frames x bands): severity (residual power / noise floor, signed) and flags."""
    rd: RecData
    severity: dict
    flags: dict
    rel: dict
    floor: dict = field(default_factory=dict)


QUIET_TWIN_REL = 1e-3     # a frame is quiet when the twin predicts <= this x its busiest frame
# one flagged cell alone is a region when the measured amplitude is >= 2x the model's and the
# residual >= 30x the noise floor (a short free decay of an unmodelled resonance: one 0.5 s frame)
STRONG_REL, STRONG_SEV = 1.0, 30.0
MIN_QUIET_CELLS = 3
CLIP_REL_MEDIAN = 4.0


def _modal_band_mask(rd: RecData, rel: float = 0.12) -> np.ndarray:
    """Bands holding a guideway mode of the nominal design (+-rel), from the recording's metadata."""
    key = id(rd.rec.metadata)
    hit = _MODAL_CACHE.get(key)
    if hit is not None and hit[0] is rd.rec.metadata:
        freqs = hit[1]
    else:
        try:
            from .model import base_spec, guideway_modal
            freqs = np.asarray(guideway_modal(base_spec(rd.rec.metadata)).freq_hz, float)
        except Exception:           # no line / design usable: no band is protected
            freqs = np.zeros(0)
        if len(_MODAL_CACHE) > 64:
            _MODAL_CACHE.clear()
        _MODAL_CACHE[key] = (rd.rec.metadata, freqs)
    e = rd.grid.edges_hz
    m = np.zeros(rd.grid.n_bands, bool)
    for f in freqs:
        m |= (e[1:] >= f * (1 - rel)) & (e[:-1] <= f * (1 + rel))
    return m


_MODAL_CACHE: dict = {}


def _clipped_mean(x: np.ndarray, k: float = np.inf) -> float:
    """Mean of x without values above the 99 % point of a Gamma(k) scatter around the median
    (at least ``CLIP_REL_MEDIAN`` x the median): robust to a minority of cells holding a real
    effect, nearly unbiased for band powers of noise however heavy-tailed (small k)."""
    med = float(np.median(x))
    clip = CLIP_REL_MEDIAN
    if np.isfinite(k) and k > 0:
        clip = max(clip, float(gamma_dist.ppf(0.99, k) / gamma_dist.median(k)))
    keep = x[x <= clip * med] if med > 0 else x
    return float(np.mean(keep)) if keep.size else med


def _loglog_fill(ratio: np.ndarray, known: np.ndarray, fc: np.ndarray) -> np.ndarray:
    """Fill unknown bands by linear interpolation of log(ratio) over log(f) (nearest value beyond the ends)."""
    out = ratio.copy()
    lf = np.log(fc)
    out[~known] = np.exp(np.interp(lf[~known], lf[known], np.log(ratio[known])))
    return out


_K_TABLE = np.logspace(-1.5, 2.5, 400)
_Q_RATIO = gamma_dist.ppf(0.25, _K_TABLE) / gamma_dist.ppf(0.75, _K_TABLE)     # increasing in k


def _gamma_shape(x: np.ndarray) -> float:
    """Gamma shape k matching the sample's quartile ratio Q1/Q3 (scale-free, and robust to a
    minority of cells holding a real effect, unlike the log-moment ML estimate)."""
    x = x[np.isfinite(x) & (x > 0)]
    if x.size < 4:
        return np.inf
    q1, q3 = np.percentile(x, [25, 75])
    r = q1 / q3 if q3 > 0 else 1.0
    if r >= _Q_RATIO[-1]:
        return np.inf
    return float(np.interp(r, _Q_RATIO, _K_TABLE))


def local_noise_floor(rd: RecData, model_p: dict) -> dict:
    """Per channel (n_bands,) noise floor; see :func:`noise_floor_and_dof`."""
    return noise_floor_and_dof(rd, model_p)[0]


def noise_floor_and_dof(rd: RecData, model_p: dict) -> tuple[dict, dict]:
    """Per channel (n_bands,): max(model floor, level of the recording's own quiet cells).

    ``model_p - rd.noise`` is what the model predicts beyond noise (twin, stochastic extensions);
    cells where that is <= ``QUIET_TWIN_REL`` x ``rd.noise`` are quiet. Bands with fewer than
    ``MIN_QUIET_CELLS`` quiet cells (or guideway channels' modal bands) take the
    interpolation (log-log) of their neighbours' ratio quiet level / model floor, the nearest
    ratio beyond the ends; with no quiet band at all the model floor stands.

    Also the degrees of freedom of a band power per channel and band: 2 x periodogram bins, but
    never more than twice the Gamma shape fitted to the quiet cells (1/f noise concentrates its
    power in the lowest bins, so the lowest band scatters much more than its bin count says).
    """
    g = rd.grid
    fc = np.maximum(g.band_center_hz, 0.5 * g.edges_hz[1])
    modal = None
    out, dofs = {}, {}
    nb = np.array([max(1.0, round(w * g.frame_s)) for w in np.diff(g.edges_hz)])
    for n, ch in rd.rec.channels.items():
        base = np.asarray(rd.noise[n], float)
        pm = rd.pm[n]
        fin = np.all(np.isfinite(pm), axis=1)
        if ch.on_vehicle or fin.sum() < MIN_QUIET_CELLS:
            # a vehicle is never at rest on the line: no frame of a vehicle channel is quiet (its
            # model floor already comes from the measured-minus-twin signal, see evaluate.prepare)
            out[n], dofs[n] = base, 2.0 * nb
            continue
        # what the model predicts beyond noise and beyond any stationary (stochastic) part
        pred = np.asarray(model_p[n], float) - base[None, :]
        pred = pred - np.nanmin(np.where(fin[:, None], pred, np.inf), axis=0)[None, :]
        tot = np.nansum(np.where(rd.masks[n][None, :], pred, 0.0), axis=1)
        top = float(np.max(tot[fin])) if fin.any() else 0.0
        qf = fin & (tot <= QUIET_TWIN_REL * top) if top > 0 else fin.copy()
        quiet = np.repeat(qf[:, None], g.n_bands, axis=1)
        level = np.full(g.n_bands, np.nan)
        dof = 2.0 * nb
        for b in range(g.n_bands):
            q = pm[quiet[:, b], b]
            k = _gamma_shape(q) if q.size >= 2 * MIN_QUIET_CELLS else np.inf
            if q.size >= MIN_QUIET_CELLS:
                level[b] = _clipped_mean(q, k)
            if np.isfinite(k):
                dof[b] = min(dof[b], max(0.5, 2.0 * k))
        dofs[n] = dof
        known = np.isfinite(level) & (level > 0) & rd.masks[n]
        if ch.group.startswith("guideway"):
            if modal is None:
                modal = _modal_band_mask(rd)
            known &= ~modal
        if not known.any():
            out[n] = base
            continue
        # the correction is a ratio to the model floor (band widths and the floor's colour carry over)
        ratio = np.where(known, level / np.where(base > 0, base, np.inf), 1.0)
        known &= ratio > 0
        if not known.any():
            out[n] = base
            continue
        out[n] = base * np.maximum(1.0, _loglog_fill(ratio, known, fc))
    return out, dofs


def residual_map(rd: RecData, model_p: dict) -> ResidualMap:
    """Flags and severities of every (frame, band) cell per channel against the local noise floor."""
    sev, flags, rel = {}, {}, {}
    floor, dofs = noise_floor_and_dof(rd, model_p)
    for n in rd.rec.channels:
        dof = dofs[n]
        pn = floor[n][None, :]
        pm, pmod = rd.pm[n], model_p[n] + np.clip(pn - rd.noise[n][None, :], 0, None)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.abs(np.sqrt(np.clip(pm, 0, None)) - np.sqrt(pmod)) / np.sqrt(pmod)
            s = (pm - pmod) / np.maximum(pn, 1e-300)
        f = (r > np.maximum(0.3, 3.0 / np.sqrt(dof))[None, :]) & (np.abs(s) > 3.0)
        # only bands the fit trusts: a gap channel judged through its magnet's transmissibility
        # (its band amplitudes follow the reconstructed rail, not the twin's physics) flags nothing
        f &= fit_mask(rd, n)[None, :] & np.isfinite(pm)
        sev[n], flags[n], rel[n] = np.nan_to_num(s), f, np.nan_to_num(r)
    return ResidualMap(rd, sev, flags, rel, floor)


def _positions(rd: RecData, t0: float, t1: float, chans: list[str]) -> tuple[float, float] | None:
    """Stretch of the line a region refers to. Vehicle channels: where the vehicle (all its
    magnets) was meanwhile. Guideway channels: the spans holding those sensors, narrowed to the
    part the vehicle covered meanwhile when it was on them (a girder answers its own load; in
    the free decay after the vehicle left, the sensors' spans)."""
    rec = rd.rec
    spans = (rec.metadata.get("line") or {}).get("spans") or []
    line0 = min((s["start_m"] for s in spans), default=None)
    line1 = max((s["start_m"] + s["length_m"] for s in spans), default=None)
    sens = [rec.channels[c].position_m for c in chans if rec.channels[c].position_m is not None]
    own = [(s["start_m"], s["start_m"] + s["length_m"]) for s in spans
           if any(s["start_m"] <= x <= s["start_m"] + s["length_m"] for x in sens)]
    guideway_only = bool(sens) and all(rec.channels[c].group.startswith("guideway") for c in chans)
    if rec.position_time_s is not None and line0 is not None:
        offs = (rec.metadata.get("vehicle") or {}).get("magnet_offsets_m") or [0.0]
        x = rec.position_at(np.linspace(t0, t1, 20))
        lo, hi = max(float(np.min(x) + min(offs)), line0), min(float(np.max(x) + max(offs)), line1)
        if guideway_only and own:
            a, b = min(o[0] for o in own), max(o[1] for o in own)
            lo, hi = (max(lo, a), min(hi, b)) if max(lo, a) < min(hi, b) else (a, b)
            return lo, hi
        if lo < hi:
            return lo, hi
    if own:
        return min(o[0] for o in own), max(o[1] for o in own)
    if sens:
        return float(min(sens)), float(max(sens))
    return None


def strong_cells(rmap: ResidualMap, name: str) -> np.ndarray:
    """Flagged cells of a channel that count on their own (see ``STRONG_REL``)."""
    return rmap.flags[name] & (rmap.rel[name] >= STRONG_REL) & (np.abs(rmap.severity[name]) >= STRONG_SEV)


def mismatches(rmap: ResidualMap, max_regions: int = 12, min_cells: int = 2) -> list[Mismatch]:
    rd = rmap.rd
    g = rd.grid
    out = []
    for grp in GROUPS:
        names = [n for n, c in rd.rec.channels.items() if c.group == grp]
        if not names:
            continue
        anyf = np.zeros((g.n_frames, g.n_bands), bool)
        strong = np.zeros_like(anyf)
        for n in names:
            anyf |= rmap.flags[n]
            strong |= strong_cells(rmap, n)
        lab, nlab = ndimage.label(anyf)
        for k in range(1, nlab + 1):
            cells = lab == k
            if cells.sum() < min_cells and not (strong & cells).any():
                continue
            fr, bd = np.nonzero(cells)
            chans = [n for n in names if (rmap.flags[n] & cells).any()]
            t0 = float(g.t_center_s[fr.min()] - g.frame_s / 2)
            t1 = float(g.t_center_s[fr.max()] + g.frame_s / 2)
            f0, f1 = float(g.edges_hz[bd.min()]), float(g.edges_hz[bd.max() + 1])
            sev = float(np.mean([np.abs(rmap.severity[n][cells & rmap.flags[n]]).mean() for n in chans]))
            out.append(Mismatch(tuple(chans), (t0, t1), _positions(rd, t0, t1, chans), (f0, f1), sev, grp,
                                rd.rec.source))
    out.sort(key=lambda m: -m.severity * (m.time_s[1] - m.time_s[0]))
    return out[:max_regions]


def region_after(m: Mismatch, before: ResidualMap, after: ResidualMap) -> dict | None:
    """How a mismatch's cells look against another twin (the one with the found physics): the
    mean |severity| over the cells flagged before, and the share of them still flagged. None when
    the maps do not cover its channels, frames and bands."""
    g = before.rd.grid
    if m.frequency_hz is None or after.rd.grid.n_frames != g.n_frames:
        return None
    fr = (g.t_center_s - g.frame_s / 2 >= m.time_s[0] - 1e-9) & (g.t_center_s + g.frame_s / 2 <= m.time_s[1] + 1e-9)
    bd = (g.edges_hz[:-1] >= m.frequency_hz[0] - 1e-9) & (g.edges_hz[1:] <= m.frequency_hz[1] + 1e-9)
    region = fr[:, None] & bd[None, :]
    sev, n_before, n_after = [], 0, 0
    for n in m.channels:
        if n not in before.flags or n not in after.flags:
            continue
        cells = region & before.flags[n]
        n_before += int(cells.sum())
        n_after += int((cells & after.flags[n]).sum())
        sev.extend(np.abs(after.severity[n][cells]).tolist())
    if not n_before:
        return None
    return {"severity": float(np.mean(sev)), "flagged_share": n_after / n_before}


def excess_by_channel(rmap: ResidualMap) -> dict:
    """Share of flagged cells per channel (for ranking sensor-error candidates)."""
    return {n: float(f.mean()) for n, f in rmap.flags.items()}


# a band of one guideway sensor whose measured/twin amplitude ratio differs from its peers' median
# by >= this (ln; ~1.4x) in every recording with the same sign is a persistent local misfit.
# Measured on the benchmark's calibrated twins (20 clean cases, 2 passes each, 6 guideway
# accelerometers): no band of a clean case reached 0.30 in both passes; attachments on a girder
# reached 0.36-0.63 on their span's sensors (the mode they detune, or their own band)
PERSISTENT_MIN_LOG = 0.35
# ... and it is off from the twin itself by >= this (ln, same sign): with half of the group on the
# affected span (a 2-span line) the peers' median is itself off, and a healthy sensor of the other
# span looked 1.44x off its "peers" while it matched the twin within 5 %
PERSISTENT_MIN_ABS_LOG = 0.2
PERSISTENT_ONE_RECORDING_LOG = 0.5      # with one recording only: no second look, a higher bar
PERSISTENT_MIN_SNR = 3.0                # measured band power >= this x noise floor (not noise)


def persistent_mismatches(rds: list[RecData], model_ps: list[dict]) -> list[Mismatch]:
    """Local misfits that single frames hide: a guideway sensor's band amplitude, averaged over a
    whole recording, set against the same ratio of its peers (same group; the median removes what
    the twin gets wrong for the whole group). Frame by frame such a misfit (1.4-1.9x) drowns in the
    scatter of a 0.5 s band power (:func:`residual_map` needs 1.3x and 3/sqrt(dof)); over a recording
    it is sharp. One Mismatch per span and contiguous band run, placed on the span of its sensors."""
    from .scale_signature import log_amplitude_ratio
    if not rds:
        return []
    per: dict[tuple[str, int], list[float]] = {}
    absolute: dict[tuple[str, int], list[float]] = {}
    snr_ok: dict[tuple[str, int], bool] = {}
    for rd, mp in zip(rds, model_ps):
        groups: dict[str, list[str]] = {}
        for n, c in rd.rec.channels.items():
            if c.group.startswith("guideway") and c.position_m is not None:
                groups.setdefault(c.group, []).append(n)
        for names in groups.values():
            if len(names) < 3:
                continue
            R = {n: log_amplitude_ratio(rd.pm[n], mp[n], rd.masks[n] & fit_mask(rd, n)) for n in names}
            for n in names:
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)      # bands no peer has: NaN
                    d = R[n] - np.nanmedian(np.array([R[p] for p in names if p != n]), axis=0)
                    snr = np.nanmean(rd.pm[n], axis=0) / np.maximum(rd.noise[n], 1e-300)
                for b in np.flatnonzero(np.isfinite(d)):
                    per.setdefault((n, int(b)), []).append(float(d[b]))
                    absolute.setdefault((n, int(b)), []).append(float(R[n][b]))
                    snr_ok[(n, int(b))] = snr_ok.get((n, int(b)), True) and bool(snr[b] >= PERSISTENT_MIN_SNR)
    n_rec = len(rds)
    hits: dict[str, dict[int, float]] = {}
    for (n, b), ds in per.items():
        ds_a = np.asarray(ds)
        ab = np.sign(ds_a) * np.asarray(absolute[(n, b)])
        bar = PERSISTENT_MIN_LOG if n_rec >= 2 else PERSISTENT_ONE_RECORDING_LOG
        if (len(ds) == n_rec and snr_ok[(n, b)] and np.all(np.abs(ds_a) >= bar)
                and (np.all(ds_a > 0) or np.all(ds_a < 0)) and np.all(ab >= PERSISTENT_MIN_ABS_LOG)):
            hits.setdefault(n, {})[b] = float(np.mean(ds_a))
    rd0 = rds[0]
    spans = (rd0.rec.metadata.get("line") or {}).get("spans") or []

    def span_of(x):
        for s in spans:
            if s["start_m"] <= x <= s["start_m"] + s["length_m"]:
                return (s["start_m"], s["start_m"] + s["length_m"])
        return (float(x), float(x))
    runs: dict[tuple, list] = {}
    for n, bs in hits.items():
        place = span_of(rd0.rec.channels[n].position_m)
        for b in sorted(bs):
            runs.setdefault(place, []).append((b, n, bs[b]))
    e = rd0.grid.edges_hz
    out = []
    for place, items in runs.items():
        items.sort()
        group: list = []
        for it in items + [None]:
            if it is not None and (not group or it[0] <= group[-1][0] + 1):
                group.append(it)
                continue
            if group:
                b0, b1 = min(g[0] for g in group), max(g[0] for g in group)
                chans = tuple(sorted({g[1] for g in group}))
                # severity as for every mismatch: mean |measured - model| band power over the noise floor
                sev = float(np.mean([np.nanmean(np.abs(rd.pm[c][:, b0:b1 + 1] - mp[c][:, b0:b1 + 1]))
                                     / max(float(np.mean(rd.noise[c][b0:b1 + 1])), 1e-300)
                                     for rd, mp in zip(rds, model_ps) for c in chans if c in rd.pm]))
                ratio = float(np.mean([math.exp(abs(g[2])) for g in group]))
                out.append(Mismatch(chans, (rd0.rec.t0_s, rd0.rec.t1_s), place, (float(e[b0]), float(e[b1 + 1])),
                                    sev, rd0.rec.channels[chans[0]].group, "all recordings (persistent band misfit)",
                                    ratio))
            group = [it] if it is not None else []
    out.sort(key=lambda m: -m.severity)
    return out
