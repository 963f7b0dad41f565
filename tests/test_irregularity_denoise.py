"""Coherent Wiener gain for the reconstructed irregularity (maglev_ros.irregularity.denoise).

Reference: two magnets see one rail r with a known spectrum plus independent white errors of a
known level; the Wiener gain for their mean is R / (R + N / 2) with R and N the generating spectra."""
import numpy as np
import pytest

from maglev_ros.irregularity.denoise import apply_gain, coherent_gain

DX = 0.02


def _rail_and_noise(seed, n=2 ** 15, k0=1.0, noise_std=2e-5):
    rng = np.random.default_rng(seed)
    k = np.fft.rfftfreq(n, DX)
    # one-sided rail PSD R(k) = 1e-9 m^2/(cycle/m) / (1 + (k/k0)^4): strong long waves, steep fall
    # above k0; it meets the mean's noise N/2 near 0.3 m wavelength
    amp = np.sqrt(1e-9 * n / (4 * DX)) / np.sqrt(1.0 + (k / k0) ** 4)
    spec = amp * (rng.standard_normal(k.size) + 1j * rng.standard_normal(k.size))
    spec[0] = 0.0
    rail = np.fft.irfft(spec, n)
    noise = noise_std * rng.standard_normal((2, n))
    return k, amp, rail, noise


def test_gain_matches_the_wiener_gain_of_the_generating_spectra():
    k, amp, rail, noise = _rail_and_noise(1)
    g = coherent_gain(rail[None, :] + noise, DX)
    n = rail.size
    # one-sided PSDs of the generating processes (rfft amplitude convention of _rail_and_noise)
    R = 2 * (2 * amp ** 2) * DX / n
    N = 2 * (2e-5) ** 2 * DX
    want = R / (R + N / 2)
    for kk in (0.3, 2.0, 4.0, 6.0, 10.0):
        got = np.interp(kk, g.wavenumber_cpm, g.gain)
        w = np.interp(kk, k, want)
        assert abs(got - w) < 0.12, (kk, got, w)
    assert g.n_magnets == 2


def test_filtered_mean_is_closer_to_the_rail_than_the_raw_mean():
    _, _, rail, noise = _rail_and_noise(2)
    prof = rail[None, :] + noise
    g = coherent_gain(prof, DX)
    raw = prof.mean(axis=0)
    den = apply_gain(raw, DX, g)
    e_raw = np.sqrt(np.mean((raw - rail) ** 2))
    e_den = np.sqrt(np.mean((den - rail) ** 2))
    assert e_den < 0.5 * e_raw
    # the rail's shape is kept (better than in the raw mean)
    assert np.corrcoef(den, rail)[0, 1] > max(0.98, np.corrcoef(raw, rail)[0, 1])
    assert g.cut_wavelength_m() is not None and 0.05 < g.cut_wavelength_m() < 1.0


def test_what_the_magnets_agree_on_is_kept():
    _, _, rail, _ = _rail_and_noise(3)
    g = coherent_gain(np.vstack([rail, rail, rail]), DX)
    assert np.all(g.gain[g.wavenumber_cpm < 15] > 0.99)


@pytest.mark.parametrize("shape", [(1, 5000), (2, 40)])
def test_one_magnet_or_too_short_gives_none(shape):
    assert coherent_gain(np.ones(shape), DX) is None


def test_nan_outside_common_stretch_is_ignored():
    _, _, rail, noise = _rail_and_noise(4)
    prof = rail[None, :] + noise
    prof[0, :3000] = np.nan
    prof[1, -2000:] = np.nan
    g = coherent_gain(prof, DX)
    assert g is not None and g.n_points == rail.size - 5000
