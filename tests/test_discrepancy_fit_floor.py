"""What limits the calibrated fit: the gap sensors' noise in the rail (maglev_ros.discrepancy.floor).

References: the Wiener estimate's mean-square error (analytic: (1 - G)^2 R + G^2 N/n equals
R (N/n) / (R + N/n)); Welch spectra of the drawn error profiles (scipy); on a generated clean line,
the same recordings simulated without sensor noise (the misfit the noisy rail makes against the
noise-free one is what the floor estimates); and the whole calibrated misfit, which a part of it
cannot exceed (the sample bags, in test_sample_bags).
"""
from __future__ import annotations

import os
import sys
from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from maglev_ros.discrepancy.floor import draw_rail_error, rail_error_psd

sys.path.insert(0, os.path.dirname(__file__))


def _gain(n_magnets=4, segment_m=2.0):
    from maglev_ros.irregularity.denoise import RailGain
    k = np.linspace(0.0, 70.0, 300)
    rail = 1e-10 / (1.0 + (k / 5.0) ** 4)
    noise = np.full(k.size, 4e-13)
    return RailGain(k, rail, noise, n_magnets, 10000, segment_m)


def test_the_error_spectrum_is_the_wiener_estimates_mean_square_error():
    g = _gain()
    k = g.wavenumber_cpm[g.wavenumber_cpm > 1.0]
    G = np.interp(k, g.wavenumber_cpm, g.gain(g.n_magnets))
    R = np.interp(k, g.wavenumber_cpm, g.rail_psd)
    N = np.interp(k, g.wavenumber_cpm, g.noise_psd) / g.n_magnets
    assert np.allclose(rail_error_psd(g, k), (1 - G) ** 2 * R + G ** 2 * N, rtol=1e-9, atol=1e-30)
    # waves longer than half the spectra's segment are not resolved by them: no error drawn there
    assert np.all(rail_error_psd(g, np.array([0.1, 0.5, 0.9])) == 0.0)


def test_the_white_level_is_the_disagreement_where_no_rail_shows():
    """A profile error white at 4e-13 plus a disagreement at the first mode's wavelength (0.3 m) that
    is no sensor noise: the white level is read where the rail is not detected; capped there, the
    error spectrum at 0.3 m follows the white level, not the bump."""
    from maglev_ros.discrepancy.floor import sensor_noise_psd
    from maglev_ros.irregularity.denoise import RailGain
    k = np.linspace(0.0, 70.0, 300)
    rail = np.where(k < 20.0, 1e-9 / (1.0 + (k / 3.0) ** 4), 0.0)
    noise = 4e-13 + 1e-9 * np.exp(-0.5 * ((k - 1 / 0.3) / 0.4) ** 2)
    g = RailGain(k, rail, noise, 4, 10000, 2.0)
    assert sensor_noise_psd(g, 60.0) == pytest.approx(4e-13, rel=1e-6)
    kq = np.array([1 / 0.3])
    R = np.interp(kq, k, rail)
    capped = rail_error_psd(g, kq, noise_psd=4e-13)
    assert capped == pytest.approx(R * 1e-13 / (R + 1e-13), rel=1e-6)
    assert rail_error_psd(g, kq)[0] > 100 * capped[0]


def test_a_drawn_rail_error_has_that_spectrum():
    g = _gain()
    rng = np.random.default_rng(3)
    dx = 0.007
    e = np.concatenate([draw_rail_error(rng, 20000, dx, g) for _ in range(8)])
    k, p = signal.welch(e, 1.0 / dx, nperseg=2048)
    E = rail_error_psd(g, k)
    band = (k > 2.0) & (k < 60.0)
    ratio = p[band] / E[band]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.05)
    assert np.all((ratio > 0.6) & (ratio < 1.6))          # Welch's scatter with ~140 segments
    assert e.var() == pytest.approx(np.trapezoid(E, k), rel=0.05)


