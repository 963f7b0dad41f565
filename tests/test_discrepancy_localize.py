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


def _tone_case():
    """White noise on G1 and G2, a 47 Hz tone on G2 in 3-5 s; the model: the noise floor alone."""
    rng = np.random.default_rng(7)
    t = np.arange(0, 8, 1 / FS)
    tone = np.where((t > 3.0) & (t < 5.0), 0.2 * np.sin(2 * np.pi * 47.0 * t), 0.0)
    sig = {"G1": (t, rng.normal(0, 0.01, t.size)), "G2": (t, rng.normal(0, 0.01, t.size) + tone)}
    # vehicle at 10 m/s, reference point at -20 m at t = 0: at 3-5 s it is at 10-30 m
    rec = _rec(sig, (t[::5], 10.0 * t[::5] - 20.0, np.full(t[::5].size, 10.0)))
    rd = _rd(rec, 0.01)
    model = {n: np.broadcast_to(rd.noise[n], rd.pm[n].shape) for n in rec.channels}
    return t, tone, rd, model


def test_injected_tone_is_located_in_time_place_and_band():
    _t, _tone, rd, model = _tone_case()
    found = mismatches(residual_map(rd, model))
    assert len(found) >= 1
    m = found[0]
    assert m.channels == ("G2",)
    assert m.frequency_hz[0] <= 47.0 <= m.frequency_hz[1]
    assert 2.5 <= m.time_s[0] <= 3.3 and 4.7 <= m.time_s[1] <= 5.5
    # place: the vehicle (magnets at ref and ref-2 m) covered about 8-30 m meanwhile; G2 sits on
    # span S2 (20-40 m), which answers only its own load: the overlap, about 20-30 m
    assert m.position_m[0] == pytest.approx(20.0) and 28.0 <= m.position_m[1] <= 33.0
    # severity: tone power 0.02 over the 44-52 Hz... band noise power -> >> 1
    assert m.severity > 10



def test_a_mismatch_is_explained_once_the_twin_carries_its_physics():
    """The tone's mismatch against a twin that has the tone (its exact band powers, computed from
    the tone alone) leaves no cell flagged; against the same twin without it, every cell stays."""
    from maglev_ros.discrepancy.localize import region_after
    t, tone, rd, without = _tone_case()
    with_tone = dict(without, G2=without["G2"] + band_powers(t, tone, FS, rd.grid))
    before = residual_map(rd, without)
    m = mismatches(before)[0]
    kept = region_after(m, before, residual_map(rd, without))
    assert kept == region_after(m, before, before) and kept["flagged_share"] == 1.0
    assert kept["severity"] == pytest.approx(m.severity, rel=0.1)     # the region's box, not only its cells
    explained = region_after(m, before, residual_map(rd, with_tone))
    assert explained["flagged_share"] == 0.0 and explained["severity"] < 0.1 * m.severity

# ---- noise floor from the recording's own quiet frames (coloured sensor noise) ----------------
def _coloured(rng, n, colour, std):
    """Independent reference noise of RMS ``std``: white, pink (PSD ~ 1/f down to the record's
    lowest frequency) or brown (PSD ~ 1/(f^2 + 0.5^2): a random walk leaking at 0.5 Hz, as an
    instrument chain with its high-pass gives; an unbounded random walk is a drift, not noise)."""
    w = rng.standard_normal(n)
    if colour != "white":
        f = np.fft.rfftfreq(n, 1 / FS)
        f[0] = f[1]
        shape = np.sqrt(f ** 2 + 0.5 ** 2) if colour == "brown" else np.sqrt(f)
        w = np.fft.irfft(np.fft.rfft(w) / shape, n)
    return std * w / w.std()


def _pass_case(rng, colour, std, tone_amp=0.0, tone_hz=47.0):
    """8 s record; the 'twin' signal (a vehicle-passage response: 2-6 Hz quasi-static bump and a
    decaying 17 Hz mode) lives in 2.5-5.5 s, known exactly to the model; noise of one colour on
    top; optionally an unmodelled tone on G2 in 3-5 s (the real effect)."""
    from maglev_ros.discrepancy.evaluate import fit_noise_floor
    t = np.arange(0, 8, 1 / FS)
    env = np.clip(np.sin(np.pi * (t - 2.5) / 3.0), 0, None) * ((t > 2.5) & (t < 5.5))
    twin = {"G1": 0.5 * env * np.sin(2 * np.pi * 17.0 * t) + 0.3 * env,
            "G2": 0.4 * env * np.sin(2 * np.pi * 17.0 * t + 1.0) + 0.2 * env}
    tone = tone_amp * np.sin(2 * np.pi * tone_hz * t) * ((t > 3.0) & (t < 5.0))
    sig = {"G1": (t, twin["G1"] + _coloured(rng, t.size, colour, std)),
           "G2": (t, twin["G2"] + _coloured(rng, t.size, colour, std) + tone)}
    rec = _rec(sig, (t[::5], 10.0 * t[::5] - 20.0, np.full(t[::5].size, 10.0)))
    g = frame_grid(rec)
    pm = {n: band_powers(c.time_s, c.values, c.sample_rate_hz, g) for n, c in rec.channels.items()}
    masks = {n: usable_bands(g, c.sample_rate_hz) for n, c in rec.channels.items()}
    rd = RecData(rec, g, pm, masks)
    model = {}
    for n, c in rec.channels.items():
        pt = band_powers(c.time_s, twin[n], c.sample_rate_hz, g)
        tot = pt.sum(axis=1)
        quiet = tot <= 1e-3 * tot.max()
        # the model's own floor, as evaluate.prepare makes it: a power law through quiet frames
        rd.noise[n] = fit_noise_floor(pm[n][quiet], g, masks[n], np.zeros(g.n_bands, bool))
        rd.quiet[n] = quiet
        model[n] = pt + rd.noise[n][None, :]
    return rd, model


