"""Band powers, noise floor and mismatch localization against analytic references and Monte Carlo."""
import math

import numpy as np
import pytest

from maglev_ros.discrepancy.evaluate import RecData, fit_noise_floor
from maglev_ros.discrepancy.features import FrameGrid, band_powers, band_widths, frame_grid, usable_bands
from maglev_ros.discrepancy.localize import mismatches, residual_map
from maglev_ros.discrepancy.recording import recording_from_arrays

FS = 500.0


def _grid(t):
    return FrameGrid(np.arange(0.25, t[-1] - 0.25, 0.25), 0.5, np.array([0, 5, 10, 20, 40, 80, 160.0]))


@pytest.mark.parametrize("f0,amp", [(12.0, 0.3), (57.0, 2.0), (101.0, 0.05)])
def test_sinusoid_band_power_is_half_amplitude_squared(f0, amp):
    t = np.arange(0, 4, 1 / FS)
    x = amp * np.sin(2 * np.pi * f0 * t + 0.3)
    g = _grid(t)
    p = band_powers(t, x, FS, g)
    # Parseval: the bands of a frame hold the tone's mean square A^2/2
    assert np.allclose(p.sum(axis=1), amp ** 2 / 2, rtol=0.02)
    # triangular bands between the centres c_b: the share of the upper band is (f0 - c_b)/(c_b+1 - c_b)
    c = 0.5 * (g.edges_hz[1:] + g.edges_hz[:-1])
    b = np.searchsorted(c, f0) - 1
    share = (f0 - c[b]) / (c[b + 1] - c[b])
    assert np.allclose(p[:, b + 1] / p.sum(axis=1), share, atol=0.03)


def test_white_noise_band_power_and_noise_floor_monte_carlo():
    rng = np.random.default_rng(3)
    sigma = 0.01
    t = np.arange(0, 20, 1 / FS)
    g = _grid(t)
    # white: variance spread evenly to Nyquist; triangular band b integrates (c_b+1 - c_b-1)/2 Hz
    c = 0.5 * (g.edges_hz[1:] + g.edges_hz[:-1])
    width = np.empty(c.size)
    width[1:-1] = (c[2:] - c[:-2]) / 2
    width[0] = c[0] + (c[1] - c[0]) / 2
    width[-1] = (c[-1] - c[-2]) / 2 + (g.edges_hz[-1] - c[-1])
    assert np.allclose(band_widths(g), width, rtol=1e-3)
    expect = sigma ** 2 * width / (FS / 2)
    est = []
    for _ in range(5):
        p = band_powers(t, rng.normal(0, sigma, t.size), FS, g)
        est.append(fit_noise_floor(p, g, usable_bands(g, FS), np.zeros(g.n_bands, bool)))
    est = np.mean(est, axis=0)
    ok = usable_bands(g, FS)
    assert np.allclose(est[ok], expect[ok], rtol=0.12)


def _rec(signals, pos=None):
    md = {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 20.0},
                                                           {"id": "S2", "start_m": 20.0, "length_m": 20.0}]},
          "sensors": {"G1": {"topic": "/testline/guideway/accel", "position_m": 10.0, "span": "S1"},
                      "G2": {"topic": "/testline/guideway/accel", "position_m": 30.0, "span": "S2"}},
          "vehicle": {"magnet_offsets_m": [0.0, -2.0]}, "run": {"kind": "pass"}}
    return recording_from_arrays(md, signals, pos)


def _rd(rec, noise_sigma):
    g = frame_grid(rec)
    pm = {n: band_powers(c.time_s, c.values, c.sample_rate_hz, g) for n, c in rec.channels.items()}
    masks = {n: usable_bands(g, c.sample_rate_hz) for n, c in rec.channels.items()}
    rd = RecData(rec, g, pm, masks)
    width = band_widths(g)
    for n in rec.channels:
        rd.noise[n] = noise_sigma ** 2 * width / (FS / 2)
    return rd


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_noise_alone_is_never_a_mismatch(seed):
    rng = np.random.default_rng(seed)
    t = np.arange(0, 8, 1 / FS)
    sig = {"G1": (t, rng.normal(0, 0.01, t.size)), "G2": (t, rng.normal(0, 0.01, t.size))}
    rec = _rec(sig, (t[::5], 10.0 * t[::5] - 20.0, np.full(t[::5].size, 10.0)))
    rd = _rd(rec, 0.01)
    model = {n: np.broadcast_to(rd.noise[n], rd.pm[n].shape) for n in rec.channels}
    assert mismatches(residual_map(rd, model)) == []


def test_injected_tone_is_located_in_time_place_and_band():
    rng = np.random.default_rng(7)
    t = np.arange(0, 8, 1 / FS)
    tone = np.where((t > 3.0) & (t < 5.0), 0.2 * np.sin(2 * np.pi * 47.0 * t), 0.0)
    sig = {"G1": (t, rng.normal(0, 0.01, t.size)), "G2": (t, rng.normal(0, 0.01, t.size) + tone)}
    # vehicle at 10 m/s, reference point at -20 m at t = 0: at 3-5 s it is at 10-30 m
    rec = _rec(sig, (t[::5], 10.0 * t[::5] - 20.0, np.full(t[::5].size, 10.0)))
    rd = _rd(rec, 0.01)
    model = {n: np.broadcast_to(rd.noise[n], rd.pm[n].shape) for n in rec.channels}
    found = mismatches(residual_map(rd, model))
    assert len(found) >= 1
    m = found[0]
    assert m.channels == ("G2",)
    assert m.frequency_hz[0] <= 47.0 <= m.frequency_hz[1]
    assert 2.5 <= m.time_s[0] <= 3.3 and 4.7 <= m.time_s[1] <= 5.5
    # place: the vehicle (magnets at ref and ref-2 m) covered about 8-30 m meanwhile
    assert 5.0 <= m.position_m[0] <= 12.0 and 28.0 <= m.position_m[1] <= 36.0
    # severity: tone power 0.02 over the 44-52 Hz... band noise power -> >> 1
    assert m.severity > 10
