"""The signature of a sensor scale fault among sensors of the same quantity.

A sensor that reads ``s`` times the truth multiplies its band amplitudes by ``s`` in EVERY band and
every pass. The twin's model error of that channel also shifts its measured/twin amplitude ratio,
but by different amounts in different bands (modes, mode-shape nodes), and mostly alike on its
neighbours (a stiffness or forcing level off shifts the whole group). So the channel's log amplitude
ratio (measured/twin) minus the median of its peers' (same group), band by band, is a constant
``ln s`` for a scale fault and scatters around zero for model error.

Why this is needed: one faulty channel of 13 moves the whole-recording held-out NRMSE by < 5 %
(measured on a 1.35 scale fault of one guideway accelerometer: 0.196 -> 0.191), so the gates that
judge an extension on the whole recording cannot accept it, and judging it on its own channel alone
accepted model error as a 9 % "scale fault". Measured on the benchmark's calibrated twins (20 clean
and 12 sensor-fault cases, both splits, 169 healthy guideway-accelerometer channel records): healthy
channels' relative mean log ratio |mu| <= 0.09 with band-sign consistency <= 0.76; the two 1.35 scale
faults mu = 0.25-0.27 in both passes with consistency 0.94.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# thresholds (see module docstring for the measured separation)
MIN_ABS_LOG_SCALE = 0.15       # |ln s| relative to the peers: ~16 %; healthy channels <= 0.09
MIN_CONSISTENCY = 0.75         # share of bands whose relative log ratio has the sign of the mean
# (not 0.85: a 1.3 scale fault read 0.82 in one pass of a probe case; on the calibrated
# twins of both benchmark splits no healthy channel reaches |mu| >= 0.15 in both passes, and the
# offset faults that do have a consistency <= 0.65)
MAX_PASS_SPREAD = 0.10         # the relative log scale agrees between passes within this
MIN_BANDS = 6
MIN_PEERS = 2


@dataclass(frozen=True)
class ScaleSignature:
    channel: str
    log_scale_per_pass: tuple[float, ...]     # relative to the peers' median, per recording
    consistency_per_pass: tuple[float, ...]
    n_bands_per_pass: tuple[int, ...]
    peers: tuple[str, ...]

    @property
    def relative_scale(self) -> float:
        return math.exp(float(np.mean(self.log_scale_per_pass))) if self.log_scale_per_pass else 1.0

    @property
    def holds(self) -> bool:
        mu = np.asarray(self.log_scale_per_pass)
        if mu.size == 0:
            return False
        return bool(np.all(np.abs(mu) >= MIN_ABS_LOG_SCALE) and (np.all(mu > 0) or np.all(mu < 0))
                    and float(mu.max() - mu.min()) <= MAX_PASS_SPREAD
                    and min(self.consistency_per_pass) >= MIN_CONSISTENCY)

    def explain(self) -> str:
        mu = ", ".join(f"{math.exp(m):.2f}" for m in self.log_scale_per_pass)
        cons = ", ".join(f"{c * 100:.0f} %" for c in self.consistency_per_pass)
        return (f"relative to {', '.join(self.peers)} it reads x{mu} (per recording) with the same sign in "
                f"{cons} of its bands")


def log_amplitude_ratio(pm: np.ndarray, mp: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per band ln(measured / twin) of the frame-mean band amplitudes (NaN outside ``mask``)."""
    am = np.sqrt(np.clip(np.nanmean(pm, axis=0), 0, None))
    at = np.sqrt(np.clip(np.nanmean(mp, axis=0), 0, None))
    r = np.full(mask.size, np.nan)
    ok = mask & (am > 0) & (at > 0)
    r[ok] = np.log(am[ok] / at[ok])
    return r


def scale_signature(channel: str, recs: list[tuple[dict, dict, dict, dict]]) -> ScaleSignature | None:
    """``recs``: per recording (groups {name: group}, measured band powers {name: (frames, bands)},
    model band powers alike, usable-band masks {name: (bands,)}). None when the channel has fewer
    than two peers of its group in some recording."""
    mus, cons, nbs = [], [], []
    peers_all: set[str] = set()
    for rec in recs:
        if channel not in rec[1]:
            continue
        ref = _referenced(channel, rec)
        if ref is None:
            return None
        am, ar, _, peers = ref
        peers_all.update(peers)
        d = np.log(am / ar)
        mu = float(np.mean(d))
        mus.append(mu)
        cons.append(float(np.mean(np.sign(d) == np.sign(mu))))
        nbs.append(int(d.size))
    if not mus:
        return None
    return ScaleSignature(channel, tuple(mus), tuple(cons), tuple(nbs), tuple(sorted(peers_all)))


