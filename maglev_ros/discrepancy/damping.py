"""The guideway's modal damping measured on an ambient recording, for the twin's calibrate stage.

The twin damps every span with Rayleigh damping, C = a M + b K, set so that modes 1-2 of the span
have the design's ``damping_ratio`` (:func:`maglev_ros.twin.guideway.assemble_span`). A foreign
simulator or a real line can be damped otherwise; :func:`measure_damping` measures it on the
ambient recording (guideway accelerations, no vehicle) and returns the one Rayleigh ratio to give
the twin (``ModelSpec.guideway_damping_ratio``).

Method:

1. identification: the suite's own, exactly as ``maglev-ros modes`` runs an ambient recording with
   its defaults (:func:`maglev_ros.modal.bands.plan_bands` + :func:`~maglev_ros.modal.bands.identify_bands`:
   SSI-cov in bands of at most a decade, Whittle polish, the modes of all bands merged), on the
   guideway accelerometers of the instrumented span (the span holding most vertical ones); nothing
   here identifies;
2. matching: each
   identified mode is compared with the twin's modes of that span (:func:`.model.guideway_modal`)
   by the distance the suite's clustering uses, ``|ln(f / f_twin)| + (1 - MAC)`` (MAC over the
   vertical accelerometers with a position, the twin's shape evaluated there). An identified mode
   and a twin mode match when each is the other's nearest (no distance bar) and the MAC is above
   1/2; twin modes 1 and 2 are the ones the design ratio is defined on;
3. one ratio: a single Rayleigh ratio gives both modes the same damping, so the ratio that
   reproduces the two measured ones as well as one ratio can is their inverse-variance weighted
   mean (weighted least squares); its std is the weighted mean's, scaled by the Birge ratio
   sqrt(chi^2 / dof) when the modes disagree by more than their own stds. Every instrumented span
   is measured this way on its own sensors and the one ratio comes from all their modes; with three
   modes or more, a mode off the others beyond chance (Bonferroni at 0.1 %) is left out and marked
   (a spurious narrow pole would carry the mean by its small std alone). The exact Rayleigh
   pair (a, b) through both measured modes is reported too (the twin cannot take it: one ratio);
4. use: the measured ratio replaces the design's only when it differs from it by more than
   ``Z_REJECT`` of its std; otherwise the design is kept (``applied`` False, with the reason).

The per-mode std is the identification's own (the inverse Fisher information of the Whittle
polish on an ambient record, else the batch-means std over blocks, else the spread of the pole
cluster over model orders). The spread of the damping over the mode's cluster in the stabilization
diagram is reported per mode but not used: it measures how SSI-cov's damping moves with model
order, not the error of the polished estimate. Measured on 8 simulated 60 s ambient records per
truth (1 % and 4.5 %, design 2 %): the identification's std was 1.1-1.5 x the record-to-record
scatter of the mode's damping, the cluster spread 0.25-8 x it; the combined ratio erred by
rms 0.05 / 0.11 % (0.84 / 0.73 of its std). Mode 1 read +0.10 / +0.13 % high on average (3 / 1.6
standard errors; mode 2 unbiased): the weighting by the std leaves a fifth of that in the ratio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from maglev_ros.errors import UserError
from maglev_ros.modal.peaks import spectral_peak

from .model import ModelSpec, guideway_modal
from .recording import Recording

# the design value is rejected when it lies outside the two-sided 95 % interval of the estimate
# (normal errors): a 1-sigma rule would replace a right design value on a third of the recordings
Z_REJECT = 1.96
# a match needs MAC > 1/2: the identified shape then projects more of its norm on the twin's
# shape than on everything orthogonal to it (a shape unlike the twin's is no evidence of it)
MIN_MAC = 0.5
# the Rayleigh ratio is defined on the span's first two modes (design block, guideway.py)
RAYLEIGH_MODES = (1, 2)


def _f(x) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


@dataclass(frozen=True)
class ModeDamping:
    """One of the twin's modes 1-2 of the instrumented span and what was measured for it."""
    twin_mode: int                      # 1 or 2: the span's mode number in the twin
    twin_freq_hz: float
    twin_damping_ratio: float           # what the twin gives it now (design or spec's ratio)
    freq_hz: float | None               # measured (None: not matched)
    damping_ratio: float | None
    std_damping_ratio: float | None     # the identification's own std (used for weighting)
    cluster_std_damping_ratio: float | None   # spread over the stabilization cluster (reported only)
    mac: float | None                   # MAC of the matched shape with the twin's (best MAC if none)
    mode_id: str | None                 # id of the identified mode (M1, ...)
    reason: str
    std_freq_hz: float | None = None    # the identification's standard error of the frequency
    in_band: bool = True                # below the band limit the accelerometers pass (else not used)
    consistent: bool = True             # False: off the other spans' modes beyond chance (a spurious pole)

    @property
    def matched(self) -> bool:
        return self.damping_ratio is not None

    @property
    def usable(self) -> bool:
        return self.matched and self.in_band and self.consistent and self.std_damping_ratio is not None

    def to_dict(self) -> dict:
        return {"twin_mode": self.twin_mode, "twin_freq_hz": float(self.twin_freq_hz),
                "twin_damping_ratio": float(self.twin_damping_ratio), "freq_hz": _f(self.freq_hz),
                "damping_ratio": _f(self.damping_ratio), "std_damping_ratio": _f(self.std_damping_ratio),
                "cluster_std_damping_ratio": _f(self.cluster_std_damping_ratio), "mac": _f(self.mac),
                "mode_id": self.mode_id, "matched": self.matched, "reason": self.reason,
                "std_freq_hz": _f(self.std_freq_hz), "in_band": self.in_band, "consistent": self.consistent}


