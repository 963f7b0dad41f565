"""Transmissibility / Forsythe-RFP identification: exact analytic checks and simulated truth."""
from __future__ import annotations

import numpy as np
import pytest

from maglev_ros.errors import UserError
from maglev_ros.modal.transmissibility import (
    TransmissibilityID, comrade_roots, forsythe_basis, rfp_common_denominator,
)
from modal_data import assert_modes_match, guideway_model, simulate_ambient

FR = np.array([23.49, 41.76, 43.77, 79.69])
ZE = np.array([0.015, 0.012, 0.018, 0.020])
LAM = -ZE * 2 * np.pi * FR + 1j * 2 * np.pi * FR * np.sqrt(1 - ZE ** 2)


def _half_spectrum(s, phi, gamma):
    """Analytic positive half spectrum sum_m phi_m gamma_m / (s - lam_m) + conjugate terms."""
    out = np.zeros((s.size, phi.shape[0], gamma.shape[0]), dtype=complex)
    for m in range(LAM.size):
        out += (phi[:, m][None, :, None] * gamma[:, m][None, None, :]) / (s - LAM[m])[:, None, None]
        out += (phi[:, m].conj()[None, :, None] * gamma[:, m].conj()[None, None, :]) / \
            (s - LAM[m].conj())[:, None, None]
    return out


def test_forsythe_basis_orthonormal_and_comrade_roots_match_power_basis():
    x = np.linspace(-1, 1, 200)
    p, a, b = forsythe_basis(x, 12)
    np.testing.assert_allclose(p.T @ p, np.eye(13), atol=1e-12)
    rng = np.random.default_rng(0)
    d = rng.standard_normal(6) + 1j * rng.standard_normal(6)
    # independent reference: the same polynomial in the power basis, fitted through the values
    vals = p[:, :6] @ d
    coef = np.polyfit(x, vals, 5)
    np.testing.assert_allclose(np.sort_complex(comrade_roots(d, a, b)),
                               np.sort_complex(np.roots(coef)), atol=1e-8)


def test_rfp_recovers_poles_of_exact_frfs():
    f = np.arange(5.0, 100.0, 0.25)
    s = 2j * np.pi * f
    rng = np.random.default_rng(1)
    phi = rng.standard_normal((5, 4))
    h = _half_spectrum(s, phi, rng.standard_normal((2, 4)))
    h = h.reshape(f.size, -1)
    wc, wh = 2 * np.pi * 52.5, 2 * np.pi * 47.5
    p, a, b = forsythe_basis((2 * np.pi * f - wc) / wh, 12)
    d = rfp_common_denominator(h, p, 10)
    w = wc + wh * comrade_roots(d, a, b)
    lam = 1j * w                                        # pole = j * (complex angular frequency)
    for l0 in LAM:
        assert np.min(np.abs(lam - l0)) / abs(l0) < 1e-5


def test_psdt_converge_at_poles_and_delta_inverse_has_the_poles():
    """PSD transmissibilities with different reference outputs meet at every pole (exactly, by
    the modal expansion), so 1/Delta has the system poles: fitted per test point."""
    rng = np.random.default_rng(2)
    phi = rng.standard_normal((6, 4))
    gamma = rng.standard_normal((6, 4)) + 0.3j * rng.standard_normal((6, 4))
    j, k1, k2 = 0, 1, 2
    for m, l0 in enumerate(LAM):
        s = np.array([l0 + 1e-10 * abs(l0)])
        sp = _half_spectrum(s, phi, gamma)[0]
        t1 = sp[:, k1] / sp[j, k1]
        t2 = sp[:, k2] / sp[j, k2]
        np.testing.assert_allclose(t1, phi[:, m] / phi[j, m], rtol=1e-4)
        np.testing.assert_allclose(t2, phi[:, m] / phi[j, m], rtol=1e-4)
    f = np.arange(5.0, 100.0, 0.1)
    sp = _half_spectrum(2j * np.pi * f, phi, gamma)
    wc, wh = 2 * np.pi * 52.5, 2 * np.pi * 47.5
    p, a, b = forsythe_basis((2 * np.pi * f - wc) / wh, 24)
    hits = np.zeros(LAM.size)
    for i in range(3, 6):
        delta = sp[:, i, k1] / sp[:, j, k1] - sp[:, i, k2] / sp[:, j, k2]
        d = rfp_common_denominator((1.0 / delta)[:, None], p, 24)
        lam = 1j * (wc + wh * comrade_roots(d, a, b))
        hits += [np.min(np.abs(lam - l0)) / abs(l0) < 1e-4 for l0 in LAM]
    assert np.all(hits == 3)


@pytest.mark.parametrize("variant,seed", [(None, 0), (2, 3)])
def test_half_spectra_rfp_on_simulated_ambient(variant, seed):
    model = guideway_model(variant)
    y = simulate_ambient(model, 500.0, 120.0, noise_frac=0.05, seed=seed)
    res = TransmissibilityID().fit(y, 500.0, model.channels)
    assert res.method == "half-spectra-rfp"
    chk = assert_modes_match(res.modes, model, 150.0)
    assert chk["missing"] == []
    assert chk["freq_rel"] < 0.005
    assert chk["damping_abs"] < 0.005
    assert len(chk["spurious"]) <= 1
    assert res.to_dict()["schema"] == "maglev-modes/1"


def test_psdt_on_simulated_ambient_finds_dominant_modes():
    model = guideway_model(None)
    y = simulate_ambient(model, 500.0, 120.0, noise_frac=0.05, seed=0)
    res = TransmissibilityID(source="psdt").fit(y, 500.0, model.channels)
    assert res.method == "psd-transmissibility"
    f = res.frequencies_hz()
    # limited on noisy ambient data (see module docstring): at least two of the paper's four modes,
    # and nothing that is not a true mode
    found = [f0 for f0 in (23.49, 41.76, 43.77, 79.69) if np.min(np.abs(f - f0)) / f0 < 0.005]
    assert len(found) >= 2
    assert all(np.min(np.abs(model.frequency_hz - x) / model.frequency_hz) < 0.01 for x in f)


def test_transmissibility_user_errors():
    y = np.random.default_rng(0).standard_normal((5000, 2))
    with pytest.raises(UserError, match="3 channels"):
        TransmissibilityID(freq_range_hz=(5, 40)).fit(y, 100.0)
    with pytest.raises(UserError, match="Nyquist"):
        TransmissibilityID(freq_range_hz=(5, 60)).fit(np.zeros((5000, 3)), 100.0)
    with pytest.raises(UserError, match="source"):
        TransmissibilityID(source="foo")
