"""Inertial profiler against the KNOWN irregularity of synthetic recordings (tests/irregularity_data).

The reference is the true profile on the result's grid band-passed with the filter the result
states (Butterworth order 4, zero-phase, corners 1/max_wavelength and 1/min_wavelength); the
vehicle model (2nd-order levitation follower + car-body sinusoids) is independent of the twin.
Targets: correlation >= 0.95 and RMS error <= 10 % of the band-limited truth RMS.
"""
from __future__ import annotations

import warnings
from types import SimpleNamespace as NS

import numpy as np
import pytest

from irregularity_data import bandpass_truth, make_recording
from maglev_ros.errors import UserError
from maglev_ros.irregularity.profile import IncrementalProfiler, InertialProfiler


def _score(res, truth_fn, lam=None):
    lo, hi = lam or (res.min_wavelength_m, res.max_wavelength_m)
    truth = bandpass_truth(res.position_m, truth_fn(res.position_m), lo, hi)
    m = res.valid
    est = res.irregularity_m[m]
    c = float(np.corrcoef(est, truth[m])[0, 1])
    rel = float(np.sqrt(np.mean((est - truth[m]) ** 2)) / np.sqrt(np.mean(truth[m] ** 2)))
    return c, rel, truth


CASES = [  # km/h, speed kind, seed, f_c
    (15, "constant", 11, 0.3),
    (25, "uneven", 12, 0.2),
    (30, "stop", 13, 0.2),
    (40, "constant", 14, 0.2),
    (40, "uneven", 15, 0.15),
    (20, "stop", 16, 0.25),
]


