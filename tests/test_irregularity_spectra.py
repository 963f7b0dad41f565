"""Profile spectra: Welch PSD + chi-square band vs known spectra, EN 13848 band RMS vs analytic.

References: white noise has the flat one-sided PSD 2 sigma^2 dx (Monte Carlo coverage of the
stated confidence); a Gaussian profile drawn from the German low-disturbance PSD (typed in
tests/irregularity_data.py) must give back that PSD and its band RMS = sqrt(integral of S over
the band), integrated here with scipy.integrate.quad.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from irregularity_data import german_low_psd_rad, random_profile
from maglev_ros.irregularity.spectra import band_rms, compare_reference, profile_psd


def test_confidence_band_coverage_white_noise():
    rng = np.random.default_rng(0)
    dx, sigma = 0.25, 1e-3
    hits, total = 0, 0
    for _ in range(40):
        x = np.arange(4000) * dx
        y = sigma * rng.standard_normal(x.size)
        y[1500:1520] = np.nan                           # two stretches, combined
        sp = profile_psd(x, y, segment_length_m=64.0, confidence=0.9)
        m = sp.freq_cycles_per_m > 0.05
        m &= sp.freq_cycles_per_m < 1.9
        true = 2 * sigma ** 2 * dx
        inside = (sp.lower_m2_per_cycle_per_m[m] <= true) & (true <= sp.upper_m2_per_cycle_per_m[m])
        hits += inside.sum()
        total += m.sum()
    cov = hits / total
    assert 0.85 <= cov <= 0.95, cov


@pytest.mark.parametrize("seed", [1, 2])
def test_german_low_profile_psd_and_reference_ranking(seed):
    rng = np.random.default_rng(seed)
    x, r = random_profile(20000.0, 0.02, rng)
    x, r = x[::12], r[::12]
    sp = profile_psd(x, r, min_wavelength_m=1.0, max_wavelength_m=100.0)
    f = sp.freq_cycles_per_m[sp.in_band]
    s_true = 2 * np.pi * german_low_psd_rad(2 * np.pi * f)
    lr = np.log10(sp.psd_m2_per_cycle_per_m[sp.in_band] / s_true)
    assert abs(np.mean(lr)) < 0.03
    inside = ((sp.lower_m2_per_cycle_per_m[sp.in_band] <= s_true)
              & (s_true <= sp.upper_m2_per_cycle_per_m[sp.in_band]))
    assert inside.mean() > 0.8
    comp = compare_reference(sp)
    assert comp[0]["name"] == "german_low"


@pytest.mark.parametrize("seed", [3, 4])
def test_en13848_band_rms_vs_analytic(seed):
    rng = np.random.default_rng(seed)
    x, r = random_profile(20000.0, 0.02, rng)
    x, r = x[::12], r[::12]
    sp = profile_psd(x, r, min_wavelength_m=1.0, max_wavelength_m=100.0)
    out = {d["band"]: d for d in band_rms(x, r, 1.0, 100.0, spectrum=sp)}
    for name, (lo, hi) in (("D1", (3.0, 25.0)), ("D2", (25.0, 70.0))):
        ref = np.sqrt(integrate.quad(german_low_psd_rad, 2 * np.pi / hi, 2 * np.pi / lo)[0])
        assert out[name]["available"]
        assert out[name]["rms_m"] == pytest.approx(ref, rel=0.08)
        assert out[name]["rms_from_psd_m"] == pytest.approx(ref, rel=0.12)


def test_bands_outside_valid_band_flagged_unavailable():
    rng = np.random.default_rng(5)
    x = np.arange(4000) * 0.25
    y = 1e-3 * rng.standard_normal(x.size)
    out = {d["band"]: d for d in band_rms(x, y, 3.0, 20.0)}
    assert out["D1"]["available"] is False and out["D1"]["rms_m"] is None
    assert "does not cover" in out["D1"]["reason"]
    assert out["D2"]["available"] is False
    out = {d["band"]: d for d in band_rms(x, y, 3.0, 30.0)}
    assert out["D1"]["available"] is True and out["D2"]["available"] is False