@dataclass(frozen=True)
class ExtraMode:
    """An identified mode of the instrumented span that no twin mode of that span claims (each twin
    mode below the twin's highest one + 10 % takes its nearest identified mode): physics the twin
    leaves out, e.g. an attached component's own mode, or a torsional mode of the deck."""
    freq_hz: float
    damping_ratio: float
    best_mac: float                     # best MAC with any twin mode of the span
    symmetric_share: float | None       # shape energy in the left+right symmetric part (None: no L/R pairs)
    mode_id: str
    peak_ratio: float = 0.0             # spectral peak at it over the local level (best channel)
    peak_needed: float = 0.0            # what the Welch estimate's own scatter allows by chance (3 std)

    @property
    def in_the_data(self) -> bool:
        """The recording shows it: its spectral peak clears the PSD estimate's scatter (an SSI pole
        without one is a numerical pole, whatever its stability)."""
        return self.peak_ratio > self.peak_needed

    @property
    def vertical(self) -> bool:
        """Not a torsional mode: left and right move together (or no pair says otherwise)."""
        return self.symmetric_share is None or self.symmetric_share >= 0.5

    def to_dict(self) -> dict:
        return {"freq_hz": float(self.freq_hz), "damping_ratio": _f(self.damping_ratio), "best_mac": _f(self.best_mac),
                "symmetric_share": _f(self.symmetric_share), "mode_id": self.mode_id, "vertical": self.vertical,
                "peak_ratio": _f(self.peak_ratio), "peak_needed": _f(self.peak_needed), "in_the_data": self.in_the_data}


