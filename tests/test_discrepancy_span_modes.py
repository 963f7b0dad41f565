"""Per-span first mode from the free decay after a pass (discrepancy.span_modes), on recordings whose
ring-down frequencies are known by construction (damped sinusoids after the vehicle leaves each span),
and the wide-band report of an added mass (resonator.supported_band)."""
import math
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import L_SPAN, metadata  # noqa: E402

from maglev_ros.discrepancy.model import base_spec, guideway_modal  # noqa: E402
from maglev_ros.discrepancy.recording import recording_from_arrays  # noqa: E402
from maglev_ros.discrepancy.resonator import supported_band  # noqa: E402
from maglev_ros.discrepancy.span_modes import SPAN_MODE_MIN_REL, detuned_spans, span_mode_shifts  # noqa: E402

FS = 500.0


def _pass(factors, n_spans=3, speed=25.0, seed=0, zeta=0.02, tail_s=3.0, noise=0.004):
    """A pass whose guideway accelerometers ring at factor x the twin's first mode of their span from
    the moment the rearmost magnet leaves it (forced part: broadband noise while on the span)."""
    md = metadata({}, "pass", speed, n_spans, body_sensors=False)
    spec = base_spec(md)
    modal = guideway_modal(spec)
    offs = np.array(md["vehicle"]["magnet_offsets_m"])
    rng = np.random.default_rng(seed)
    x0 = -offs.max() - 10.0
    x1 = n_spans * L_SPAN - offs.min()
    t = np.arange(0.0, (x1 - x0) / speed + tail_s, 1 / FS)
    pos = x0 + speed * t
    sig = {}
    for name, s in md["sensors"].items():
        if not s["topic"].startswith("/testline/guideway"):
            continue
        i = int(s["span"][1:]) - 1
        f = factors[i] * float(np.min(modal.freq_hz[modal.span_index == i]))
        t_exit = ((i + 1) * L_SPAN - x0 - offs.min()) / speed
        on = (pos + offs.max() >= i * L_SPAN) & (t < t_exit)
        tau = np.clip(t - t_exit, 0, None)
        wd = 2 * math.pi * f * math.sqrt(1 - zeta ** 2)
        y = np.where(t >= t_exit, np.exp(-zeta * 2 * math.pi * f * tau) * np.sin(wd * tau + 0.3), 0.0)
        y = y + np.where(on, rng.standard_normal(t.size) * 0.5, 0.0) + noise * rng.standard_normal(t.size)
        sig[name] = (t, y if s["quantity"] == "acceleration" else 1e-4 * y)
    for name, s in md["sensors"].items():
        if s["topic"].startswith("/testline/vehicle"):
            sig[name] = (t, (0.010 if name.endswith("G") else 0.0) + 1e-5 * rng.standard_normal(t.size))
    pt = t[::5]
    rec = recording_from_arrays(md, sig, (pt, x0 + speed * pt, np.full(pt.size, speed)), source=f"synthetic/{seed}")
    return rec, spec


def test_a_detuned_span_is_found_with_its_shift_and_the_others_are_not():
    recs = [_pass((0.97, 1.0, 1.0), seed=s, speed=v) for s, v in ((1, 25.0), (2, 31.0))]
    spec = recs[0][1]
    shifts = {s.span_id: s for s in span_mode_shifts([r for r, _ in recs], spec)}
    assert set(shifts) == {"S1", "S2", "S3"}
    # the constructed ring-down frequencies: S1 3 % low, the others at the twin's
    assert shifts["S1"].shift == pytest.approx(math.log(0.97), abs=0.002)
    assert abs(shifts["S2"].shift) < 0.002 and abs(shifts["S3"].shift) < 0.002
    assert [s.span_id for s in detuned_spans(list(shifts.values()))] == ["S1"]
    m = shifts["S1"].to_mismatch()
    assert m.position_m == (0.0, L_SPAN)
    f_twin = shifts["S1"].twin_hz
    assert m.frequency_hz[0] == pytest.approx(0.97 * f_twin, rel=0.003) and m.frequency_hz[1] == pytest.approx(f_twin)
    assert set(m.channels) == {"G1A", "G1Q"}


def test_a_shift_all_spans_share_is_the_calibration_not_a_span():
    recs = [_pass((0.98, 0.98, 0.98), seed=s) for s in (3, 4)]
    shifts = span_mode_shifts([r for r, _ in recs], recs[0][1])
    assert all(abs(s.shift) < 0.002 for s in shifts)
    assert detuned_spans(shifts) == []


def test_a_shift_below_the_bar_or_in_one_pass_only_is_not_reported():
    small = [_pass((1 - 0.5 * SPAN_MODE_MIN_REL, 1.0, 1.0), seed=s) for s in (5, 6)]
    assert detuned_spans(span_mode_shifts([r for r, _ in small], small[0][1])) == []
    once = [_pass((0.96, 1.0, 1.0), seed=7)[0], _pass((1.0, 1.0, 1.0), seed=8)[0]]
    assert detuned_spans(span_mode_shifts(once, small[0][1])) == []


def test_a_span_the_recording_ends_on_has_no_free_decay_and_is_not_judged():
    rec, spec = _pass((1.0, 1.0, 0.95), seed=9, tail_s=0.3)
    s3 = next(s for s in span_mode_shifts([rec], spec) if s.span_id == "S3")
    assert np.isnan(s3.measured_hz[0]) and not s3.consistent()


