"""Catalogue of physics extensions: each a parameterised addition to the twin with its signature.

Every entry builds ``Hypothesis`` objects (one per candidate location): the parameter with its
bounds and trial value, how it changes a :class:`~.model.ModelSpec`, whether it is physically
plausible, and how to say it to a rail engineer.

| effect | category | parameter | signature |
|---|---|---|---|
| bearing_stiffness | boundary_condition | log10 kb factor of one span end | that span's mode lower, larger response near that end, mostly when the vehicle is there |
| control_delay | control | transport delay or first-order lag tau [s] | vehicle gap/accel amplitude at levitation frequencies, all along the line; above 1/(2 pi tau) a delay turns the phase, a lag attenuates |
| magnet_nonlinearity | magnetic_force | current headroom L / peak demand | saturating current (I0 + L tanh((I-I0)/L), on both sides of I0 or above it only): extra gap excursions where demand is high; limited above only, skewed magnet accelerations |
| ambient_excitation | excitation | log10 modal force PSD | guideway vibration at its modes before entry and after exit (no vehicle) |
| girder_stiffness_loss | guideway_structure | relative EI loss of one span, or of one zone (a quarter) of an instrumented span | that span deflects more, its modes drop (a zone: each mode by its curvature there) |
| carbody_flexibility | vehicle_structure | car-body bending frequency [Hz] | vehicle accel band near the bending frequency |
| sensor_error | instrumentation | scale, offset, drift of one channel (or a dropout) | one channel only, others agree with the twin |
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .model import CAL_PARAMS, ModelSpec, guideway_modal

CATEGORIES = ("boundary_condition", "control", "magnetic_force", "excitation", "guideway_structure",
              "vehicle_structure", "suspension", "instrumentation", "other")
EFFECTS = {"bearing_stiffness": "boundary_condition", "control_delay": "control",
           "magnet_nonlinearity": "magnetic_force", "ambient_excitation": "excitation",
           "girder_stiffness_loss": "guideway_structure", "carbody_flexibility": "vehicle_structure",
           "sensor_error": "instrumentation"}
# categories of physics that act on the vehicle's channels only: fitted and judged there
# (fitting.fit_hypothesis, diagnose.Diagnoser.fit)
VEHICLE_WIDE = ("control", "magnetic_force")
# physics whose effect grows with the excitation (current saturation at the demand peaks): held out
# at the training amplitude too, on the second half of the training pass (on the slower pass alone a
# 1.2 x saturation cut the true twin's magnet misfit 4 %, on the fast pass 16 %)
AMPLITUDE_DEPENDENT = ("magnet_nonlinearity",)
# what separates levitation physics from re-fitted control gains (kp, kv), its null model: said in a
# rejection when the gains explain the held-out pass nearly as well
SEPARATED_BY = {
    "control_delay": "a recorded magnet current, or a faster pass that excites the control above 20 Hz",
    "magnet_nonlinearity": "a pass with a clearly larger current demand, faster or over a rougher stretch,",
}


@dataclass(frozen=True, eq=False)
class Hypothesis:
    effect: str
    label: str                                   # effect + location, unique
    param_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    trial: tuple[float, ...]
    apply: Callable[[ModelSpec, np.ndarray], ModelSpec]
    needs_sim: bool = True
    location: dict = field(default_factory=dict)  # position_m [x0,x1] | None, span, channels
    plausible: Callable[[np.ndarray], tuple[bool, str]] = lambda p: (True, "")
    describe: Callable[[np.ndarray, ModelSpec], tuple[str, dict]] = lambda p, s: ("", {})
    band_hz: tuple[float, float] | None = None
    log_search: bool = False                     # scale-like parameter: search on a geometric grid
    form: str = ""                               # one of several models of one effect (delay/lag, zone)

    @property
    def category(self) -> str:
        return EFFECTS.get(self.effect, "other")


def _span_factor(spec: ModelSpec, i: int, v: float) -> tuple:
    f = list(spec.span_e_factor) or [1.0] * len(spec.spans)
    f[i] = v
    return tuple(f)


def _bearing(spec: ModelSpec, i: int, end: int, v: float) -> tuple:
    b = [list(x) for x in (spec.bearing_factor or tuple((1.0, 1.0) for _ in spec.spans))]
    b[i][end] = v
    return tuple(tuple(x) for x in b)


def _loss_plausible(of: str, max_loss: float, beyond: str) -> Callable[[np.ndarray], tuple[bool, str]]:
    """A stiffness loss is a finding from 5 % (smaller is within the calibration's reach) up to
    ``max_loss`` (beyond it the girder, or the zone ``of`` names, would not carry the line)."""
    def plaus(p):
        if p[0] < 0.05:
            return False, f"fitted stiffness change {-p[0] * 100:+.0f} %{of} is not a loss of at least 5 %"
        if p[0] > max_loss:
            return False, f"fitted loss {p[0] * 100:.0f} %{of} {beyond}"
        return True, ""
    return plaus


def girder_hypotheses(spec: ModelSpec, f1_hz: np.ndarray) -> list[Hypothesis]:
    out = []
    for i, s in enumerate(spec.spans):
        def apply(sp, p, i=i):
            return sp.with_(span_e_factor=_span_factor(sp, i, 1.0 - float(p[0])))

        plaus = _loss_plausible("", 0.8, "is beyond a girder still in service")

        def desc(p, sp, i=i, s=s):
            f_new = f1_hz[i] * math.sqrt(max(1 - p[0], 1e-6))
            return (f"Girder span {s.span_id} ({s.start_m:.1f}-{s.end_m:.1f} m) is about {p[0] * 100:.0f} % "
                    f"less stiff in bending than the calibrated line (e.g. cracking or prestress loss): it "
                    f"deflects more under the vehicle and its first bending mode drops from about "
                    f"{f1_hz[i]:.1f} Hz to {f_new:.1f} Hz.",
                    {"span": s.span_id, "stiffness_loss": float(p[0]),
                     "first_mode_hz": float(f_new)})
        out.append(Hypothesis("girder_stiffness_loss", f"girder_stiffness_loss@{s.span_id}", ("stiffness_loss",),
                              (-0.3,), (0.85,), (0.3,), apply,
                              location={"position_m": [s.start_m, s.end_m], "span": s.span_id},
                              plausible=plaus, describe=desc,
                              band_hz=(0.5 * f1_hz[i], 1.05 * f1_hz[i])))
    return out


ZONES_PER_SPAN = 4   # quarters: a sensor at 1/8, 1/4, 1/2, 3/4 or 7/8 of a span sees each one's curvature


def tie_first_mode(spec: ModelSpec, span_index: int, f1_hz: float, iterations: int = 3) -> ModelSpec:
    """``spec`` with the line's calibrated E (``cal``) scaled so that span ``span_index``'s first bending
    mode rings at ``f1_hz``. A damaged zone lowers the measured span's first mode, which the calibrated
    E had matched: with the zone in, E goes back to what the sound girder has, the value the unmeasured
    spans need. f1 ~ sqrt(E) but for the bearings' share, so a few fixed-point steps."""
    k = CAL_PARAMS.index("E")
    for _ in range(iterations):
        m = guideway_modal(spec)
        f = float(m.freq_hz[m.span_index == span_index].min())
        step = 2.0 * math.log(f1_hz / f)
        if abs(step) < 1e-5:
            break
        cal = list(spec.cal) + [0.0] * (len(CAL_PARAMS) - len(spec.cal))
        cal[k] += step
        spec = spec.with_(cal=tuple(cal))
    return spec


def girder_zone_hypotheses(spec: ModelSpec, span_indices, f1_hz: np.ndarray,
                           measured_f1_hz: dict | None = None) -> list[Hypothesis]:
    """A damaged zone (one quarter of the span, EI lowered there) on each span in ``span_indices``
    (those with guideway sensors: the mode shapes they sample are what place a zone). A uniform
    loss lowers every mode of the span by the same ratio; a zone lowers each mode by its curvature
    there, so it is told from a changed E by the pattern of the span's modes. ``measured_f1_hz``
    (span index -> the first mode measured on the ambient recording): the line's E is re-scaled with
    each trial loss so that span keeps that mode (:func:`tie_first_mode`); the loss is then set by
    the rest of the span's response, not traded against E."""
    measured_f1_hz = measured_f1_hz or {}
    out = []
    for i in span_indices:
        s = spec.spans[i]
        q = s.length_m / ZONES_PER_SPAN
        for k in range(ZONES_PER_SPAN):
            x0, x1 = k * q, (k + 1) * q

            def apply(sp, p, i=i, x0=x0, x1=x1):
                keep = tuple(z for z in sp.girder_zones if (z[0], z[1], z[2]) != (i, x0, x1))
                out = sp.with_(girder_zones=keep + ((i, x0, x1, 1.0 - float(p[0])),))
                return tie_first_mode(out, i, measured_f1_hz[i]) if i in measured_f1_hz else out

            plaus = _loss_plausible(" of the zone", 0.9, "leaves no girder there")

            def desc(p, sp, i=i, s=s, x0=x0, x1=x1):
                m = guideway_modal(sp)
                f_new = float(m.freq_hz[m.span_index == i].min())
                e_pa = s.props.youngs_modulus_pa * sp.cal_factor("E")
                tied = (f" With the zone in, the line's sound girder has E = {e_pa / 1e9:.1f} GPa (so that the span's "
                        f"first mode rings at the measured {f_new:.2f} Hz)." if i in measured_f1_hz else "")
                return (f"A zone of girder span {s.span_id} from {s.start_m + x0:.1f} to {s.start_m + x1:.1f} m is "
                        f"about {p[0] * 100:.0f} % less stiff in bending (cracking, local prestress loss): the span "
                        f"deflects more there and its bending modes drop each by its curvature in the zone, "
                        f"which changes the ratio of its first two modes.{tied}",
                        {"span": s.span_id, "stiffness_loss": float(p[0]), "zone_m": [s.start_m + x0, s.start_m + x1],
                         "first_mode_hz": f_new, "youngs_modulus_pa": e_pa})
            out.append(Hypothesis("girder_stiffness_loss", f"girder_stiffness_loss@{s.span_id}[{x0:.1f}-{x1:.1f} m]",
                                  ("stiffness_loss",), (-0.3,), (0.9,), (0.5,), apply,
                                  location={"position_m": [s.start_m + x0, s.start_m + x1], "span": s.span_id},
                                  plausible=plaus, describe=desc, form="zone",
                                  band_hz=(0.5 * f1_hz[i], 1.05 * f1_hz[i])))
    return out


def bearing_hypotheses(spec: ModelSpec) -> list[Hypothesis]:
    out = []
    for i, s in enumerate(spec.spans):
        kb = s.props.bearing_stiffness_n_per_m * spec.cal_factor("kb")
        # a degradation is judged against the larger of the calibrated and the design stiffness: the
        # global kb is measured through the instrumented span's own bearings, so a soft one drags it down
        # (at 250 Hz a bearing at 0.2 pulled the calibrated kb to 0.44 of design; fitted 0.63 of that)
        kb_ref = max(kb, s.props.bearing_stiffness_n_per_m)
        for end in (0, 1):
            x = s.start_m if end == 0 else s.end_m

            def apply(sp, p, i=i, end=end):
                return sp.with_(bearing_factor=_bearing(sp, i, end, 10.0 ** float(p[0])))

            def plaus(p, kb=kb, kb_ref=kb_ref):
                f = 10.0 ** p[0]
                if f * kb / kb_ref > 0.6:
                    ref = "" if kb_ref == kb else f" ({f * kb / kb_ref:.2f} of the design stiffness)"
                    return False, f"fitted bearing stiffness factor {f:.2f}{ref} is not a clear degradation (< 0.6)"
                if f < 2e-3:
                    return False, f"fitted bearing stiffness factor {f:.1e} means no support at all"
                return True, ""

            def desc(p, sp, s=s, end=end, kb=kb, kb_ref=kb_ref, x=x):
                f = 10.0 ** p[0]
                side = "start" if end == 0 else "end"
                than = "the calibrated bearings" if kb_ref == kb else "the design (the calibrated bearings are softer)"
                return (f"The bearing at the {side} of span {s.span_id} (x = {x:.1f} m) is about "
                        f"{kb_ref / (kb * f):.0f} times softer than {than} ({kb * f:.2e} N/m instead of "
                        f"{kb_ref:.2e} N/m): a degraded or loose bearing lets that girder end move and lowers the "
                        f"span's modes.",
                        {"span": s.span_id, "end": side, "position_m": x, "stiffness_factor": float(f),
                         "bearing_stiffness_n_per_m": float(kb * f)})
            out.append(Hypothesis("bearing_stiffness", f"bearing_stiffness@{s.span_id}.{'start' if end == 0 else 'end'}",
                                  ("log10_stiffness_factor",), (-3.0,), (0.5,), (-1.0,), apply,
                                  location={"position_m": [x - 0.25 * s.length_m, x + 0.25 * s.length_m],
                                            "span": s.span_id},
                                  plausible=plaus, describe=desc))
    return out


MIN_DELAY_SAMPLES = 1.0   # a fitted delay shorter than one sample period of the vehicle channels is no finding
# ... nor one shorter than a levitation controller's own period: digital levitation control runs at
# 1 kHz or faster, so a slower recording does not make a longer delay the controller's own
CONTROL_PERIOD_S = 1e-3


CONTROL_DELAY_FORMS = ("delay", "lag")   # transport delay of the law, first-order lag of the current


def control_delay_hypothesis(vehicle_channels: list[str], form: str = "delay", sample_rate_hz: float = 1000.0) -> Hypothesis:
    """The levitation current late on the control law: ``form`` "delay" (a transport delay, what a
    digital controller's sampling, filters and bus give) or "lag" (a first-order lag, what a coil's
    L/R gives). Both are fitted: they differ where w tau ~ 1, and which one the data follow is evidence.
    ``sample_rate_hz``: of the vehicle channels (the shortest delay that counts is one sample, or
    one control period when the recording is slower than the controller)."""
    sample_s = MIN_DELAY_SAMPLES / float(sample_rate_hz)
    min_delay_s = min(sample_s, CONTROL_PERIOD_S)
    if form not in CONTROL_DELAY_FORMS:
        raise ValueError(f"control_delay form: expected one of {CONTROL_DELAY_FORMS}, got {form!r}")

    def apply(sp, p):
        v = max(float(p[0]), 0.0)
        return sp.with_(control_delay_s=v) if form == "delay" else sp.with_(control_lag_s=v)

    def plaus(p):
        if p[0] < min_delay_s:
            # a lag shorter than one sample of the recording (or one control period) is what a digital
            # controller's own sample-and-hold gives: the calibrated gains absorb it
            what = ("one sample period of the vehicle channels" if sample_s <= CONTROL_PERIOD_S
                    else "one period of a levitation controller")
            return False, (f"fitted delay {p[0] * 1e3:.2f} ms is below {what} "
                           f"({min_delay_s * 1e3:.2f} ms: within the controller's own lag)")
        if p[0] > 0.025:
            return False, f"fitted delay {p[0] * 1e3:.0f} ms is longer than any levitation controller allows"
        return True, ""

    def desc(p, sp):
        how = ("acts on measurements about {:.1f} ms old (sensor filtering, sampling, bus latency)" if form == "delay"
               else "current lags the control law with a time constant of about {:.1f} ms (coil, chopper)")
        return (f"The levitation control {how.format(p[0] * 1e3)}: the magnets follow the rail less tightly, "
                f"so gap and magnet acceleration differ from the twin all along the line.",
                {"delay_s": float(p[0]), "form": "transport delay" if form == "delay" else "first-order lag"})
    label = "control_delay" if form == "delay" else "control_delay.lag"
    return Hypothesis("control_delay", label, ("delay_s",), (2.5e-4,), (0.03,), (0.006,), apply,
                      location={"position_m": None, "span": None, "channels": vehicle_channels},
                      plausible=plaus, describe=desc, log_search=True, form=form)


def carbody_hypothesis(vehicle_channels: list[str]) -> Hypothesis:
    def apply(sp, p):
        return sp.with_(carbody_bend_hz=float(p[0]))

    def plaus(p):
        if not 4.0 <= p[0] <= 20.0:
            return False, f"fitted car-body bending frequency {p[0]:.1f} Hz is outside 4-20 Hz"
        return True, ""

    def desc(p, sp):
        return (f"The car body is not rigid: its first vertical bending mode near {p[0]:.1f} Hz shows in the "
                f"magnet accelerations (the twin models the body as rigid).", {"bending_frequency_hz": float(p[0])})
    return Hypothesis("carbody_flexibility", "carbody_flexibility", ("bending_frequency_hz",), (3.0,), (25.0,),
                      (8.0,), apply, location={"position_m": None, "span": None, "channels": vehicle_channels},
                      plausible=plaus, describe=desc, log_search=True)


AMBIENT_MAX_RMS_MPS2 = 2.0     # stronger ambient vibration than this on a guideway is a fault, not a background


def _ambient_plausible(rms_mps2: dict) -> tuple[bool, str]:
    mx = max(rms_mps2.values(), default=0.0)
    if mx > AMBIENT_MAX_RMS_MPS2:
        return False, f"fitted ambient vibration {mx:.2f} m/s^2 RMS is implausibly strong"
    return True, ""


def ambient_hypothesis(guideway_channels: list[str], rms_of: Callable[[float, float], dict]) -> Hypothesis:
    """Parameters: log10 modal-force PSD at 20 Hz [N^2/Hz per unit modal mass] and its slope in f."""
    def apply(sp, p):
        return sp.with_(ambient_log10_psd=float(p[0]), ambient_slope=float(p[1]))

    def plaus(p):
        return _ambient_plausible(rms_of(float(p[0]), float(p[1])))

    def desc(p, sp):
        r = rms_of(float(p[0]), float(p[1]))
        mx = max(r.values()) if r else 0.0
        return (f"The guideway vibrates at its own modes even without our vehicle (about {mx * 1e3:.0f} mm/s^2 "
                f"RMS), before the vehicle enters and after it leaves: vibration from adjacent lines or the "
                f"ground, which the twin does not include.",
                {"log10_modal_force_psd_at_20hz": float(p[0]), "spectral_slope": float(p[1]),
                 "ambient_rms_mps2": {k: float(v) for k, v in r.items()}})
    return Hypothesis("ambient_excitation", "ambient_excitation", ("log10_modal_force_psd", "spectral_slope"),
                      (-9.0, -4.0), (4.0, 4.0), (-2.0, 0.0), apply, needs_sim=False,
                      location={"position_m": None, "span": None, "channels": guideway_channels},
                      plausible=plaus, describe=desc)


def ambient_background_hypothesis(guideway_channels: list[str], background: dict, source: str,
                                  accel_channels: frozenset = frozenset()) -> Hypothesis:
    """The ambient vibration as measured on the quiet stretches of a pass (``background``: channel -> band
    powers above the noise floor on the pass it is fitted on, :attr:`..evaluate.RecData.background`;
    every other pass with quiet stretches of its own brings its own, :func:`..evaluate.ambient_powers`),
    times one level factor (parameter: its log10): a foreign line's ambient need not follow the twin's
    modes and a power law in frequency. The RMS it reports is of ``accel_channels``."""
    bg = tuple((n, tuple(float(x) for x in v)) for n, v in sorted(background.items()))
    rms1 = {n: math.sqrt(sum(v)) for n, v in bg if n in accel_channels}

    def apply(sp, p):
        return sp.with_(ambient_log10_psd=float(p[0]), ambient_slope=0.0, ambient_background=bg)

    def rms_of(p):
        return {n: r * math.sqrt(10.0 ** float(p[0])) for n, r in rms1.items()}

    def plaus(p):
        return _ambient_plausible(rms_of(p))

    def desc(p, sp):
        r = rms_of(p)
        mx = max(r.values(), default=0.0)
        return (f"The guideway vibrates even without our vehicle (about {mx * 1e3:.0f} mm/s^2 RMS above the "
                f"sensors' noise, as measured before the vehicle enters and after it leaves {source}): vibration "
                f"from adjacent lines or the ground, which the twin does not include.",
                {"level_factor": 10.0 ** float(p[0]), "measured_on": source,
                 "ambient_rms_mps2": {k: float(v) for k, v in r.items()}})
    return Hypothesis("ambient_excitation", "ambient_excitation.measured", ("log10_level",), (-2.0,), (2.0,),
                      (0.0,), apply, needs_sim=False,
                      location={"position_m": None, "span": None, "channels": guideway_channels},
                      plausible=plaus, describe=desc)


def sensor_hypothesis(channel: str, unit: str, noise_std: float, t_span_s: float,
                      rezeroed: bool = False) -> Hypothesis:
    """Scale, offset and drift of one channel (parameters: ln scale, offset, drift per second).
    ``rezeroed``: the offset and drift are the instrument's bias of each recording, re-estimated on
    every pass (an accelerometer's); the parameters then hold those of the pass it was fitted on."""
    def apply(sp, p):
        return sp.with_(sensor_error=((channel, math.exp(float(p[0])), float(p[1]), float(p[2])),),
                        sensor_rezeroed=(channel,) if rezeroed else ())

    def plaus(p):
        s, o, d = math.exp(p[0]), p[1], p[2]
        if abs(p[0]) < 0.05 and abs(o) < 3 * noise_std and abs(d) * t_span_s < 3 * noise_std:
            return False, "fitted scale/offset/drift are within 5 % / the noise"
        if not 0.2 < s < 5.0:
            return False, f"fitted scale {s:.2f} is not a plausible calibration error"
        return True, ""

    def desc(p, sp):
        s, o, d = math.exp(p[0]), p[1], p[2]
        parts = []
        if abs(p[0]) >= 0.05:
            parts.append(f"reads {s:.2f} times the true value")
        if abs(o) >= 3 * noise_std:
            parts.append(f"has an offset of {o:.3g} {unit}")
        if abs(d) * t_span_s >= 3 * noise_std:
            parts.append(f"drifts by {d:.3g} {unit}/s")
        what = ", ".join(parts) or "is slightly off"
        if rezeroed and (abs(o) >= 3 * noise_std or abs(d) * t_span_s >= 3 * noise_std):
            what += " on the pass it was fitted on (its bias is re-estimated on each recording)"
        return (f"Sensor {channel} {what}; the other sensors agree with the twin, so this is the instrument, "
                f"not the structure (recalibrate or replace it).",
                {"channel": channel, "scale": s, "offset": o, "drift_per_s": d, "bias_per_recording": rezeroed})
    return Hypothesis("sensor_error", f"sensor_error@{channel}", ("ln_scale", "offset", "drift_per_s"),
                      (-2.0, -np.inf, -np.inf), (2.0, np.inf, np.inf), (0.0, 0.0, 0.0), apply, needs_sim=False,
                      location={"position_m": None, "span": None, "channels": [channel]},
                      plausible=plaus, describe=desc)


MAGNET_NONLINEARITY_FORMS = ("both", "upper")   # current limited on both sides of I0, or above it only


def magnet_nonlinearity_hypothesis(vehicle_channels: list[str], demand_a: float, static_current_a: float,
                                   form: str = "both") -> Hypothesis:
    """Magnet current saturation (chopper/core): the force sees I0 + L tanh((I - I0) / L).

    Parameter: p = L / demand_a, the saturation current headroom L relative to the calibrated
    twin's largest current excursion ``demand_a`` on the training pass where it is compared (so one
    bound fits every line and speed); above ~4 saturation is invisible. Below 1 the twin's peaks are
    compressed, not lost: that demand carries the reconstructed rail's errors (1.25 x the true peak
    demand on one simulated case), so a true headroom of 1.1-1.2 sits near 0.9 of it; a twin that loses
    levitation fails its simulation and is no fit.
    A smooth limit keeps the linearised magnet (slope 1 at the static current), so it is not a
    change of the calibrated gains in disguise: it only compresses large current demands.
    ``form``: "both" limits the current on both sides of I0; "upper" only above it (a supply's maximum
    current: the static current is far from zero, so nothing limits it below), with ``demand_a`` the
    largest excursion above I0. The upper form skews the magnets' accelerations (a recording with
    such a limit: skewness -0.8 to -1.6 against +0.2 to +0.5 on clean ones), the two-sided one cannot."""
    if form not in MAGNET_NONLINEARITY_FORMS:
        raise ValueError(f"magnet_nonlinearity form: expected one of {MAGNET_NONLINEARITY_FORMS}, got {form!r}")
    demand = max(float(demand_a), 1e-6)

    def apply(sp, p):
        return sp.with_(current_limit_a=float(p[0]) * demand, current_limit_sides=form)

    # a limit on both sides takes away force authority both ways: below ~half the peak demand the twin
    # could not have followed the rail; above I0 only, the magnet keeps all of it below I0 (it can always
    # pull less), so a far smaller headroom still levitates and the simulation itself is the check
    lowest = 0.55 if form == "both" else 0.2

    def plaus(p):
        if p[0] > 3.0:
            return False, (f"fitted current headroom {p[0]:.1f} times the largest demand means the current "
                           f"never saturates")
        if p[0] < lowest:
            return False, (f"fitted current headroom {p[0]:.2f} times the largest demand: the magnets could not "
                           f"have followed this rail")
        return True, ""

    def desc(p, sp):
        L = float(p[0]) * demand
        where = (f"saturates about {L:.2f} A from its static {static_current_a:.1f} A" if form == "both" else
                 f"cannot rise more than about {L:.2f} A above its static {static_current_a:.1f} A")
        return (f"The levitation magnets cannot deliver the current the control asks for at high demand: the "
                f"current {where} (supply voltage or current limit, or iron saturation), so the force lags the "
                f"demand where the rail is roughest and the gaps vary more than the twin predicts.",
                {"current_headroom_a": L, "static_current_a": float(static_current_a),
                 "headroom_over_peak_demand": float(p[0]), "limited_sides": form})
    label = "magnet_nonlinearity" if form == "both" else "magnet_nonlinearity.upper"
    return Hypothesis("magnet_nonlinearity", label, ("headroom_over_peak_demand",), (0.5 if form == "both" else 0.15,),
                      (4.0,), (1.5,), apply,
                      location={"position_m": None, "span": None, "channels": vehicle_channels},
                      plausible=plaus, describe=desc, log_search=True)
