"""The pattern of the instrumented span's bending modes in the ambient recording, against the twin's.

The girder's density, and its stiffness together with its bearings', scale every bending mode of a
span alike, so the ratio f2 / f1 of its second to its first vertical bending frequency depends on
none of them: it changes only with how stiffness, mass and support are distributed along the span.
It is compared with the calibrated twin's (whose E and kb set the girder's stiffness relative to its
bearings). Soft bearings lower it (the first mode drops more); a damaged zone between a quarter point
and midspan, or a mass near midspan, raises it. The ambient recording measures both modes with standard
errors (SSI-cov, :mod:`.damping`); the twin's own error of the ratio is taken as its change when its
mesh is doubled. A ratio off the twin's by more than ``N_SIGMA`` of their combined standard error is a
located mismatch. Measured on an independent simulator's recordings: spans without a change within
0.3 % (about two standard errors), soft bearings -2.6 and -4.4 %, damaged zones +4.7 and +7.1 %, a
midspan attachment +9.3 %.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .damping import MeasuredDamping
from .localize import Mismatch
from .model import ModelSpec, guideway_modal
from .recording import Recording
from .resonator import resonator_modal

N_SIGMA = 3.0     # a 3-standard-error departure: a 0.3 % chance for a Gaussian error


@dataclass(frozen=True)
class ModePattern:
    span_id: str
    position_m: tuple[float, float]
    channels: tuple[str, ...]
    time_s: tuple[float, float]
    source: str                         # the ambient recording
    measured_hz: tuple[float, float]    # modes 1 and 2 of the span
    std_hz: tuple[float, float]
    twin_hz: tuple[float, float]
    log_ratio_shift: float              # ln(measured f2/f1 / twin f2/f1)
    std: float                          # its standard error (identification and twin mesh)

    @property
    def n_sigma(self) -> float:
        return abs(self.log_ratio_shift) / self.std if self.std > 0 else math.inf

    @property
    def flagged(self) -> bool:
        return self.n_sigma > N_SIGMA

    def words(self) -> str:
        pct = 100 * (math.exp(self.log_ratio_shift) - 1)
        m, t = self.measured_hz, self.twin_hz
        what = ("a damaged zone between a quarter point and midspan, or a mass near midspan (they lower the first "
                "mode more)" if pct > 0 else "softer bearings (they lower the first mode more)")
        return (f"Span {self.span_id}'s first two bending modes ring at {m[0]:.2f} and {m[1]:.2f} Hz in the ambient "
                f"recording (twin {t[0]:.2f} and {t[1]:.2f} Hz): their ratio is {pct:+.1f} % off the twin's "
                f"({self.n_sigma:.0f} standard errors). The girder's density, and its stiffness with the bearings', "
                f"scale both modes alike and cannot change it: how stiffness, mass or support are distributed along the span differs from the "
                f"twin, e.g. {what}.")

    def to_mismatch(self) -> Mismatch:
        return Mismatch(self.channels, self.time_s, self.position_m,
                        (min(self.measured_hz[0], self.twin_hz[0]), max(self.measured_hz[1], self.twin_hz[1])),
                        self.n_sigma, "guideway_accel", f"{self.source} (span {self.span_id}'s mode ratio)",
                        explanation=self.words())

    def to_dict(self) -> dict:
        return {"span": self.span_id, "measured_hz": list(self.measured_hz), "std_hz": list(self.std_hz),
                "twin_hz": list(self.twin_hz), "ratio_shift": math.exp(self.log_ratio_shift) - 1,
                "standard_errors": self.n_sigma, "flagged": self.flagged}


def _span_pair(spec: ModelSpec, span_index: int, near_hz: tuple[float, float]) -> tuple[float, float]:
    """The span's twin modes nearest the measured two (an added resonator brings a mode of its own)."""
    if spec.resonator is not None:
        m = resonator_modal(spec.with_(resonator=None), spec.resonator)
    else:
        m = guideway_modal(spec)
    f = m.freq_hz[m.span_index == span_index]
    return tuple(float(f[np.argmin(np.abs(f - x))]) for x in near_hz)


def mode_pattern(damping: MeasuredDamping, spec: ModelSpec, ambient: Recording | None) -> ModePattern | None:
    """The instrumented span's mode ratio against ``spec``'s, or None (no ambient recording, modes 1
    and 2 not both matched with standard errors)."""
    if ambient is None or damping.span_id is None:
        return None
    modes = {m.twin_mode: m for m in damping.modes if m.freq_hz is not None and m.consistent}
    if not {1, 2} <= set(modes) or any(not (modes[k].std_freq_hz or 0) > 0 for k in (1, 2)):
        return None
    ids = [s.span_id for s in spec.spans]
    i = ids.index(damping.span_id)
    f1, f2 = modes[1].freq_hz, modes[2].freq_hz
    t1, t2 = _span_pair(spec, i, (f1, f2))
    num = spec.config.numerics
    fine = spec.with_(config=replace(spec.config, numerics=replace(num, n_elements_per_span=2 * num.n_elements_per_span)))
    f1f, f2f = _span_pair(fine, i, (f1, f2))
    mesh = abs(math.log((f2f / f1f) / (t2 / t1)))
    s1, s2 = modes[1].std_freq_hz, modes[2].std_freq_hz
    std = math.sqrt((s1 / f1) ** 2 + (s2 / f2) ** 2 + mesh ** 2)
    sp = spec.spans[i]
    return ModePattern(sp.span_id, (sp.start_m, sp.end_m), tuple(damping.channels),
                       (float(ambient.t0_s), float(ambient.t1_s)), ambient.source, (f1, f2), (s1, s2), (t1, t2),
                       math.log((f2 / f1) / (t2 / t1)), std)


def mode_patterns(damping: MeasuredDamping, spec: ModelSpec, ambient: Recording | None) -> tuple[ModePattern, ...]:
    """Every instrumented span's mode ratio (:func:`mode_pattern` of each span's own measurement), most
    standard errors first."""
    out = [p for d in damping.each_span if (p := mode_pattern(d, spec, ambient)) is not None]
    return tuple(sorted(out, key=lambda p: -p.n_sigma))

