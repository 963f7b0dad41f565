"""Which span rings at another frequency than the twin says: each span's first bending mode from the
free decay after the vehicle has left it, measured against the calibrated twin, relative to the
other spans.

Why: a local change of one girder (an attached mass or component, a stiffness loss, a softer
bearing) detunes that span's first mode by a few per cent. In band powers the detuned mode moves
energy across a band edge, which the frame and persistent band tests (:mod:`.localize`) can miss
(a 60 Hz, 3 % mass attachment lowered its span's first mode by 3 %; the band misfits
stayed under their bars), whereas a frequency read from the ring-down is sharp: after the last
magnet has left a span the span rings freely and SSI-cov on that window
(:mod:`maglev_ros.modal.free_decay`) gives its first mode to ~0.05 %.

Method, per pass and span: the span's guideway accelerometers over the free-decay window (from
``margin_s`` after the rearmost magnet left the span to the end of the recording, at least
``min_window_s`` long); the identified pole nearest the twin's first mode of that span (within
``search_rel``) against the twin's eigenfrequency, ``d = ln(f_measured / f_twin)``. The calibration
fits one Young's modulus for the whole line, so a deviation that all spans share is the
calibration's and is removed: each span's deviation is taken relative to the median over all spans
(three or more; with two spans, relative to the other one, which then reads the opposite). A span
is reported when that relative deviation is at least ``min_rel`` in every pass, with the same sign.
Measured on simulated cases' calibrated twins: in a clean case every span
read -0.31..-0.38 % against the twin and within 0.05 % of each other; a 3 % mass attachment read
-3.2 % against its peers, a 20 % stiffness loss -11.1 %, a bearing at 2 % of its stiffness -15.5 %. The bar
(1 %, 20x that scatter) leaves room for what real spans differ by and what another simulator's
discretisation does.
Not by hand where it matters: the identification is the suite's SSI-cov; what is written here is
the window choice per span and the comparison (~60 lines).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from maglev_ros.modal.free_decay import identify_free_decay, select_free_decay
from maglev_ros.modal.ssi_cov import SSICov

from .localize import Mismatch
from .model import ModelSpec, guideway_modal
from .recording import Recording

SPAN_MODE_MIN_REL = 0.01


@dataclass(frozen=True)
class SpanModeShift:
    """One span's first mode, measured in each pass vs the twin."""
    span_id: str
    span_index: int
    start_m: float
    end_m: float
    channels: tuple[str, ...]
    twin_hz: float
    measured_hz: tuple[float, ...]           # per pass (NaN: not identified)
    relative: tuple[float, ...]              # per pass: ln(f/f_twin) minus the spans' median
    windows_s: tuple[tuple[float, float], ...]

    @property
    def shift(self) -> float:
        """Mean relative deviation over the passes (ln; ~ relative frequency change)."""
        r = np.asarray(self.relative, float)
        return float(np.mean(r)) if r.size and np.all(np.isfinite(r)) else math.nan

    def consistent(self, min_rel: float = SPAN_MODE_MIN_REL) -> bool:
        r = np.asarray(self.relative, float)
        return bool(r.size and np.all(np.isfinite(r)) and np.all(np.abs(r) >= min_rel)
                    and (np.all(r > 0) or np.all(r < 0)))

    def to_mismatch(self, min_rel: float = SPAN_MODE_MIN_REL) -> Mismatch:
        f = [x for x in self.measured_hz if np.isfinite(x)] + [self.twin_hz]
        t0 = min(w[0] for w in self.windows_s)
        t1 = max(w[1] for w in self.windows_s)
        return Mismatch(self.channels, (t0, t1), (self.start_m, self.end_m), (min(f), max(f)),
                        abs(self.shift) / min_rel, "guideway_accel",
                        "free decay after each pass (span's first mode vs the twin)")

    def words(self) -> str:
        pct = 100 * (math.exp(self.shift) - 1)
        meas = ", ".join(f"{x:.2f}" for x in self.measured_hz)
        return (f"span {self.span_id}'s first bending mode rings at {meas} Hz after the vehicle has left it "
                f"(twin {self.twin_hz:.2f} Hz), {pct:+.1f} % relative to the other spans in every pass")


