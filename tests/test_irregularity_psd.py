"""Reference irregularity PSDs and random profile sampling.

References are independent of the module: published class constants typed here from the
literature tables, scipy quadrature of the PSD formulas, Welch estimates of sampled profiles.
"""

import numpy as np
import pytest
from scipy import integrate, signal, stats

from maglev_ros.errors import UserError
from maglev_ros.twin import irregularity_psd as ip

BAND_001 = (0.314, 6.28)


def _fra_cm2(omega, a_cm2, k=0.25, wc=0.8245):
    """Zhai (2020) metric FRA vertical form, S in cm^2/(rad/m)."""
    return k * a_cm2 * wc**2 / (omega**2 * (omega**2 + wc**2))


@pytest.mark.parametrize("cls,a_cm2", [(1, 1.2107), (2, 1.0181), (3, 0.6816), (4, 0.5376), (5, 0.2095), (6, 0.0339)])
def test_fra_classes_match_published_table(cls, a_cm2):
    psd = ip.fra_class(cls)
    om = np.geomspace(0.05, 10.0, 17)
    np.testing.assert_allclose(psd(om), _fra_cm2(om, a_cm2) * 1e-4, rtol=1e-12)
    assert psd.to_dict()["units"].startswith("one-sided m^2/(rad/m)")


def test_fra_classes_ordered_and_german_forms():
    om = 1.3
    vals = [float(ip.fra_class(c)(om)) for c in range(1, 7)]
    assert all(a > b for a, b in zip(vals, vals[1:]))  # class 6 is the best track
    lo, hi = ip.german_high_speed("low"), ip.german_high_speed("high")
    for p, a in ((lo, 4.032e-7), (hi, 1.08e-6)):
        expect = a * 0.8246**2 / ((om**2 + 0.0206**2) * (om**2 + 0.8246**2))
        assert float(p(om)) == pytest.approx(expect, rel=1e-12)
    # German form is finite at Omega -> 0 (low cutoff Omega_r), FRA diverges like 1/Omega^2
    assert np.isfinite(lo(0.0)) and float(lo(0.0)) == pytest.approx(4.032e-7 / 0.0206**2, rel=1e-12)
    assert ip.psd_by_name("maglev_001").roughness_m2_rad_per_m == 1.5e-7
    with pytest.raises(UserError):
        ip.psd_by_name("fra9")
    with pytest.raises(UserError):
        ip.german_high_speed("medium")


@pytest.mark.parametrize("name", ["fra1", "fra6", "german_low", "german_high", "maglev_001"])
@pytest.mark.parametrize("band", [BAND_001, (0.05, 0.4), (2.0, 30.0)])
def test_band_variance_against_quadrature(name, band):
    psd = ip.psd_by_name(name)
    ref, _ = integrate.quad(lambda w: float(psd(w)), *band, limit=200, epsabs=0, epsrel=1e-11)
    assert float(psd.band_variance(*band)) == pytest.approx(ref, rel=1e-8)
    assert psd.rms_m(band) == pytest.approx(np.sqrt(ref), rel=1e-8)


def test_unit_conversions_preserve_variance():
    psd = ip.german_high_speed("high")
    lo, hi = BAND_001
    var = float(psd.band_variance(lo, hi))
    # per cycle/m
    v_cyc, _ = integrate.quad(lambda f: float(psd.per_cycle(f)), lo / (2 * np.pi), hi / (2 * np.pi), epsrel=1e-11)
    assert v_cyc == pytest.approx(var, rel=1e-8)
    # time domain at 100 km/h, per rad/s and per Hz
    v = 27.78
    v_t, _ = integrate.quad(lambda w: float(psd.temporal(w, v)), v * lo, v * hi, epsrel=1e-11)
    v_hz, _ = integrate.quad(lambda f: float(psd.temporal_hz(f, v)), v * lo / (2 * np.pi), v * hi / (2 * np.pi),
                             epsrel=1e-11)
    assert v_t == pytest.approx(var, rel=1e-8) and v_hz == pytest.approx(var, rel=1e-8)
    f, s_f = ip.per_rad_to_per_cycle(2.0, psd(2.0))
    om, s_back = ip.per_cycle_to_per_rad(f, s_f)
    assert om == pytest.approx(2.0) and s_back == pytest.approx(float(psd(2.0)))
    assert float(s_f) == pytest.approx(float(psd.per_cycle(2.0 / (2 * np.pi))))
    assert ip.band_from_wavelengths(1.0, 20.0) == pytest.approx((2 * np.pi / 20.0, 2 * np.pi))
    with pytest.raises(UserError):
        psd.temporal(1.0, 0.0)
    with pytest.raises(UserError):
        ip.band_from_wavelengths(5.0, 1.0)