@dataclass(frozen=True)
class MeasuredDamping:
    """The guideway's Rayleigh ratio measured on an ambient recording (see the module docstring).

    ``damping_ratio``: the one Rayleigh ratio on modes 1-2 of the instrumented span that reproduces
    the measured modes best (None: nothing measured); ``std_damping_ratio`` its std;
    ``applied``: whether the twin should take it (:attr:`twin_damping_ratio`), ``reason`` why."""
    damping_ratio: float | None
    std_damping_ratio: float | None
    design_damping_ratio: float
    modes: tuple[ModeDamping, ...]
    applied: bool
    reason: str
    span_id: str | None = None
    rayleigh_alpha_per_s: float | None = None   # exact Rayleigh pair through both measured modes
    rayleigh_beta_s: float | None = None
    chi2: float | None = None                   # disagreement of the two modes with one ratio (1 dof)
    channels: tuple[str, ...] = ()
    n_identified: int = 0
    source: str = ""
    identification: dict = field(default_factory=dict)
    extra_modes: tuple[ExtraMode, ...] = ()     # identified modes of the span the twin does not have
    spans: tuple["MeasuredDamping", ...] = ()   # each instrumented span's own result (when more than one)

    @property
    def each_span(self) -> tuple["MeasuredDamping", ...]:
        """Every instrumented span's own result, the span with most sensors first."""
        return self.spans or ((self,) if self.span_id is not None else ())

    @property
    def twin_damping_ratio(self) -> float | None:
        """The value for ``ModelSpec.guideway_damping_ratio``: the measured ratio when applied,
        else None (the design's)."""
        return self.damping_ratio if self.applied else None

    def to_dict(self) -> dict:
        return {"damping_ratio": _f(self.damping_ratio), "std_damping_ratio": _f(self.std_damping_ratio),
                "design_damping_ratio": float(self.design_damping_ratio), "applied": bool(self.applied),
                "reason": self.reason, "span_id": self.span_id,
                "rayleigh_alpha_per_s": _f(self.rayleigh_alpha_per_s),
                "rayleigh_beta_s": _f(self.rayleigh_beta_s), "chi2": _f(self.chi2),
                "modes": [m.to_dict() for m in self.modes], "channels": list(self.channels),
                "n_identified": int(self.n_identified), "source": self.source,
                "identification": dict(self.identification),
                "extra_modes": [m.to_dict() for m in self.extra_modes],
                **({"spans": [d.to_dict() for d in self.spans]} if self.spans else {})}


def _not_measured(design: float, reason: str, rec: Recording | None, **kw) -> MeasuredDamping:
    return MeasuredDamping(None, None, float(design), kw.pop("modes", ()), False, reason,
                           source=rec.name if rec is not None else "", **kw)


def _instrumented_spans(rec: Recording, spec: ModelSpec) -> list[int]:
    """Indices of the spans holding vertical guideway accelerometers, most accelerometers first."""
    counts = np.zeros(len(spec.spans), dtype=int)
    for n in _vertical(rec):
        x = rec.channels[n].position_m
        for i, sp in enumerate(spec.spans):
            if sp.start_m <= x <= sp.end_m:
                counts[i] += 1
                break
    return [int(i) for i in np.argsort(-counts, kind="stable") if counts[i] > 0]


def _vertical(rec: Recording) -> list[str]:
    """Guideway accelerometers with a position and not declared lateral (the twin is vertical)."""
    sensors = rec.metadata.get("sensors", {}) or {}
    return [n for n, c in rec.channels.items() if c.group == "guideway_accel" and c.position_m is not None
            and (sensors.get(n) or {}).get("direction", "vertical") != "lateral"]


def _span_channels(rec: Recording, span) -> list[str]:
    """Guideway accelerometers on ``span`` (an accelerometer without a position belongs to none)."""
    return [n for n in rec.names("guideway_accel")
            if rec.channels[n].position_m is not None and span.start_m <= rec.channels[n].position_m <= span.end_m]