def span_mode_shifts(passes: list[Recording], spec: ModelSpec, *, margin_s: float = 0.1,
                     min_window_s: float = 1.0, search_rel: float = 0.4) -> list[SpanModeShift]:
    """Every span's first-mode deviation (see the module docstring). Spans without a guideway
    accelerometer are left out; a pass without a usable free decay of a span carries NaN there."""
    modal = guideway_modal(spec)
    spans = spec.spans
    if len(spans) < 2:
        return []
    twin = [float(np.min(modal.freq_hz[modal.span_index == i])) if np.any(modal.span_index == i) else math.nan
            for i in range(len(spans))]
    dev = np.full((len(passes), len(spans)), np.nan)
    meas = np.full_like(dev, np.nan)
    wins: dict = {}
    chans: dict = {}
    for k, rec in enumerate(passes):
        if rec.position_time_s is None:
            continue
        offs = (rec.metadata.get("vehicle") or {}).get("magnet_offsets_m") or [0.0]
        for i, sp in enumerate(spans):
            names = [n for n, c in rec.channels.items() if c.group == "guideway_accel" and c.position_m is not None
                     and sp.start_m <= c.position_m <= sp.end_m]
            if not names or not np.isfinite(twin[i]):
                continue
            chans[i] = tuple(names)
            fs = rec.channels[names[0]].sample_rate_hz
            t = rec.channels[names[0]].time_s
            if any(rec.channels[n].time_s.size != t.size for n in names):
                continue
            y = np.stack([rec.channels[n].values for n in names], axis=1)
            if not np.all(np.isfinite(y)):
                continue
            try:
                w = select_free_decay(y, fs, time_s=t, position_m=rec.position_m,
                                      position_time_s=rec.position_time_s, span_end_m=sp.end_m,
                                      rear_offset_m=float(min(offs)), margin_s=margin_s, min_length_s=min_window_s)
                if w.stop_s - w.start_s < min_window_s - 1.0 / fs:
                    continue
                f_lo, f_hi = twin[i] * (1 - search_rel), twin[i] * (1 + search_rel)
                res = identify_free_decay(y, fs, w, SSICov(block_rows=40, orders=range(2, 41, 2),
                                                           freq_range_hz=(f_lo, f_hi), spectrum=False))
            except Exception:            # no decay after the pass, nothing identified: unknown there
                continue
            f = res.frequencies_hz()
            if f.size == 0:
                continue
            fm = float(f[np.argmin(np.abs(f - twin[i]))])
            meas[k, i] = fm
            dev[k, i] = math.log(fm / twin[i])
            wins.setdefault(i, []).append((float(t[0] + w.start_s), float(t[0] + w.stop_s)))
    out = []
    for i, sp in enumerate(spans):
        if i not in chans:
            continue
        rel = []
        for k in range(len(passes)):
            # the median over ALL spans (itself included): with three spans and one detuned, the median
            # of the two others would be pulled halfway to the odd one; with two spans, the other one
            ok = np.isfinite(dev[k])
            if ok.sum() >= 3:
                ref = float(np.median(dev[k, ok]))
            else:
                other = [dev[k, j] for j in np.flatnonzero(ok) if j != i]
                ref = other[0] if ok.sum() == 2 and other else math.nan
            rel.append(float(dev[k, i] - ref) if np.isfinite(dev[k, i]) and np.isfinite(ref) else math.nan)
        out.append(SpanModeShift(sp.span_id, i, float(sp.start_m), float(sp.end_m), chans[i], twin[i],
                                 tuple(float(x) for x in meas[:, i]), tuple(rel), tuple(wins.get(i, ()))))
    return out


def detuned_spans(shifts: list[SpanModeShift], min_rel: float = SPAN_MODE_MIN_REL) -> list[SpanModeShift]:
    """The spans whose first mode is off its peers' consistently (strongest first)."""
    return sorted((s for s in shifts if s.consistent(min_rel)), key=lambda s: -abs(s.shift))
