"""Statistical accuracy of the modal estimates against the Cramer-Rao bound (issue 4).

References, all independent of the estimator under test:
* the single-mode asymptotic bound ``var(f)/f^2 = var(zeta) = zeta / (2 pi f T)`` (Whittle
  information of a Lorentzian peak);
* the multichannel Whittle bound of the exact simulated structure (modal_data.cramer_rao_std);
* an oracle that knows the model structure: least squares on an exact AR(2) record (the discrete
  displacement of one mode driven by white noise, asymptotically maximum likelihood).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from maglev_ros.modal.ssi_cov import SSICov
from modal_data import ModalModel, cramer_rao_std, guideway_model, simulate_ambient

FS = 500.0


def _bound(f_hz, zeta, duration_s):
    return np.sqrt(zeta / (2 * np.pi * f_hz * duration_s))


def test_single_mode_whittle_bound_matches_formula():
    """Multichannel Whittle CRB of a one-mode structure == sqrt(zeta / (2 pi f T))."""
    for f0, z0 in ((23.49, 0.015), (80.0, 0.02)):
        base = guideway_model(None)
        shapes = base.shapes[:, :1]
        one = ModalModel(np.array([f0]), np.array([z0]), shapes, base.channels, base.kinds[:1],
                         np.zeros_like(shapes))
        sf, sz = cramer_rao_std(one, FS, 120.0, noise_frac=0.05, grid_hz=0.05)
        ref = _bound(f0, z0, 120.0)
        assert sf[0] == pytest.approx(ref, rel=0.05)
        assert sz[0] == pytest.approx(ref, rel=0.05)


def test_oracle_ar2_estimator_reaches_the_bound():
    """Monte Carlo: the ML (least-squares) AR(2) fit of an exact single-mode record has
    std(f)/f = sqrt(zeta / (2 pi f T)): the bound is attainable, not just a lower limit."""
    rng = np.random.default_rng(7)
    f0, z0, T, n_rec = 23.49, 0.015, 120.0, 300
    wn = 2 * np.pi * f0
    mu = np.exp((-z0 * wn + 1j * wn * np.sqrt(1 - z0 ** 2)) / FS)
    a = np.array([1.0, -2 * mu.real, abs(mu) ** 2])
    n = int(T * FS)
    x = lfilter([1.0], a, rng.standard_normal((n_rec, n + 2000)), axis=1)[:, 2000:]
    y, x1, x2 = x[:, 2:], x[:, 1:-1], x[:, :-2]
    g11, g12, g22 = (x1 * x1).sum(1), (x1 * x2).sum(1), (x2 * x2).sum(1)
    b1, b2 = (y * x1).sum(1), (y * x2).sum(1)
    det = g11 * g22 - g12 ** 2
    a1, a2 = (g22 * b1 - g12 * b2) / det, (g11 * b2 - g12 * b1) / det
    roots = (a1[:, None] + np.array([1, -1]) * np.sqrt((a1 ** 2 + 4 * a2 + 0j))[:, None]) / 2
    lam = np.log(roots[:, 0]) * FS
    f = np.abs(lam) / (2 * np.pi)
    z = -lam.real / np.abs(lam)
    ref = _bound(f0, z0, T)
    # 300 records: the sample std is known to +-4 % (1 sigma)
    assert np.std(f / f0 - 1) == pytest.approx(ref, rel=0.15)
    assert np.std(z - z0) == pytest.approx(ref, rel=0.15)
    assert abs(np.mean(f / f0 - 1)) < 0.3 * ref


def _errors(n_seeds, seed0, polish="whittle", duration_s=120.0):
    model = guideway_model(None)
    errs = []
    for s in range(n_seeds):
        y = simulate_ambient(model, FS, duration_s, noise_frac=0.05, seed=seed0 + s)
        res = SSICov(spectrum=False, polish=polish).fit(y, FS, model.channels)
        f = res.frequencies_hz()
        errs.append([f[np.argmin(np.abs(f - f0))] / f0 - 1 for f0 in model.frequency_hz[:6]])
    bound = _bound(model.frequency_hz[:6], model.damping_ratio[:6], duration_s)
    return np.array(errs), bound


def test_frequency_scatter_near_the_bound_fast():
    """8 records x 6 modes: the RMS of error / bound is ~1.25 for the default estimator (80-record
    bench: per-mode std 1.05-1.35 x the bound, |bias| <= 0.85 x); 1.7 leaves > 3 sigma of
    sampling scatter for 48 values. Plain SSI-cov (1.05-2.1 x) is the slower test's contrast."""
    e, bound = _errors(8, 300)
    z = e / bound
    assert np.sqrt(np.mean(z ** 2)) < 1.7
    assert np.max(np.abs(z)) < 5.0


@pytest.mark.slow
def test_frequency_std_per_mode_against_crb_many_seeds():
    """30 records: per-mode std of the default estimator within 1.75 x the exact-structure CRB
    (measured 1.06-1.33 x; 30 samples give a std to +-13 %), and on the same records lower than
    plain SSI-cov's on the modes where SSI-cov is far from the bound (43.8-132 Hz: SSI-cov
    1.3-2.1 x; the polish 0.65-0.86 x SSI-cov's std there)."""
    model = guideway_model(None)
    crb, _ = cramer_rao_std(model, FS, 120.0, 0.05, grid_hz=0.1)
    e_ml, _ = _errors(30, 400)
    e_ssi, _ = _errors(30, 400, polish=None)
    sd_ml, sd_ssi = e_ml.std(axis=0, ddof=1), e_ssi.std(axis=0, ddof=1)
    assert np.all(sd_ml < 1.75 * crb[:6]), sd_ml / crb[:6]
    assert np.all(sd_ml > 0.7 * crb[:6]), sd_ml / crb[:6]      # nothing beats the bound
    assert np.mean(sd_ml[2:] / sd_ssi[2:]) < 0.9