def _data(rec: Recording, names: list[str] | None = None) -> tuple[np.ndarray, float, list[str]]:
    """(n, channels) guideway accelerations (``names``, default all) on one clock, the rate and the
    names: the channels of the most common length (one topic shares a rate), their mean rate."""
    names = list(names) if names is not None else rec.names("guideway_accel")
    sizes = [rec.channels[n].values.size for n in names]
    size = max(set(sizes), key=sizes.count)
    names = [n for n, s in zip(names, sizes) if s == size]
    t = rec.channels[names[0]].time_s
    fs = (t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else 0.0
    return np.stack([rec.channels[n].values for n in names], axis=1), float(fs), names


def _extra_modes(res, d_ij: np.ndarray, m_ij: np.ndarray, twin_f: np.ndarray, rec: Recording, vert: list[str],
                 col: list[int]) -> tuple[ExtraMode, ...]:
    """Identified modes no twin mode of the span claims (each twin mode takes its nearest identified
    one by the clustering distance), within the twin's own range (above its highest mode + 10 % the
    twin has no modes to compare with)."""
    claimed = {int(np.argmin(d_ij[:, j])) for j in range(d_ij.shape[1])}
    f_id = res.frequencies_hz()
    top = 1.1 * float(np.max(twin_f))
    sides = rec.metadata.get("sensors", {}) or {}
    pairs = {}
    for k, n in enumerate(vert):
        side = (sides.get(n) or {}).get("side")
        if side in ("left", "right"):
            pairs.setdefault(round(float(rec.channels[n].position_m), 3), {})[side] = col[k]
    pairs = [(p["left"], p["right"]) for p in pairs.values() if len(p) == 2]
    out = []
    for i in range(len(res.modes)):
        if i in claimed or not f_id[i] <= top:
            continue
        shape = np.asarray(res.complex_shapes[i])
        share = None
        if pairs:
            lft, rgt = np.array([shape[a] for a, _ in pairs]), np.array([shape[b] for _, b in pairs])
            tot = float(np.sum(np.abs(lft) ** 2 + np.abs(rgt) ** 2))
            share = float(np.sum(np.abs(lft + rgt) ** 2) / (2 * tot)) if tot > 0 else None
        m = res.modes[i]
        ratio, needed = spectral_peak([rec.channels[n].values for n in vert],
                                      [rec.channels[n].sample_rate_hz for n in vert], float(m.frequency_hz),
                                      np.delete(f_id, i))
        out.append(ExtraMode(float(m.frequency_hz), float(m.damping_ratio), float(np.max(m_ij[i])) if m_ij.size else 0.0,
                             share, str(m.id), ratio, needed))
    return tuple(out)


def _cluster_spread(res, k: int) -> float | None:
    st = res.stabilization
    if st is None or len(st) == 0:
        return None
    z = st.damping_ratio[st.cluster == k]
    return float(np.std(z, ddof=1)) if z.size > 1 else None


def measure_damping(ambient: Recording | None, spec: ModelSpec, below_hz: float | None = None) -> MeasuredDamping:
    """Measure the guideway's Rayleigh damping ratio on ``ambient`` (see the module docstring).
    ``below_hz``: the band the accelerometers pass (an instrument's low-pass found on the passes,
    :mod:`.instrument_band`); a mode above it is not used, its damping being read through the filter's
    roll-off (a 100 Hz filter: the 91 Hz mode read 1.5 % for a true 2 %).
    Every span with vertical accelerometers is measured on its own (``spans``); the twin's one ratio
    comes from the measured modes of all of them, the other fields are the span with most sensors'.
    Never raises on a recording without modes: ``applied`` is then False with the reason."""
    if ambient is None:
        d = spec.spans[0].props.damping_ratio if spec.spans else float("nan")
        return _not_measured(d, "no ambient recording: design damping kept", None)
    spans = _instrumented_spans(ambient, spec)
    design = spec.spans[spans[0] if spans else 0].props.damping_ratio
    if ambient.kind != "ambient":
        return _not_measured(design, f"run.kind is {ambient.kind!r}, not 'ambient': design damping kept", ambient)
    if not spans:
        return _not_measured(design, "no vertical guideway accelerometer on a span of the line: design damping kept",
                             ambient)
    modal = guideway_modal(spec)
    per = [_measure_span(ambient, spec, modal, i, below_hz) for i in spans]
    if len(per) == 1:
        return per[0]
    return _combined(per)


def _combined(per: list[MeasuredDamping]) -> MeasuredDamping:
    """The first span's result with the one ratio of every span's measured modes (the twin damps all
    spans alike) and each span's own result in ``spans``."""
    where = [(k, j) for k, d in enumerate(per) for j, m in enumerate(d.modes) if m.usable]
    if not where:
        why = "; ".join(f"span {d.span_id}: {d.reason}" for d in per)
        return replace(per[0], damping_ratio=None, std_damping_ratio=None, applied=False, chi2=None,
                       reason=f"no span's modes 1-2 measured ({why})", spans=tuple(per))
    zeta, std, chi2, applied, reason, dropped = _one_ratio([per[k].modes[j] for k, j in where],
                                                           per[0].design_damping_ratio,
                                                           [per[k].span_id for k, _ in where])
    for i in dropped:           # marked in its span's own result: its frequency is not the span's mode either
        k, j = where[i]
        modes = list(per[k].modes)
        modes[j] = replace(modes[j], consistent=False,
                           reason=modes[j].reason + "; damping off the other spans' modes beyond chance: not used")
        per[k] = replace(per[k], modes=tuple(modes))
    return replace(per[0], damping_ratio=zeta, std_damping_ratio=std, applied=applied, reason=reason, chi2=chi2,
                   spans=tuple(per))


def _one_ratio(used: list[ModeDamping], design: float, span_ids: list[str] | None = None
               ) -> tuple[float, float, float | None, bool, str, list[int]]:
    """(ratio, std, chi2, applied, reason, indices of ``used`` left out): the inverse-variance weighted mean of the measured modes'
    damping, its std widened by the Birge ratio when they disagree, applied when it rejects ``design``.
    With three modes or more, a mode off the mean of the others beyond chance (:func:`_outliers`) is
    left out: one ratio damps every span, and a spurious narrow pole matched in a span's place (0.35 %
    +- 0.02 % beside five modes at 2 %) would carry the mean by its small std alone."""
    span_ids = list(span_ids) if span_ids else None
    out = _outliers(used)
    dropped = ""
    if out:
        ids = span_ids or [None] * len(used)
        dropped = "; left out as off the other modes beyond chance: " + ", ".join(
            f"{'span ' + ids[i] + ' ' if ids[i] else ''}mode {used[i].twin_mode} {100 * used[i].damping_ratio:.2f} "
            f"+- {100 * used[i].std_damping_ratio:.2f} % ({r:.1f} std)" for i, r in out)
        keep = [i for i in range(len(used)) if i not in {i for i, _ in out}]
        used = [used[i] for i in keep]
        span_ids = [span_ids[i] for i in keep] if span_ids else None
    z = np.array([m.damping_ratio for m in used])
    s = np.array([m.std_damping_ratio for m in used])
    w = 1.0 / s ** 2
    zeta = float(np.sum(w * z) / np.sum(w))
    std = float(1.0 / math.sqrt(np.sum(w)))
    chi2 = None
    if len(used) > 1:
        chi2 = float(np.sum(w * (z - zeta) ** 2))
        std *= math.sqrt(max(chi2 / (len(used) - 1), 1.0))   # Birge ratio: the modes' disagreement widens it
    where = [f"span {sid} " if sid else "" for sid in (span_ids or [None] * len(used))]
    which = " and ".join(f"{w_}mode {m.twin_mode} {100 * m.damping_ratio:.2f} +- {100 * m.std_damping_ratio:.2f} %"
                         for w_, m in zip(where, used))
    alone = "" if len(used) != 1 or span_ids else f" (mode {3 - used[0].twin_mode} not measured)"
    alone += dropped
    dev = (zeta - design) / std
    # applied only when the data reject the design value
    applied = abs(dev) > Z_REJECT
    if applied:
        reason = (f"measured {100 * zeta:.2f} +- {100 * std:.2f} % from {which}{alone}: "
                  f"{abs(dev):.1f} std from the design's {100 * design:.2f} %, applied")
    else:
        reason = (f"measured {100 * zeta:.2f} +- {100 * std:.2f} % from {which}{alone}: within "
                  f"{Z_REJECT:g} std of the design's {100 * design:.2f} %, design damping kept")
    return zeta, std, chi2, bool(applied), reason, [i for i, _ in out]


def _outliers(used: list[ModeDamping], alpha: float = 1e-3) -> list[tuple[int, float]]:
    """(index, standard errors) of the modes left out one at a time, worst first, while three or more
    remain: a mode whose damping is off the others' weighted mean by more than the two-sided normal
    point of ``alpha`` shared over the modes tested (Bonferroni), in the combined std of both."""
    from scipy.stats import norm
    idx = list(range(len(used)))
    out = []
    while len(idx) >= 3:
        z = np.array([used[i].damping_ratio for i in idx])
        s = np.array([used[i].std_damping_ratio for i in idx])
        w = 1.0 / s ** 2
        r = np.empty(len(idx))
        for k in range(len(idx)):
            wo = np.delete(w, k)
            mo = float(np.sum(wo * np.delete(z, k)) / np.sum(wo))
            r[k] = abs(z[k] - mo) / math.sqrt(s[k] ** 2 + 1.0 / np.sum(wo))
        k = int(np.argmax(r))
        if r[k] <= norm.isf(alpha / (2 * len(idx))):
            break
        out.append((idx[k], float(r[k])))
        del idx[k]
    return out


def _measure_span(ambient: Recording, spec: ModelSpec, modal, span: int, below_hz: float | None) -> MeasuredDamping:
    """Modes 1-2 of one span identified on its own accelerometers, matched to the twin's, one ratio."""
    from maglev_ros.modal.bands import identify_bands, plan_bands
    from maglev_ros.modal.stabilization import mac

    design = spec.spans[span].props.damping_ratio
    sp = spec.spans[span]
    sel = np.flatnonzero(modal.span_index == span)
    sel = sel[np.argsort(modal.freq_hz[sel])]
    if sel.size < len(RAYLEIGH_MODES):
        return _not_measured(design, f"the twin has fewer than {len(RAYLEIGH_MODES)} modes on span {sp.span_id}",
                             ambient, span_id=sp.span_id)

    # 1. identification: the `maglev-ros modes` verb's path for an ambient record, its defaults, on the
    # span's own accelerometers: identical spans ring at one frequency, and with their sensors in the
    # set the pole is repeated and never stabilizes (three decoupled spans: no mode identified)
    y, fs, names = _data(ambient, _span_channels(ambient, sp))
    try:
        if not np.all(np.isfinite(y)):
            raise UserError("guideway accelerations hold NaN or inf")
        if not fs > 0:
            raise UserError(f"{y.shape[0]} samples give no sampling rate")
        # the verb scales channels only when their units differ; guideway accelerations are all m/s^2
        plan = plan_bands(fs, y.shape[0], y.shape[1], stationary=True, scale_channels=False,
                          scale_source="all channels in m/s^2: recorded amplitudes kept")
        res, _ = identify_bands(y, fs, plan, names)
    except (UserError, np.linalg.LinAlgError) as e:
        return _not_measured(design, f"modal identification failed ({e}): design damping kept", ambient,
                             span_id=sp.span_id, channels=tuple(names))
    ident = {"fs_hz": fs, "duration_s": y.shape[0] / fs if fs > 0 else 0.0,
             "searched_hz": [float(plan.fmin_hz), float(plan.fmax_hz)], "n_bands": len(plan.bands),
             "method": res.method, "uncertainty": res.uncertainty,
             "modes_hz": [round(float(m.frequency_hz), 4) for m in res.modes]}
    common = dict(span_id=sp.span_id, channels=tuple(names), n_identified=len(res.modes), identification=ident)

    # 2. matching on the vertical accelerometers with a position
    vert = [n for n in _vertical(ambient) if n in names]
    col = [names.index(n) for n in vert]
    x = np.array([ambient.channels[n].position_m for n in vert], dtype=float)
    twin_f = modal.freq_hz[sel]
    twin_z = modal.damping_ratio[sel]
    twin_shapes = modal.shapes_at(x)[:, sel] if x.size else np.zeros((0, sel.size))
    n_id = len(res.modes)
    if n_id and x.size:
        meas_shapes = np.array([np.asarray(res.complex_shapes[k])[col] for k in range(n_id)]).T
        m_ij = np.atleast_2d(mac(meas_shapes, twin_shapes.astype(complex)))          # (n_id, n_twin)
        f_id = res.frequencies_hz()
        d_ij = np.abs(np.log(f_id[:, None] / twin_f[None, :])) + (1.0 - m_ij)
    else:
        m_ij = d_ij = np.zeros((n_id, sel.size))
    modes = []
    for j, num in enumerate(RAYLEIGH_MODES):
        jj = num - 1
        base = dict(twin_mode=num, twin_freq_hz=float(twin_f[jj]), twin_damping_ratio=float(twin_z[jj]))
        if n_id == 0 or x.size == 0:
            why = "no mode identified" if n_id == 0 else "no vertical accelerometer with a position"
            modes.append(ModeDamping(**base, freq_hz=None, damping_ratio=None, std_damping_ratio=None,
                                     cluster_std_damping_ratio=None, mac=None, mode_id=None, reason=why))
            continue
        mine = [i for i in range(n_id) if int(np.argmin(d_ij[i])) == jj]
        best = min(mine, key=lambda i: d_ij[i, jj]) if mine else None
        if best is None or m_ij[best, jj] <= MIN_MAC:
            i = int(np.argmax(m_ij[:, jj]))
            why = (f"no identified mode is nearest to it (best MAC {m_ij[i, jj]:.2f} at "
                   f"{res.modes[i].frequency_hz:.2f} Hz)") if best is None else (
                   f"nearest identified mode {res.modes[best].frequency_hz:.2f} Hz has MAC "
                   f"{m_ij[best, jj]:.2f} <= {MIN_MAC}")
            modes.append(ModeDamping(**base, freq_hz=None, damping_ratio=None, std_damping_ratio=None,
                                     cluster_std_damping_ratio=None, mac=float(m_ij[i, jj]), mode_id=None,
                                     reason=why))
            continue
        m = res.modes[best]
        sz = m.std_damping_ratio if np.isfinite(m.std_damping_ratio) and m.std_damping_ratio > 0 else None
        cs = _cluster_spread(res, best)
        if sz is None and cs is not None and cs > 0:
            sz = cs                      # no own std reported: the cluster spread is all there is
        why = f"matched {m.id} (MAC {m_ij[best, jj]:.3f}, {100 * (m.frequency_hz / twin_f[jj] - 1):+.1f} % vs twin)"
        if sz is None:
            why += "; no uncertainty: not used"
        in_band = below_hz is None or m.frequency_hz <= below_hz
        if not in_band:
            why += f"; above the {below_hz:.0f} Hz the accelerometers pass: not used"
        modes.append(ModeDamping(**base, freq_hz=float(m.frequency_hz), damping_ratio=float(m.damping_ratio),
                                 std_damping_ratio=sz, cluster_std_damping_ratio=cs,
                                 mac=float(m_ij[best, jj]), mode_id=m.id, reason=why,
                                 std_freq_hz=_f(getattr(m, "std_frequency_hz", None)), in_band=in_band))
    modes = tuple(modes)
    if n_id and x.size:
        common["extra_modes"] = _extra_modes(res, d_ij, m_ij, twin_f, ambient, vert, col)

    # 3. one Rayleigh ratio from the measured modes
    used = [m for m in modes if m.usable]
    if n_id == 0:
        return _not_measured(design, "no mode identified in the ambient recording: design damping kept", ambient,
                             modes=modes, **common)
    if not used:
        why = "; ".join(f"mode {m.twin_mode}: {m.reason}" for m in modes)
        return _not_measured(design, f"no twin mode 1-2 of span {sp.span_id} measured ({why}): design damping kept",
                             ambient, modes=modes, **common)
    zeta, std, chi2, applied, reason, _ = _one_ratio(used, design)
    alpha = beta = None
    if len(used) == 2:
        # the exact Rayleigh pair through both: zeta_j = a / (2 w_j) + b w_j / 2 (measured w_j)
        om = 2 * math.pi * np.array([m.freq_hz for m in used])
        a_mat = np.column_stack([1.0 / (2 * om), om / 2])
        alpha, beta = (float(v) for v in np.linalg.solve(a_mat, np.array([m.damping_ratio for m in used])))
    return MeasuredDamping(zeta, std, float(design), modes, bool(applied), reason, sp.span_id, alpha, beta, chi2,
                           tuple(names), len(res.modes), ambient.name, ident, common.get("extra_modes", ()))
