"""system3d irregularity: rational spectra (variance vs numerical quadrature, forms vs the
twin's reference PSDs), samplers (Welch PSD vs target, variance vs the PSD integral), and the
four-process <-> left/right rail mapping."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.signal import csd, welch

from maglev_ros.errors import UserError
from maglev_ros.system3d.irregularity import PROCESSES, RAILS, TrackIrregularity, load_irregularity
from maglev_ros.system3d.irregularity_spectra import rational_psd
from maglev_ros.system3d.scenario_values import load_yaml, plain
from maglev_ros.twin.irregularity_psd import fra_class, german_high_speed, maglev_guideway_001

CONFIG = Path(__file__).resolve().parents[1] / "maglev_ros" / "config" / "system3d"
CUT = {"omega_c": 0.8246, "omega_r": 0.0206, "omega_s": 0.438}
SPACING_M = 0.25
N_X = 1024                    # one full period of the sampler's FFT grid (256 m)
N_SAMPLES = 48


@pytest.fixture(scope="module")
def track():
    return load_irregularity(CONFIG / "paper001_irregularity.yaml")


@pytest.fixture(scope="module")
def samples(track):
    return track.sample((N_X - 1) * SPACING_M, SPACING_M, rng=20260, n_samples=N_SAMPLES)


@pytest.mark.parametrize("form, b", [("fra_profile", None), ("fra_crosslevel", None), ("german_profile", None),
                                     ("german_crosslevel", None), ("german_crosslevel", 0.75)])
def test_band_variance_equals_quadrature(form, b):
    psd = rational_psd("p", form, 2.5e-7, CUT, k=0.25, half_gauge_m=b)
    for lo, hi in ((0.314, 6.28), (0.05, 0.9), (1.0, 30.0)):
        ref, _ = quad(psd, lo, hi, limit=200, epsabs=0, epsrel=1e-11)
        assert float(psd.band_variance(lo, hi)) == pytest.approx(ref, rel=1e-8)


def test_forms_match_the_twin_reference_spectra():
    om = np.geomspace(0.05, 20.0, 50)
    g = german_high_speed("low")
    ours = rational_psd("e", "german_profile", g.roughness_m2_rad_per_m, CUT)
    np.testing.assert_allclose(ours(om), g(om), rtol=1e-12)
    f5 = fra_class(5)
    ours = rational_psd("e", "fra_profile", f5.roughness_m2_rad_per_m, {"omega_c": f5.cutoff_rad_per_m}, k=f5.k)
    np.testing.assert_allclose(ours(om), f5(om), rtol=1e-12)


def test_paper001_elevation_agrees_with_the_twin_maglev_form_in_band(track):
    """The German form chosen for paper 001 vs the FRA form of twin.maglev_guideway_001 (same
    A1): within 0.5 % over the paper's band 0.314-6.28 rad/m (Omega_r << band)."""
    om = np.linspace(0.314, 6.28, 200)
    np.testing.assert_allclose(track.psds["elevation"](om), maglev_guideway_001()(om), rtol=5e-3)


def test_sample_variance_equals_the_psd_integral(track, samples):
    """Over one period the sampler's variance is the band integral of the PSD (quadrature)."""
    lo, hi = track.band_rad_per_m
    assert samples.x_m.size == N_X
    for k in PROCESSES:
        ref, _ = quad(track.psds[k], lo, hi, limit=200, epsrel=1e-11)
        var = samples.processes[k].var(axis=1)
        np.testing.assert_allclose(var, ref, rtol=1e-6, err_msg=k)


def _welch_per_rad(a, b=None):
    """One-sided (cross-)PSD per rad/m of the rows of a (and b), averaged over rows."""
    fs = 1.0 / SPACING_M
    if b is None:
        f, p = welch(a, fs=fs, nperseg=256, axis=-1)
    else:
        f, p = csd(a, b, fs=fs, nperseg=256, axis=-1)
    return 2 * np.pi * f, p.mean(axis=0) / (2 * np.pi)


def _in_band(om):
    return (om >= 0.8) & (om <= 5.6)     # 2 Welch bins (0.1 rad/m each) inside the 0.314-6.28 band


def test_sampled_process_psds_match_their_targets(track, samples):
    """Welch (64 m Hann segments, 48 samples x 7 segments): every bin in 0.8-5.6 rad/m within
    15 % of the target and the mean ratio within 3 % (statistical spread ~ 1/sqrt(336) = 5 %;
    seeds 1, 2, 3, 99, 20260 gave worst bins 5-8.5 % and mean ratios within 1.6 %)."""
    for k in PROCESSES:
        om, p = _welch_per_rad(samples.processes[k])
        sel = _in_band(om)
        ratio = p[sel] / track.psds[k](om[sel])
        assert np.all(np.abs(ratio - 1) < 0.15), (k, ratio.min(), ratio.max())
        assert abs(ratio.mean() - 1) < 0.03, (k, ratio.mean())