@pytest.mark.parametrize("name,seed", [("maglev_001", 1), ("fra6", 2), ("german_low", 3)])
def test_random_profile_rms_and_gaussianity(name, seed):
    psd = ip.psd_by_name(name)
    band_m = (1.0, 20.0)
    var = float(psd.band_variance(*ip.band_from_wavelengths(*band_m)))
    x, r = ip.random_profile(psd, 400.0, 0.05, band_m, np.random.default_rng(seed), n_samples=300, start_m=-10.0)
    assert x[0] == -10.0 and x[-1] == pytest.approx(390.0) and r.shape == (300, x.size)
    # ensemble variance at fixed x (sampling error ~ sqrt(2/300) ~ 8% on one point: average over x)
    pooled = np.mean(r**2)
    assert pooled == pytest.approx(var, rel=0.05)
    # per-sample spatial variance around the band integral
    assert np.median(np.mean(r**2, axis=1)) == pytest.approx(var, rel=0.15)
    # sum of many random-phase cosines: close to Gaussian
    z = r[:, ::40].ravel() / np.sqrt(var)
    assert abs(stats.kurtosis(z, fisher=False) - 3.0) < 0.15
    assert abs(np.mean(z)) < 0.05
    one_x, one_r = ip.random_profile(psd, 50.0, 0.05, band_m, seed)
    assert one_r.shape == one_x.shape


@pytest.mark.parametrize("name,seed", [("maglev_001", 11), ("german_high", 12)])
def test_random_profile_welch_matches_target(name, seed):
    psd = ip.psd_by_name(name)
    band_m = (2.0, 50.0)
    dx = 0.1
    x, r = ip.random_profile(psd, 8192 * dx, dx, band_m, np.random.default_rng(seed), n_samples=120)
    nper = 4096
    f, p = signal.welch(r, fs=1.0 / dx, nperseg=nper, axis=-1)  # one-sided m^2/(cycle/m)
    p = p.mean(axis=0)
    om, s_est = ip.per_cycle_to_per_rad(f, p)
    lo, hi = ip.band_from_wavelengths(*band_m)
    inside = (om > 1.5 * lo) & (om < 0.8 * hi)
    groups = np.array_split(np.flatnonzero(inside), 12)
    for g in groups:
        est = s_est[g].mean()
        tgt = float(np.mean(psd(om[g])))
        # 120 samples x 3 segments per bin, group of bins: ~2 % (1 sigma) error
        assert est == pytest.approx(tgt, rel=0.08), (om[g][0], est / tgt)
    # outside the band: nothing beyond window leakage
    far = (om > 1.3 * hi) & (om < 0.9 * np.pi / dx)
    assert s_est[far].max() < 1e-3 * float(psd(hi))


def test_random_profile_bad_input():
    psd = ip.maglev_guideway_001()
    with pytest.raises(UserError, match="spacing_m"):
        ip.random_profile(psd, 100.0, 0.6, (1.0, 20.0), 0)
    with pytest.raises(UserError, match="wavelength_band_m"):
        ip.random_profile(psd, 100.0, 0.05, (20.0, 1.0), 0)
    with pytest.raises(UserError):
        ip.random_profile(psd, -1.0, 0.05, (1.0, 20.0), 0)
    with pytest.raises(UserError):
        psd.band_variance(0.0, 1.0)
