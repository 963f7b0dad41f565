"""SSI-cov against the known truth of simulated modal structures (tests/modal_data.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from maglev_ros.errors import UserError
from maglev_ros.modal.ssi_cov import ModalResult, SSICov, output_covariances
from maglev_ros.modal.stabilization import mac, mpc, mpd, real_mode_shape
from modal_data import assert_modes_match, guideway_model, simulate_ambient

FS = 500.0
T = 120.0


def _statistical_tol(model, r, duration_s):
    """Cramer-Rao std of a frequency/damping estimate of a white-noise-driven mode,
    sqrt(zeta / (omega T)) (relative for frequency, absolute for damping; checked against the
    multichannel bound of the exact structure and an oracle estimator in test_modal_accuracy.py)."""
    w = 2 * np.pi * model.frequency_hz[r]
    return np.sqrt(model.damping_ratio[r] / (w * duration_s))


# Error budget in units of that bound (bench/bench_modal_accuracy.py, 80 records of the nominal
# structure, 30 of a randomized one): the default estimator's frequency std is <= 1.4 x the bound
# and its |bias| <= 0.85 x the bound on every mode (damping: std <= 1.6 x, |bias| <= 0.7 x), so
# an error beyond 5.5 x the bound is a >= 3 sigma event (p < 3e-3 per mode): a regression, not
# bad luck. A fixed 0.2 % cannot be asserted for every mode: at 120 s the bound of the
# 23.5 Hz mode is 0.09-0.12 %, so even an efficient estimator misses 0.2 % on 3-9 % of records.
K_BOUND = 5.5


@pytest.mark.parametrize("seed,variant,excitation", [
    (11, None, "white"),        # nominal paper-like modes
    (12, 3, "filtered"),        # randomized structure, coloured ambient load
    (13, 4, "white"),
    (14, 5, "filtered"),
])
def test_ambient_accuracy_against_truth(seed, variant, excitation):
    model = guideway_model(variant)
    y = simulate_ambient(model, FS, T, noise_frac=0.05, excitation=excitation, seed=seed)
    res = SSICov(block_rows=40, orders=range(2, 81, 2)).fit(y, FS, model.channels)
    found = [m for m in res.modes if 5.0 <= m.frequency_hz <= 150.0]
    truth = [r for r in range(model.frequency_hz.size) if 5.0 <= model.frequency_hz[r] <= 150.0]
    assert len(found) == len(truth), ([m.frequency_hz for m in found], model.frequency_hz)
    w = assert_modes_match(res.modes, model, 150.0)
    assert w["missing"] == [] and w["spurious"] == []
    for r in truth:
        m = min(found, key=lambda mm: abs(mm.frequency_hz - model.frequency_hz[r]))
        s = _statistical_tol(model, r, T)
        assert abs(m.frequency_hz / model.frequency_hz[r] - 1) < K_BOUND * s
        assert abs(m.damping_ratio - model.damping_ratio[r]) < K_BOUND * s
        shape = m.shape_vector(model.channels)
        assert mac(shape, model.shapes[:, r]) > 0.98
        assert m.mpc > 0.95 and m.mpd < 10.0


def test_close_pair_and_paper_modes_nominal():
    """The paper's 41.76 / 43.77 Hz pair (2 Hz apart) and 23.49 / 79.69 Hz are separated."""
    model = guideway_model(None)
    y = simulate_ambient(model, FS, T, noise_frac=0.05, seed=21)
    res = SSICov().fit(y, FS, model.channels)
    f = res.frequencies_hz()
    for f0 in (23.49, 41.76, 43.77, 79.69):
        assert np.min(np.abs(f - f0)) / f0 < 0.004
    pair = [m for m in res.modes if 40 < m.frequency_hz < 46]
    assert len(pair) == 2
    a, b = (p.shape_vector(model.channels) for p in pair)
    assert mac(a, b) < 0.2


def test_uncertainty_is_calibrated_monte_carlo():
    """Block-based std vs the actual scatter over independent records (Monte Carlo)."""
    model = guideway_model(None)
    errs, stds = [], []
    for seed in range(6):
        y = simulate_ambient(model, FS, 60.0, noise_frac=0.05, seed=100 + seed)
        res = SSICov(block_rows=40, orders=range(2, 61, 2), spectrum=False).fit(y, FS, model.channels)
        f = res.frequencies_hz()
        for r in range(6):
            k = int(np.argmin(np.abs(f - model.frequency_hz[r])))
            errs.append(f[k] - model.frequency_hz[r])
            stds.append(res.modes[k].std_frequency_hz)
    errs, stds = np.array(errs), np.array(stds)
    z = errs / stds
    assert np.all(np.isfinite(stds)) and np.all(stds > 0)
    # reported std neither far too small nor far too large (chi-square of 36 values)
    assert 0.3 < np.sqrt(np.mean(z ** 2)) < 2.0
    assert np.max(np.abs(z)) < 5.0