@dataclass(frozen=True)
class PeerReferencedFit:
    """A channel's scale judged against its peers' level instead of the twin's: the reference
    amplitude of each band is the twin's times the peers' median measured/twin ratio of that band
    (the group's common model error), the scale is the training recording's relative log scale, and
    it is checked on the held-out recordings. Used when the twin's level of the whole group is off
    (measured: a calibrated twin over-predicting every guideway accelerometer by ~17 % hid a 1.2
    scale fault of one of them, which then 'matched' the twin)."""
    channel: str
    log_scale: float                  # fitted on the training recording, relative to the peers
    heldout_before: float             # RMS over bands of the amplitude error relative to the peer reference
    heldout_after: float              # ... with the scale applied
    delta_bic: float                  # training recording, relative band errors, one parameter
    group_level: float                # peers' median measured/twin amplitude ratio (training)


def _referenced(channel: str, rec: tuple[dict, dict, dict, dict]):
    """(measured amplitudes, peer-referenced model amplitudes, peers' median log ratio, peers) over
    the channel's bands that have >= MIN_PEERS finite peers; None when not testable (fewer than
    MIN_PEERS peers or MIN_BANDS such bands)."""
    groups, pm, mp, masks = rec
    if channel not in pm:
        return None
    peers = [n for n, g in groups.items() if g == groups[channel] and n != channel and n in pm]
    if len(peers) < MIN_PEERS:
        return None
    r = log_amplitude_ratio(pm[channel], mp[channel], masks[channel])
    rp = np.array([log_amplitude_ratio(pm[p], mp[p], masks[p]) for p in peers])
    with np.errstate(all="ignore"):
        ok = np.isfinite(r) & (np.sum(np.isfinite(rp), axis=0) >= MIN_PEERS)
        if ok.sum() < MIN_BANDS:
            return None
        med = np.nanmedian(rp[:, ok], axis=0)
    am = np.sqrt(np.clip(np.nanmean(pm[channel], axis=0), 0, None))[ok]
    at = np.sqrt(np.clip(np.nanmean(mp[channel], axis=0), 0, None))[ok]
    return am, at * np.exp(med), med, peers


def peer_referenced_fit(channel: str, train: list, test: list) -> PeerReferencedFit | None:
    """Fit the channel's scale against its peer reference on ``train`` recordings and judge it on
    ``test`` ones (each as in :func:`scale_signature`). None when the channel is not testable."""
    tr = [x for x in (_referenced(channel, r) for r in train if channel in r[1]) if x is not None]
    te = [x for x in (_referenced(channel, r) for r in test if channel in r[1]) if x is not None]
    if not tr or not te:
        return None
    # errors relative to each band's reference amplitude, RMS over the bands: band amplitudes span
    # decades, and weighted by amplitude one or two bands ruled the measure (on synthetic groups
    # with 8 % band scatter a true 1.2 fault then "worsened" the held-out fit in 2 of 20 draws)
    q = np.concatenate([x[0] / x[1] for x in tr])
    ln_s = float(np.mean(np.log(q)))
    s = math.exp(ln_s)
    rss0, rss1 = float(np.sum((q - 1) ** 2)), float(np.sum((q / s - 1) ** 2))
    n = q.size
    dbic = n * math.log(max(rss1, 1e-300) / max(rss0, 1e-300)) + math.log(n)
    qt = np.concatenate([x[0] / x[1] for x in te])
    before = float(np.sqrt(np.mean((qt - 1) ** 2)))
    after = float(np.sqrt(np.mean((qt / s - 1) ** 2)))
    level = math.exp(float(np.median(np.concatenate([x[2] for x in tr]))))
    return PeerReferencedFit(channel, ln_s, before, after, dbic, level)