@pytest.fixture(scope="module")
def noisy_and_clean():
    """A clean line at 8 and 10 m/s with 5x the generator's sensor noise (a 5 um gap sensor), and the
    same line, vehicle and rail recorded without noise; the twin is the truth (no design error)."""
    from discrepancy_cases import make_case

    from maglev_ros.discrepancy.evaluate import fit_report, prepare
    from maglev_ros.discrepancy.irregularity import with_twin_irregularities
    from maglev_ros.discrepancy.model import base_spec
    kw = dict(seed=5, speeds=(8.0, 10.0), design_error={"E": 0.0, "kb": 0.0, "kp": 0.0})
    noisy = make_case("floor", None, {}, variant={"noise_scale": 5.0}, **kw)
    clean = make_case("floor", None, {}, variant={"noise_scale": 0.0}, **kw)
    spec = base_spec(noisy.passes[0].metadata, 24)
    rds = [prepare(r, spec) for r in with_twin_irregularities(noisy.passes, spec)]
    rails = [r.irregularity for r in with_twin_irregularities(clean.passes, spec)]
    return spec, rds, rails, fit_report(spec, rds)[0]


def test_the_floor_covers_the_misfit_the_gap_noise_makes_without_exaggerating_it(noisy_and_clean):
    from maglev_ros.discrepancy.evaluate import _fit_items
    from maglev_ros.discrepancy.floor import rail_floor
    spec, rds, rails, fit = noisy_and_clean
    floor = rail_floor(spec, rds, fit)
    made = []
    for rd, rail in zip(rds, rails):
        noisy_items = _fit_items(spec, rd)
        clean_items = _fit_items(spec, replace(rd, rec=replace(rd.rec, irregularity=rail)))
        made += [float(np.sqrt(np.sum((a[1] - b[1]) ** 2))) / a[2] for a, b in zip(noisy_items, clean_items)]
    made_nrmse = float(np.sqrt(np.mean(np.square(made))))
    assert made_nrmse > 0.01                      # the noise matters on this line
    assert 0.5 * made_nrmse <= floor.nrmse <= 1.5 * made_nrmse
    assert floor.nrmse <= fit
    assert floor.remainder_nrmse == pytest.approx(np.sqrt(fit ** 2 - floor.nrmse ** 2))
    assert floor.n_draws == 2 and set(floor.per_pass) == {rd.rec.name for rd in rds}


def test_no_floor_without_a_measured_error_spectrum(noisy_and_clean):
    from maglev_ros.discrepancy.floor import rail_floor
    spec, rds, _, fit = noisy_and_clean
    bare = [replace(rd, rec=replace(rd.rec, irregularity_info={})) for rd in rds]
    assert rail_floor(spec, bare, fit) is None
    # a valid stretch off the rail's grid: nothing reconstructed to perturb
    end = max(float(rd.rec.irregularity[0][-1]) for rd in rds)
    off = [replace(rd, rec=replace(rd.rec, irregularity_valid_m=(end + 10.0, end + 20.0))) for rd in rds]
    assert rail_floor(spec, off, fit) is None


def test_the_floors_words_state_its_numbers():
    from maglev_ros.discrepancy.floor import RailFloor
    f = RailFloor(0.035, {"guideway_accel": 0.04}, {"G4RV": 0.045}, {"pass": 0.035}, 0.059, 1.6e-6, 0.064, 2,
                  ["G4RV"])
    d = f.to_dict()
    assert d["rail_uncertainty_nrmse"] == 0.035 and d["remainder_nrmse"] == pytest.approx(0.0475, abs=1e-4)
    text = d["explanation"]
    assert "0.035" in text and "0.059" in text and "35 %" in text and "6 cm" in text and "G4RV" in text
    assert "gap sensors' noise" in text and f"({d['remainder_nrmse']:.3f})" in text
    at = RailFloor(0.063, {}, {}, {}, 0.063, 1.9e-6, 0.073, 2, []).explanation()
    assert "as well as their gap noise allows" in at and "0.063" in at
