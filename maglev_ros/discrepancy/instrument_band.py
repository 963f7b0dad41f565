"""The band an instrument passes, from the recording against the twin: a low-pass inside the compared bands.

A DAQ's anti-alias filter may cut well below the 0.7 x Nyquist the band features use (a structural
DAQ sampling at 1 kHz with a 100 Hz low-pass). Above its corner the measured band powers fall by
orders of magnitude under any twin's, and a calibration that compares them drags the girder's
parameters to match (a partner clean case low-passed at 100 Hz: floor 0.073 -> 0.26 and an attachment
"found"; a bearing case called a girder loss). Per recording and guideway channel group (one
acquisition system), the median over its channels' cells where the twin clearly exceeds the noise of
measured / modelled band power is read band by band down from the highest compared band: when the
highest is below a quarter (-6 dB, a filter's roll-off deepens upwards) the run of bands below one
half (-3 dB, the corner's definition) is the instrument's stop band, and the group's channels are
compared below it.
The model read against is the calibrated twin re-fitted (linearly, :func:`.fitting.reprojected_without`)
without the group's own rows: calibrated on them, the twin bends to the attenuated bands next to the corner
(a 100 Hz filter on a partner line: bearing stiffness x1.6, the 105-125 Hz band read at 1.2 for a true
0.065, the corner at 125 Hz; re-fitted without them, 0.17 and the corner at 88 Hz for a half-power 89.5 Hz),
and tuned to the span's first mode as the ambient recording rings (:func:`tuned_to`): without the guideway's
accelerometers nothing else fixes the density, and a mode misplaced by a band reads like a filter.
Parameter errors move a mode by a band at most, so the ratio stays near one at the top band of an
unfiltered line (0.51-1.2 on the 14 partner cases, 0.42 and more on 16 of ours); nothing is trimmed on such recordings.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .evaluate import RecData, Selection, _twin_powers, fit_mask, residual_rows
from .fitting import CAL_HI, CAL_LO, BaseFit, reprojected_without
from .model import CAL_PARAMS, ModelSpec, guideway_modal

HALF_POWER = 0.5        # a band below -3 dB of the twin is past the instrument's corner
TOP_BELOW = 0.25        # ... and the highest compared band past -6 dB: a roll-off, not a bump
TWIN_OVER_NOISE = 4.0   # cells where the twin clearly exceeds the noise floor
MIN_BANDS_KEPT = 1      # a stop band is cut even when few bands pass (compared, it bends the calibration: a
                        # displacement sensor low-passed to 3 bands drew E x1.6); none passing: left as it is
GUIDEWAY_GROUPS = ("guideway_accel", "guideway_disp")


@dataclass(frozen=True)
class BandLimit:
    recording: str
    group: str
    upper_hz: float                   # bands wholly below are compared
    ratio_by_band: tuple              # (band centre [Hz], median measured / model power) of the trimmed run

    def words(self) -> str:
        worst = min(r for _, r in self.ratio_by_band)
        return (f"{self.recording}: the {self.group} channels read {worst:.2g}x the twin's band power and less above "
                f"{self.upper_hz:.0f} Hz, falling with frequency like an instrument's low-pass: compared below it")

    def to_dict(self) -> dict:
        return {"recording": self.recording, "group": self.group, "upper_hz": self.upper_hz,
                "ratio_by_band": [list(x) for x in self.ratio_by_band]}


def instrument_band_limits(base: BaseFit, rd_train: list[RecData], rds: list[RecData],
                           known: dict | None = None, anchor: tuple[str, float] | None = None
                           ) -> dict[tuple[int, str], BandLimit]:
    """(index of the recording in ``rds``, channel group) -> the band limit found (none: not there); ``base``:
    the twin calibrated on ``rd_train``. ``known``: limits found before (the groups they name are compared
    below them already): there the filter is established and its roll-off is followed down while the
    highest band still compared reads under one half. ``anchor``: (span id, first bending mode [Hz]) measured
    on the ambient recording (a zero-phase filter leaves it in place), which the reference twin is tuned to."""
    known_groups = {g for _, g in (known or {})}
    out = {}
    # the guideway sensors only: their twin is forced by the vehicle's passage, within ~30 % in every
    # band on clean lines; the vehicle channels' twin follows the reconstructed rail, whose error at
    # short waves puts it at 0.03-1x the measured band power at 30-150 Hz on a clean generated line
    groups = [g for g in GUIDEWAY_GROUPS if rds and rds[0].rec.names(g)]
    for g in groups:
        others = Selection(frozenset(n for n, ch in rd_train[0].rec.channels.items() if ch.group != g), own=True)
        own = ~residual_rows(base.spec, rd_train, others)
        spec = reprojected_without(base, own) if (~own).any() else base.spec
        if anchor is not None:
            # the other channels say little of the density: a 15 % error put the twin's second mode a band
            # below the measured one and the band ratios read a misplaced mode, not the filter
            spec = tuned_to(spec, *anchor)
        top_below = HALF_POWER if g in known_groups else TOP_BELOW
        for i, rd in enumerate(rds):
            lim = _group_limit(spec, rd, g, top_below)
            if lim is not None:
                out[(i, g)] = lim
    return out


def tuned_to(spec: ModelSpec, span_id: str, f1_hz: float) -> ModelSpec:
    """``spec`` with its density scaled so that span ``span_id``'s first bending mode rings at ``f1_hz``."""
    ids = [sp.span_id for sp in spec.spans]
    if span_id not in ids or not f1_hz > 0:
        return spec
    modal = guideway_modal(spec)
    f_twin = float(modal.freq_hz[modal.span_index == ids.index(span_id)].min())
    th = np.zeros(len(CAL_PARAMS))
    th[:len(spec.cal)] = spec.cal
    th[CAL_PARAMS.index("rho")] += 2.0 * math.log(f_twin / f1_hz)        # f ~ sqrt(E / rho)
    return spec.with_(cal=tuple(float(x) for x in np.clip(th, CAL_LO, CAL_HI)))