def test_decimation_path_2khz():
    model = guideway_model(None)
    y = simulate_ambient(model, 2000.0, 60.0, noise_frac=0.05, seed=31)
    res = SSICov(block_rows=40, orders=range(2, 61, 2), decimate_to_hz=500.0).fit(y, 2000.0, model.channels)
    assert res.fs_hz == pytest.approx(500.0)
    w = assert_modes_match(res.modes, model, 150.0, freq_tol=0.004)
    assert w["missing"] == [] and w["spurious"] == []
    assert w["freq_rel"] < 0.004 and w["mac_min"] > 0.98


def test_white_noise_only_gives_no_modes():
    rng = np.random.default_rng(5)
    y = rng.standard_normal((60000, 15))
    res = SSICov(spectrum=False).fit(y, FS)
    assert [m.frequency_hz for m in res.modes if 5 <= m.frequency_hz <= 150] == []


def test_to_dict_schema_and_json():
    model = guideway_model(None)
    y = simulate_ambient(model, FS, 40.0, noise_frac=0.05, seed=41)
    res = SSICov(orders=range(2, 41, 2)).fit(y, FS, model.channels)
    d = res.to_dict()
    assert d["schema"] == "maglev-modes/1"
    assert len(d["modes"]) == len(res.modes) > 0
    for m in d["modes"]:
        for key in ("id", "frequency_hz", "damping_ratio", "mode_shape", "mpc",
                    "std_frequency_hz", "std_damping_ratio"):
            assert key in m
        assert set(m["mode_shape"]) == set(model.channels)
        assert max(abs(v) for v in m["mode_shape"].values()) == pytest.approx(1.0)
    json.dumps(res.to_dict(diagram=True))
    assert [m["id"] for m in d["modes"]] == [f"M{k + 1}" for k in range(len(d["modes"]))]
    st = res.stabilization
    assert len(st) > 0 and st.order.min() >= 2 and st.order.max() <= 40
    assert res.spectrum is not None and res.spectrum.singular_values.shape[0] == res.spectrum.frequency_hz.size


def test_covariances_match_direct_formula():
    rng = np.random.default_rng(3)
    y = rng.standard_normal((3000, 4))
    cov = output_covariances(y, 6, refs=np.array([0, 2]))[0]
    m = 3000 - 6
    for k in (0, 1, 6):
        ref = sum(np.outer(y[t + k], y[t, [0, 2]]) for t in range(m)) / m
        np.testing.assert_allclose(cov[k], ref, rtol=1e-10, atol=1e-12)


def test_shape_indicators_analytic():
    real = np.array([1.0, -0.5, 0.25, 0.0])
    assert mpc(real * np.exp(0.7j)) == pytest.approx(1.0)
    assert mpd(real * np.exp(0.7j)) == pytest.approx(0.0, abs=1e-6)
    circ = np.array([1.0, 1j, -1.0, -1j])
    assert mpc(circ) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(real_mode_shape(-2.0 * real * np.exp(1.1j)), real)
    assert mac(np.array([1.0, 0.0]), np.array([0.0, 1.0])) == pytest.approx(0.0)
    assert mac(real, 3 * real) == pytest.approx(1.0)


@pytest.mark.parametrize("bad,msg", [
    (np.zeros(100), "2-D"),
    (np.full((5000, 3), np.nan), "finite"),
    (np.zeros((50, 3)), "samples"),
])
def test_user_errors(bad, msg):
    with pytest.raises(UserError, match=msg):
        SSICov().fit(bad, FS)


def test_user_error_options():
    with pytest.raises(UserError, match="polish"):
        SSICov(polish="lsq")
    with pytest.raises(UserError, match="orders"):
        SSICov(block_rows=2, orders=range(2, 81, 2)).fit(np.random.default_rng(0).standard_normal((4000, 3)), FS)
    with pytest.raises(UserError, match="channels"):
        SSICov().fit(np.zeros((4000, 3)), FS, channels=["a"])
    with pytest.raises(UserError, match="ref_channels"):
        SSICov(ref_channels=["zz"]).fit(np.random.default_rng(0).standard_normal((4000, 3)), FS,
                                        channels=["a", "b", "c"])