def test_rail_spectra_follow_the_mapping(track, samples):
    """Rails' auto- and cross-spectra from the samples vs T diag(S) T^T: z_L = e + b theta,
    z_R = e - b theta (cross-spectrum S_e - b^2 S_theta), y_L/y_R from alignment and gauge,
    vertical and lateral uncorrelated. Error per bin relative to sqrt(S_aa S_bb): seeds 1, 2, 3,
    99 and 20260 gave a mean 0.038-0.043 (the spread of a cross-spectrum estimate from 336
    segments) and a max 0.11-0.14."""
    om, _ = _welch_per_rad(samples.rails["z_left"])
    sel = _in_band(om)
    ref = track.rail_cross_spectrum(om[sel])
    for i, a in enumerate(RAILS):
        for j, b in enumerate(RAILS[i:], start=i):
            _, p = _welch_per_rad(samples.rails[a], samples.rails[b])
            scale = np.sqrt(ref[:, i, i] * ref[:, j, j])
            err = np.abs(p.real[sel] - ref[:, i, j]) / scale
            assert err.mean() < 0.08 and err.max() < 0.25, (a, b, err.mean(), err.max())


def test_mapping_round_trip_and_unit_processes(track):
    b = track.half_gauge_m
    rng = np.random.default_rng(3)
    procs = {k: rng.normal(size=7) for k in PROCESSES}
    back = track.processes_from_rails(track.rails_from_processes(procs))
    for k in PROCESSES:
        np.testing.assert_allclose(back[k], procs[k], rtol=1e-12)
    unit = {k: np.zeros(1) for k in PROCESSES}
    r = track.rails_from_processes({**unit, "cross_level": np.ones(1)})
    assert (r["z_left"][0], r["z_right"][0], r["y_left"][0]) == (b, -b, 0.0)
    r = track.rails_from_processes({**unit, "gauge": np.ones(1)})
    assert (r["y_left"][0] - r["y_right"][0], r["y_left"][0] + r["y_right"][0], r["z_left"][0]) == (1.0, 0.0, 0.0)
    r = track.rails_from_processes({**unit, "elevation": np.ones(1), "alignment": 2 * np.ones(1)})
    assert [r[k][0] for k in RAILS] == [1.0, 1.0, 2.0, 2.0]
    # a height-difference cross-level (FRA) splits half to each rail
    fra = TrackIrregularity(track.psds, b, track.wavelength_band_m, cross_level_unit="m")
    r = fra.rails_from_processes({**unit, "cross_level": np.ones(1)})
    assert (r["z_left"][0], r["z_right"][0]) == (0.5, -0.5)
    # the four pseudo-excitations add up to the rails' cross-spectral matrix
    om = np.array([0.5, 2.0])
    pe = track.pseudo_excitation(om)
    np.testing.assert_allclose(np.einsum("nki,nkj->nij", pe, pe), track.rail_cross_spectrum(om), rtol=1e-12)


def test_summary_is_json(track):
    d = json.loads(json.dumps(track.to_dict()))
    assert set(d["processes"]) == set(PROCESSES)
    assert d["band_rms"]["elevation"] == pytest.approx(np.sqrt(quad(track.psds["elevation"], *track.band_rad_per_m)[0]))


def test_half_gauge_agrees_between_girder_and_irregularity_scenarios(track):
    rails = plain(load_yaml(CONFIG / "paper001_girder.yaml")["rails"])
    assert rails["half_gauge_m"] == track.half_gauge_m


def test_user_errors_name_the_item(track):
    good = load_yaml(CONFIG / "paper001_irregularity.yaml")["irregularity"]
    bad = {**good, "processes": {k: v for k, v in good["processes"].items() if k != "gauge"}}
    with pytest.raises(UserError, match="processes: missing gauge"):
        TrackIrregularity.from_dict(bad)
    with pytest.raises(UserError, match="form: expected one of"):
        rational_psd("elevation", "iso8608", 1e-7, CUT)
    with pytest.raises(UserError, match="needs cutoffs omega_s"):
        rational_psd("gauge", "german_crosslevel", 1e-7, {"omega_c": 0.8, "omega_r": 0.02})
    with pytest.raises(UserError, match="wavelength band"):
        TrackIrregularity(track.psds, 1.0, (20.0, 1.0))
