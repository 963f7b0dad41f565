"""Band-limited double integration: analytic displacements, bias and dropout handling.

References: for a sum of sinusoids a(t) = -A (2 pi f)^2 sin(...), the displacement is
A sin(...) times the stated high-pass gain (f/fc)^8 / (1 + (f/fc)^8); a constant bias must be
reported with its value and must not appear as a parabola; a dropout must be reported and the
output must be NaN there, never a ramp.
"""
from __future__ import annotations

import numpy as np
import pytest

from maglev_ros.irregularity.integration import double_integrate, detect_dropouts

FS = 500.0


def _signal(seed, T=120.0, freqs=(0.8, 1.7, 3.1, 6.0), noise=0.0):
    rng = np.random.default_rng(seed)
    t = np.arange(int(T * FS)) / FS
    amps = rng.uniform(0.5e-3, 2e-3, len(freqs))
    ph = rng.uniform(0, 2 * np.pi, len(freqs))
    z = sum(A * np.sin(2 * np.pi * f * t + p) for A, f, p in zip(amps, freqs, ph))
    a = sum(-A * (2 * np.pi * f) ** 2 * np.sin(2 * np.pi * f * t + p)
            for A, f, p in zip(amps, freqs, ph))
    return t, a + noise * rng.standard_normal(t.size), z, rng


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sinusoids_recovered_and_corner_stated(seed):
    t, a, z, _ = _signal(seed)
    res = double_integrate(t, a, FS, highpass_hz=0.2)
    assert res.highpass_hz == 0.2 and res.filter_order == 4
    m = res.valid
    assert m.mean() > 0.9          # edges of 1/f_c = 5 s are NaN by design
    err = res.displacement_m[m] - z[m]
    assert np.sqrt(np.mean(err ** 2)) < 0.01 * np.std(z)
    assert not res.warnings


def test_component_below_corner_removed_per_stated_gain():
    t = np.arange(int(200 * FS)) / FS
    f_lo, f_hi, fc = 0.05, 1.0, 0.2
    z_lo = 0.01 * np.sin(2 * np.pi * f_lo * t)
    z_hi = 0.001 * np.sin(2 * np.pi * f_hi * t)
    a = -(2 * np.pi * f_lo) ** 2 * z_lo - (2 * np.pi * f_hi) ** 2 * z_hi
    res = double_integrate(t, a, FS, highpass_hz=fc)
    m = res.valid
    gain_lo = (f_lo / fc) ** 8 / (1 + (f_lo / fc) ** 8)       # analytic, 1.5e-5
    expected = gain_lo * z_lo + z_hi
    assert np.max(np.abs(res.displacement_m[m] - expected[m])) < 2e-5


@pytest.mark.parametrize("seed,bias", [(0, 0.01), (1, 0.03), (2, 0.05), (3, -0.02)])
def test_bias_reported_and_not_integrated_into_parabola(seed, bias):
    t, a, z, rng = _signal(seed, noise=0.01)
    res = double_integrate(t, a + bias, FS, highpass_hz=0.2)
    kinds = [w.kind for w in res.warnings]
    assert kinds.count("accel_bias") == 1
    w = res.warnings[kinds.index("accel_bias")]
    assert w.value == pytest.approx(bias, abs=0.002)
    m = res.valid
    # a parabola would reach 0.5 * bias * T^2 = 72..360 m; the result equals the bias-free one
    ref = double_integrate(t, a, FS, highpass_hz=0.2)
    assert np.array_equal(m, ref.valid)
    assert np.max(np.abs(res.displacement_m[m] - ref.displacement_m[m])) < 1e-9
    err = res.displacement_m[m] - z[m]
    assert np.sqrt(np.mean(err ** 2)) < 0.15 * np.std(z)


@pytest.mark.parametrize("seed", range(5))
def test_no_false_bias_alarm(seed):
    t, a, z, rng = _signal(seed, noise=0.02)
    res = double_integrate(t, a, FS, highpass_hz=0.2)
    assert "accel_bias" not in [w.kind for w in res.warnings]


@pytest.mark.parametrize("fault", ["nan", "stuck", "zeros", "timegap"])
def test_dropout_reported_masked_no_ramp(fault):
    t, a, z, rng = _signal(7, noise=0.01)
    i0, i1 = int(50 * FS), int(51.5 * FS)
    a = a.copy()
    if fault == "nan":
        a[i0:i1] = np.nan
    elif fault == "stuck":
        a[i0:i1] = a[i0]
    elif fault == "zeros":
        a[i0:i1] = 0.0
    else:
        keep = np.ones(t.size, bool)
        keep[i0:i1] = False
        t, a, z = t[keep], a[keep], z[keep]
        i1 = i0
    res = double_integrate(t, a, FS, highpass_hz=0.2)
    kinds = {w.kind for w in res.warnings}
    want = {"nan": "nonfinite", "stuck": "flatline", "zeros": "flatline", "timegap": "time_gap"}
    assert want[fault] in kinds
    bad = [w for w in res.warnings if w.kind == want[fault]][0]
    assert bad.start_s == pytest.approx(50.0, abs=0.05)
    # NaN over the dropout plus the stated edge margin on both sides
    tt = res.time_s
    near = (tt > 50.0 - res.edge_s + 0.01) & (tt < 51.5 + res.edge_s - 0.01)
    if fault == "timegap":
        near = (tt > 50.0 - res.edge_s + 0.01) & (tt < 51.5 + res.edge_s - 0.01)
    assert not res.valid[near].any()
    m = res.valid
    assert m.mean() > 0.75
    err = res.displacement_m[m] - z[m]
    assert np.sqrt(np.mean(err ** 2)) < 0.15 * np.std(z)
    assert np.max(np.abs(err)) < 0.5 * np.max(np.abs(z))     # a ramp would be >> |z|


def test_detect_dropouts_ignores_clean_noise():
    rng = np.random.default_rng(3)
    t = np.arange(20000) / FS
    x = 0.02 * rng.standard_normal(t.size)
    bad, warns = detect_dropouts(t, x, FS, "A")
    assert not bad.any() and not warns