@pytest.mark.parametrize("colour", ["white", "pink", "brown"])
@pytest.mark.parametrize("std", [0.003, 0.03])
@pytest.mark.parametrize("seed", [11, 12])
def test_coloured_sensor_noise_is_never_a_mismatch(colour, std, seed):
    rng = np.random.default_rng(seed + int(std * 1e4) + 100 * len(colour))
    rd, model = _pass_case(rng, colour, std)
    found = mismatches(residual_map(rd, model))
    assert found == [], [m.to_dict() for m in found]


@pytest.mark.parametrize("colour", ["white", "pink", "brown"])
def test_modest_effect_is_still_found_over_coloured_noise(colour):
    """A tone whose band power is ~25x the (true) noise power in its band, in 3-5 s on G2."""
    rng = np.random.default_rng(5)
    std = 0.01
    # true noise power in the tone's band, by Monte Carlo on the same noise process
    g = FrameGrid(np.arange(0.25, 7.75, 0.25), 0.5, __import__("maglev_ros.discrepancy.features",
                                                                fromlist=["BAND_EDGES_HZ"]).BAND_EDGES_HZ)
    t = np.arange(0, 8, 1 / FS)
    b = int(np.searchsorted(g.band_center_hz, 47.0) - 1)
    pn = np.mean([np.nanmean(band_powers(t, _coloured(rng, t.size, colour, std), FS, g)[:, b:b + 2].sum(axis=1))
                  for _ in range(10)])
    amp = math.sqrt(2 * 25 * pn)
    rd, model = _pass_case(rng, colour, std, tone_amp=amp)
    found = mismatches(residual_map(rd, model))
    hits = [m for m in found if m.frequency_hz[0] <= 47.0 <= m.frequency_hz[1]]
    assert hits, [m.to_dict() for m in found]
    m = hits[0]
    assert m.channels == ("G2",)
    assert 2.4 <= m.time_s[0] <= 3.3 and 4.7 <= m.time_s[1] <= 5.6
    # nothing else is called a mismatch
    assert len(found) == len(hits)


def test_pink_noise_floor_is_raised_to_what_quiet_frames_show():
    """The power-law floor under-reads the lowest band of 1/f noise; the local floor does not."""
    from maglev_ros.discrepancy.localize import local_noise_floor
    rng = np.random.default_rng(21)
    rd, model = _pass_case(rng, "pink", 0.02)
    fl = local_noise_floor(rd, model)
    for n in rd.rec.channels:
        q = rd.quiet[n]
        mean_quiet = np.mean(rd.pm[n][q], axis=0)
        assert np.all(fl[n] >= rd.noise[n] * (1 - 1e-12))
        # lowest band: within a factor 2 of the quiet frames' mean power (chi-square scatter)
        assert 0.5 <= fl[n][0] / mean_quiet[0] <= 2.0


def test_guideway_region_without_the_vehicle_is_placed_on_the_sensors_span():
    rng = np.random.default_rng(8)
    t = np.arange(0, 8, 1 / FS)
    tone = np.where((t > 3.0) & (t < 5.0), 0.2 * np.sin(2 * np.pi * 47.0 * t), 0.0)
    sig = {"G1": (t, rng.normal(0, 0.01, t.size)), "G2": (t, rng.normal(0, 0.01, t.size) + tone)}
    # vehicle far ahead of the line (x > 100 m) while G2 rings: its span S2 is the place
    rec = _rec(sig, (t[::5], 10.0 * t[::5] + 100.0, np.full(t[::5].size, 10.0)))
    rd = _rd(rec, 0.01)
    model = {n: np.broadcast_to(rd.noise[n], rd.pm[n].shape) for n in rec.channels}
    m = mismatches(residual_map(rd, model))[0]
    assert m.channels == ("G2",) and m.position_m == pytest.approx((20.0, 40.0))