def test_two_spans_are_judged_against_each_other():
    recs = [_pass((1.0, 0.97), n_spans=2, seed=s) for s in (10, 11)]
    shifts = {s.span_id: s for s in span_mode_shifts([r for r, _ in recs], recs[0][1])}
    assert shifts["S2"].shift == pytest.approx(math.log(0.97), abs=0.002)
    assert shifts["S1"].shift == pytest.approx(-math.log(0.97), abs=0.002)


def test_supported_band_is_where_the_fit_is_nearly_as_good():
    prof = [(30.0, 0.40), (40.0, 0.55), (60.0, 0.58), (90.0, 0.57), (150.0, 0.56)]
    assert supported_band(prof, 0.58) == (40.0, 150.0)
    # a sharp optimum: only its neighbourhood
    assert supported_band([(30.0, 0.1), (40.0, 0.5), (60.0, 0.2)], 0.5) == (40.0, 40.0)
    lo, hi = supported_band([], 0.3)
    assert math.isnan(lo) and math.isnan(hi)


def test_a_rigid_point_mass_lowers_the_first_mode_as_rayleigh_says():
    """Rigid added mass (Resonator with infinite frequency) against the first-order (Rayleigh) estimate
    w^2 = w0^2 / (1 + m phi(x)^2) from the unloaded span's mass-normalised mode, and against a stiff
    spring-mass (1 kHz) through the augmented eigenproblem."""
    from maglev_ros.discrepancy.resonator import Resonator, resonator_modal
    md = metadata({}, "pass", 25.0, 3, body_sensors=False)
    spec = base_spec(md)
    base = guideway_modal(spec)
    fe = base.spans_fe[0]
    m_span = fe.span.props.mass_per_length_kg_m * fe.span.length_m
    x = 0.4 * L_SPAN
    sel = base.span_index == 0
    k1 = int(np.argmin(np.where(sel, base.freq_hz, np.inf)))
    phi_x = float(base.shapes_at(np.array([x]))[0, k1])
    f0 = float(base.freq_hz[k1])
    mu = 0.03
    rigid = resonator_modal(spec, Resonator(0, x, math.inf, mu))
    f_rigid = float(np.min(rigid.freq_hz[rigid.span_index == 0]))
    f_ray = f0 / math.sqrt(1 + mu * m_span * phi_x ** 2)
    assert f_rigid < f0
    assert f_rigid == pytest.approx(f_ray, rel=2e-3)
    stiff = resonator_modal(spec, Resonator(0, x, 1000.0, mu, 0.02))
    assert f_rigid == pytest.approx(float(np.min(stiff.freq_hz[stiff.span_index == 0])), rel=1e-3)
    # the other spans are untouched
    assert np.allclose(rigid.freq_hz[rigid.span_index == 1], base.freq_hz[base.span_index == 1])


def test_a_detuned_span_is_the_first_finding_and_is_modelled_as_an_added_mass():
    """mode_shift findings come before band findings; a lowered mode is fitted as a rigid mass sized
    by the measured mode (twin mode x exp(shift)), a raised one as a resonator searched below it."""
    from types import SimpleNamespace
    from maglev_ros.discrepancy.discovery import mode_shift_findings, model_discoveries
    from maglev_ros.discrepancy.span_modes import SpanModeShift
    spans = [SimpleNamespace(span_id=f"S{i + 1}", start_m=i * L_SPAN, end_m=(i + 1) * L_SPAN) for i in range(3)]
    low = SpanModeShift("S1", 0, 0.0, L_SPAN, ("G1A", "G1Q"), 23.5, (22.75, 22.78), (-0.032, -0.031),
                        ((4.5, 8.5), (5.0, 9.0)))
    high = SpanModeShift("S3", 2, 2 * L_SPAN, 3 * L_SPAN, ("G3A",), 23.5, (24.3, 24.4), (0.035, 0.036),
                         ((6.0, 8.5), (6.5, 9.0)))
    found = mode_shift_findings([low, high], spans)
    assert [d["location"]["span"] for d in found] == ["S1", "S3"]
    assert found[0]["target_hz"] == pytest.approx(23.5 * math.exp(-0.0315))
    assert found[0]["location"]["position_m"] == [0.0, L_SPAN]
    band = {"kind": "resonance", "frequency_hz": [37.0, 44.0], "sensed_on": "guideway", "score": 1e4,
            "location": {"span": "S2", "position_m": [L_SPAN, 2 * L_SPAN]}, "explanation": "x."}
    calls = []

    class Finder:
        def fit(self, base, tr, te, band_hz, span_index, search, zeta_max=None, rigid=False, target_hz=None, **kw):
            calls.append(dict(band=tuple(band_hz), span=span_index, search=search, rigid=rigid, target=target_hz,
                              zeta_max=zeta_max))
            return SimpleNamespace(accepted=False, verdict=None, to_dict=lambda: {"accepted": False},
                                   explanation=lambda b, what=None: f"not supported ({what}).")
    base = SimpleNamespace(spec=SimpleNamespace(spans=tuple(spans)))
    model_discoveries([band] + found, base, [], [], None, max_resonators=3, finder=Finder(), worst_span_fallback=False)
    # the detuned spans first (the stronger shift first), then the band finding despite its score
    assert [c["span"] for c in calls] == [2, 0, 1]
    c_low, c_high = calls[1], calls[0]
    assert c_low["rigid"] and c_low["target"] == pytest.approx(found[0]["target_hz"])
    assert c_low["band"][0] == pytest.approx(0.85 * 22.75, rel=1e-3) and c_low["band"][1] == pytest.approx(1.15 * 23.5)
    assert not c_high["rigid"] and c_high["target"] is None and c_high["search"][1] == pytest.approx(0.85 * 23.5)
    assert "-3.1 % relative to the other spans" in found[0]["explanation"]