def _medians(spec, rd: RecData, g: str) -> np.ndarray | None:
    pt, _ = _twin_powers(spec, rd)
    rs = []
    for n, ch in rd.rec.channels.items():
        used = fit_mask(rd, n)
        if ch.group != g or n not in pt or not used.any():
            continue
        noise = rd.noise.get(n, np.zeros(rd.grid.n_bands))[None, :]
        ok = (pt[n] > TWIN_OVER_NOISE * noise) & np.isfinite(rd.pm[n]) & used[None, :]
        rs.append(np.where(ok, rd.pm[n] / np.maximum(pt[n] + noise, 1e-300), np.nan))
    if not rs:
        return None
    cells = np.concatenate(rs, axis=0)
    have = np.sum(np.isfinite(cells), axis=0) >= 3
    med = np.full(cells.shape[1], np.nan)
    med[have] = np.nanmedian(cells[:, have], axis=0)
    return med


def _group_limit(spec, rd: RecData, g: str, top_below: float) -> BandLimit | None:
    med = _medians(spec, rd, g)
    if med is None:
        return None
    edges, centre = rd.grid.edges_hz, rd.grid.band_center_hz
    bands = np.flatnonzero(np.isfinite(med))
    if not bands.size or not med[bands[-1]] < top_below:
        return None
    k = bands.size - 1
    while k >= 0 and med[bands[k]] < HALF_POWER:
        k -= 1
    if k + 1 < MIN_BANDS_KEPT:
        return None
    cut = bands[k + 1:]
    return BandLimit(rd.rec.name, g, float(edges[cut[0]]), tuple((float(centre[b]), float(med[b])) for b in cut))


def common_limits(limits, names: list[str]) -> dict[tuple[int, str], BandLimit]:
    """Each group's lowest limit among ``limits`` (BandLimits, from every recording and round), with the trimmed runs
    of all, for every one of ``names`` (the recordings, by index): one acquisition system recorded them all (the
    ambient recording too, whose twin has no vehicle to read a roll-off from), and a pass whose twin bends more
    reads the corner higher."""
    low: dict[str, float] = {}
    runs: dict[str, set] = {}
    for lim in limits:
        low[lim.group] = min(low.get(lim.group, math.inf), lim.upper_hz)
        runs.setdefault(lim.group, set()).update(lim.ratio_by_band)
    return {(i, g): BandLimit(name, g, hz, tuple(sorted(runs[g]))) for g, hz in low.items()
            for i, name in enumerate(names)}


def apply_limits(rds: list[RecData], limits: dict[tuple[int, str], BandLimit]) -> None:
    """Compare each limited group's channels (and the features built from them) below its limit, in place."""
    for (i, g), lim in limits.items():
        rd = rds[i]
        below = rd.grid.edges_hz[1:] <= lim.upper_hz + 1e-9
        names = {n for n, ch in rd.rec.channels.items() if ch.group == g}
        for n in names:
            rd.masks[n] = rd.masks[n] & below
        for k, pair in rd.sens_pairs.items():
            if names & set(pair):
                rd.sens_masks[k] = rd.sens_masks[k] & below
        for b, mags in rd.body_pairs.items():
            if names & ({b} | set(mags)):
                rd.body_masks[b] = rd.body_masks[b] & below