@pytest.mark.parametrize("kmh,kind,seed,fc", CASES)
def test_profile_matches_truth_in_band(kmh, kind, seed, fc):
    rec = make_recording(kmh, seed, kind, bias_mps2=[0.02, -0.01, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)     # a stop must not divide by zero
        res = InertialProfiler(highpass_hz=fc).fit(rec.accel, rec.gap, rec.position,
                                                   rec.magnet_offsets_m, rec.nominal_gap_m)
    c, rel, _ = _score(res, rec.truth_at)
    assert c >= 0.95, (c, rel)
    assert rel <= 0.10, (c, rel)
    # edges: 0.6/f_c s of time and one max wavelength of space at each end are dropped
    assert res.valid.sum() * res.spacing_m > 200.0
    assert res.kind == "loaded"
    # stated band: longest wavelength from the band speed and the corner
    assert res.max_wavelength_m == pytest.approx(res.band_speed_mps / (2 * fc))
    v_nom = kmh / 3.6
    v_min = 0.75 * v_nom if kind == "uneven" else v_nom
    if kind != "stop":
        assert res.band_speed_mps == pytest.approx(v_min, rel=0.05)
    else:
        assert "slow_section" in {w.kind for w in res.warnings}
    # point sensors: the short end is 4 grid steps (the default 0.25 m grid), not a magnet length
    assert res.min_wavelength_m == pytest.approx(4 * 0.25)
    # magnets agree with one another
    assert min(a[2] for a in res.agreement) > 0.9
    # both biased magnets reported, the unbiased one not
    biased = {w.channel for w in res.warnings if w.kind == "accel_bias"}
    assert biased == {"M1A", "M2A"}


def test_no_drift_long_wavelengths_removed_not_ramped():
    """A large long-wave component (300 m, 20 mm) lies outside the band: it must be removed, the
    result must stay at in-band size, without trend."""
    rec = make_recording(30, 21, "constant", bias_mps2=0.04)
    x = rec.truth_x_m
    rec.truth_r_m = rec.truth_r_m + 0.02 * np.sin(2 * np.pi * x / 300.0)
    # re-synthesise gaps for the changed rail: gap = g0 + r - z_m, so shift gaps by the extra r
    for k, off in enumerate(rec.magnet_offsets_m):
        xm = rec.x_ref_m + off
        rec.gap.data[:, k] += 0.02 * np.sin(2 * np.pi * xm / 300.0)
    res = InertialProfiler(highpass_hz=0.2).fit(rec.accel, rec.gap, rec.position,
                                                rec.magnet_offsets_m, rec.nominal_gap_m)
    assert res.max_wavelength_m < 300.0 / 5
    c, rel, truth = _score(res, rec.truth_at)
    assert c >= 0.95 and rel <= 0.10
    m = res.valid
    xs, ys = res.position_m[m], res.irregularity_m[m]
    slope = np.polyfit(xs, ys, 1)[0]
    assert abs(slope) * (xs[-1] - xs[0]) < 0.1 * np.std(truth[m])
    assert np.max(np.abs(ys)) < 1.5 * np.max(np.abs(truth[m]))


def test_band_and_en13848_flags_stated_in_dict():
    rec = make_recording(40, 22, "constant")
    res = InertialProfiler(highpass_hz=0.2).fit(rec.accel, rec.gap, rec.position,
                                                rec.magnet_offsets_m, rec.nominal_gap_m)
    d = res.to_dict()
    assert d["max_wavelength_m"] == pytest.approx(40 / 3.6 / 0.4)
    assert d["band_filter"]["low_cut_cycles_per_m"] == pytest.approx(1 / d["max_wavelength_m"])
    assert d["highpass_hz"] == 0.2
    import json
    json.dumps(d, allow_nan=False)


def test_deflection_removed_gives_unloaded_profile():
    rec = make_recording(30, 23, "constant", deflection_amp_m=1.5e-3)

    def w_of_x(x):
        return -1.5e-3 * np.sin(np.pi * (x % 12.384) / 12.384) ** 2

    loaded = InertialProfiler().fit(rec.accel, rec.gap, rec.position, rec.magnet_offsets_m,
                                    rec.nominal_gap_m)
    assert loaded.kind == "loaded"
    c, rel, _ = _score(loaded, lambda x: rec.truth_at(x) + w_of_x(x))
    assert c >= 0.95 and rel <= 0.10
    c_un, rel_un, _ = _score(loaded, rec.truth_at)
    assert rel_un > 0.3                     # the deflection is a real part of the loaded profile
    for defl in (rec.deflection, lambda t, x, magnet: w_of_x(x)):
        un = InertialProfiler().fit(rec.accel, rec.gap, rec.position, rec.magnet_offsets_m,
                                    rec.nominal_gap_m, deflection=defl)
        assert un.kind == "unloaded"
        c, rel, _ = _score(un, rec.truth_at)
        assert c >= 0.95 and rel <= 0.10


def test_dropouts_reported_and_masked():
    rec = make_recording(30, 24, "constant")
    a, g = rec.accel.data, rec.gap.data
    a[20000:20500, 0] = np.nan
    a[40000:40300, 1] = 0.0
    g[30000:30200, 2] = g[30000, 2]
    res = InertialProfiler().fit(rec.accel, rec.gap, rec.position, rec.magnet_offsets_m,
                                 rec.nominal_gap_m)
    got = {(w.kind, w.channel) for w in res.warnings}
    assert {("nonfinite", "M1A"), ("flatline", "M2A"), ("flatline", "M3G")} <= got
    c, rel, truth = _score(res, rec.truth_at)
    assert c >= 0.95 and rel <= 0.10
    # magnet 1's profile is NaN where the dropout maps (x_ref at t = 20..20.5 s)
    xd = np.interp([20.0, 20.5], rec.t_s, rec.x_ref_m)
    sel = (res.position_m > xd[0]) & (res.position_m < xd[1])
    assert np.isnan(res.magnet_profiles_m[0][sel]).all()
    assert np.isfinite(res.irregularity_m[sel]).all()        # other magnets still cover it


def test_streaming_matches_batch_with_bounded_buffers():
    rec = make_recording(30, 25, "uneven", length_m=700)
    batch = InertialProfiler(band_speed_mps=15 / 3.6).fit(
        rec.accel, rec.gap, rec.position, rec.magnet_offsets_m, rec.nominal_gap_m)
    inc = IncrementalProfiler(rec.magnet_offsets_m, rec.nominal_gap_m, hop_s=5.0)

    def blk(cd, i0, i1):
        return NS(time_s=cd.time_s[i0:i1], data=cd.data[i0:i1], channels=cd.channels,
                  sample_rate_hz=cd.sample_rate_hz)
    n = rec.accel.time_s.size
    for i in range(0, n, 200):
        inc.partial_fit(blk(rec.accel, i, i + 200), blk(rec.gap, i, i + 200),
                        blk(rec.position, i // 10, i // 10 + 20))
    res = inc.result()
    bound_s = 2 * inc.margin_s + inc.hop_s + 1.0 + 0.2
    assert inc.max_buffer_samples <= bound_s * 1000 + 1
    assert n > 2 * inc.max_buffer_samples              # memory really bounded below the record
    c, rel, _ = _score(res, rec.truth_at)
    assert c >= 0.95 and rel <= 0.10
    assert res.max_wavelength_m == pytest.approx(batch.max_wavelength_m)
    common, ib, is_ = np.intersect1d(np.round(batch.position_m, 6), np.round(res.position_m, 6),
                                     return_indices=True)
    a, b = batch.irregularity_m[ib], res.irregularity_m[is_]
    mm = np.isfinite(a) & np.isfinite(b)
    assert mm.sum() > 0.9 * np.isfinite(a).sum()
    assert np.sqrt(np.mean((a[mm] - b[mm]) ** 2)) < 0.02 * np.sqrt(np.mean(a[mm] ** 2))


def test_user_errors_name_the_channel():
    rec = make_recording(30, 26, "constant", length_m=200)
    bad_pos = NS(time_s=rec.position.time_s, data=rec.position.data[:, :1],
                 channels=("position_m",), sample_rate_hz=100.0)
    with pytest.raises(UserError, match="speed_mps"):
        InertialProfiler().fit(rec.accel, rec.gap, bad_pos, rec.magnet_offsets_m)
    with pytest.raises(UserError, match="M9A"):
        InertialProfiler().fit(rec.accel, rec.gap, rec.position, rec.magnet_offsets_m,
                               channel_pairs={1: ("M9A", "M1G")})


def test_magnets_are_blended_where_their_coverage_changes():
    """Two magnets whose profiles differ by a constant c (a long-wave error of one of them), the
    second starting 20 m later: the plain mean jumps by c / 2 where it starts; the blended mean must
    go from the first magnet to the mean of both smoothly: its error is c w / (1 + w) with w the
    second magnet's raised-cosine weight over ``ramp`` bins, so no step exceeds c * pi / (2 ramp)
    (w' <= pi / (2 ramp)), and it is the first magnet alone before and the mean of both after the ramp."""
    from maglev_ros.irregularity.profile import _coverage_weights
    n, start, ramp, c = 3000, 1000, 400, 4e-4
    rail = 1e-3 * np.sin(np.arange(n) / 150.0)
    P = np.vstack([rail, rail + c])
    P[1, :start] = np.nan
    W = _coverage_weights(np.isfinite(P), ramp)
    mean = np.sum(W * np.nan_to_num(P), axis=0) / np.sum(W, axis=0)
    err = mean - rail
    assert np.max(np.abs(np.diff(err))) <= c * np.pi / (2 * ramp) * 1.01
    assert np.allclose(err[:start], 0.0, atol=1e-15)                 # the first magnet alone
    assert np.allclose(err[start + ramp:n - ramp], c / 2, rtol=1e-12)  # both, equally weighted
    # the plain mean's step, for contrast
    plain = np.nanmean(P, axis=0) - rail
    assert abs(plain[start] - plain[start - 1]) == pytest.approx(c / 2)
