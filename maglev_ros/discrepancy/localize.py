"""Where twin and recording differ: per channel, time (-> position along the line), band, group.

For every channel, frame and band the measured band power Pm is compared with the model's
Pmod = twin + noise floor (+ stochastic extensions). A cell is a mismatch only if BOTH
- the amplitude differs by more than the estimation scatter of a band power (relative error of
  sqrt(P) above max(0.3, 3 / sqrt(dof)), dof = 2 x periodogram bins in the band), and
- the residual power exceeds 3 x the noise floor of that band,
so sensor noise (and the random scatter of its band powers) is never called a mismatch.
Cells are grouped per channel group into connected regions (scipy.ndimage.label over
frames x bands); each region becomes a ``Mismatch`` with its channels, time, the span of the line
the vehicle covered meanwhile (guideway sensors' own positions when no vehicle is on the line),
band and severity (mean residual power over the noise floor).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .evaluate import RecData
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

    def to_dict(self) -> dict:
        return {"channels": list(self.channels), "time_s": [float(self.time_s[0]), float(self.time_s[1])],
                "position_m": None if self.position_m is None else [float(x) for x in self.position_m],
                "frequency_hz": None if self.frequency_hz is None else [float(x) for x in self.frequency_hz],
                "severity": float(self.severity)}


@dataclass
class ResidualMap:
    """Per channel (frames x bands): severity (residual power / noise floor, signed) and flags."""
    rd: RecData
    severity: dict
    flags: dict
    rel: dict


def residual_map(rd: RecData, model_p: dict) -> ResidualMap:
    sev, flags, rel = {}, {}, {}
    g = rd.grid
    nb = np.array([max(1.0, round(w * g.frame_s)) for w in np.diff(g.edges_hz)])
    dof = 2.0 * nb
    for n in rd.rec.channels:
        pm, pmod, pn = rd.pm[n], model_p[n], rd.noise[n][None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.abs(np.sqrt(np.clip(pm, 0, None)) - np.sqrt(pmod)) / np.sqrt(pmod)
            s = (pm - pmod) / np.maximum(pn, 1e-300)
        f = (r > np.maximum(0.3, 3.0 / np.sqrt(dof))[None, :]) & (np.abs(s) > 3.0)
        f &= rd.masks[n][None, :] & np.isfinite(pm)
        sev[n], flags[n], rel[n] = np.nan_to_num(s), f, np.nan_to_num(r)
    return ResidualMap(rd, sev, flags, rel)


def _positions(rd: RecData, t0: float, t1: float, chans: list[str]) -> tuple[float, float] | None:
    rec = rd.rec
    spans = (rec.metadata.get("line") or {}).get("spans") or []
    line0 = min((s["start_m"] for s in spans), default=None)
    line1 = max((s["start_m"] + s["length_m"] for s in spans), default=None)
    sens = [rec.channels[c].position_m for c in chans if rec.channels[c].position_m is not None]
    if rec.position_time_s is not None and line0 is not None:
        offs = (rec.metadata.get("vehicle") or {}).get("magnet_offsets_m") or [0.0]
        x = rec.position_at(np.linspace(t0, t1, 20))
        lo, hi = float(np.min(x) + min(offs)), float(np.max(x) + max(offs))
        lo, hi = max(lo, line0), min(hi, line1)
        if lo < hi:
            if sens and all(rec.channels[c].group.startswith("guideway") for c in chans):
                # a guideway sensor responds to the vehicle on its own span: keep the overlap
                return lo, hi
            return lo, hi
    if sens:
        return float(min(sens)), float(max(sens))
    return None


def mismatches(rmap: ResidualMap, max_regions: int = 12, min_cells: int = 2) -> list[Mismatch]:
    rd = rmap.rd
    g = rd.grid
    out = []
    for grp in GROUPS:
        names = [n for n, c in rd.rec.channels.items() if c.group == grp]
        if not names:
            continue
        anyf = np.zeros((g.n_frames, g.n_bands), bool)
        for n in names:
            anyf |= rmap.flags[n]
        lab, nlab = ndimage.label(anyf)
        for k in range(1, nlab + 1):
            cells = lab == k
            if cells.sum() < min_cells:
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


def excess_by_channel(rmap: ResidualMap) -> dict:
    """Share of flagged cells per channel (for ranking sensor-error candidates)."""
    return {n: float(f.mean()) for n, f in rmap.flags.items()}
