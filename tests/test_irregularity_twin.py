"""Irregularity for the twin (irregularity.twin_input) on coupled-twin recordings.

Recordings: ``maglev_ros.twin.simulate.run_scenario`` (coupled vehicle/guideway twin at an internal
rate of 2 kHz, causal 8th-order Butterworth anti-alias at 400 Hz, decimated to 1 kHz), magnets 1, 2
(front frame) and 7, 8 (rear frame), accelerometers with 0.02 m/s^2 white + 0.01 m/s^2 1/f noise
and a constant bias of 0.01-0.05 m/s^2 per channel, gap sensors with 5 um white noise.

Independent references: the HIDDEN true irregularity of the pass (the simulator's profile), the
TRUE twin parameters of the pass (scenario truth), the biases we put into the accelerometers, and
the anti-alias filter's low-frequency group delay computed from its data-sheet description with
scipy (the sensor latency a user would take from the acquisition system).

Targets (issue 5): inside the stated band correlation >= 0.95 and RMS error <= 10 % of the
band-limited true RMS (truth filtered by the band filter the result states); the twin (true
parameters) driven by the reconstructed profile reproduces the measured magnet accelerations
with NRMSE <= 0.2 in the band the result states (accel_nrmse: zero-phase Butterworth band-pass
highpass_hz .. v_max / min_wavelength on both signals, whole vehicle over the valid profile and on
the line).
"""
from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from scipy import signal
from types import SimpleNamespace as NS

from maglev_ros.contract import metadata_from_dict
from maglev_ros.errors import UserError
from maglev_ros.irregularity.twin_input import (accel_nrmse, profile_for_twin,
                                                simulate_recorded_pass)
from maglev_ros.twin.simulate import load_scenario, run_scenario

SPAN_M = 12.384
MAGNETS = (1, 2, 7, 8)
FS_HZ = 1000.0
OVERSAMPLE = 2
AA_ORDER, AA_FRAC = 8, 0.4


def _scenario(kmh: float, seed: int, biases, pass_m: float, speed_profile=None) -> dict:
    v = kmh / 3.6
    lead_m = 25.0 + 4 * SPAN_M            # front magnet starts 25 m before the 5-span line
    tail_m = pass_m - (25.0 + 5 * SPAN_M + 20.124)
    sc = {"kind": "pass", "seed": seed,
          "line": {"n_spans": 5, "span_length_m": SPAN_M, "instrumented_span": "S5"},
          "guideway_sensors": {"sections": 1, "sides": ["left"]},
          "vehicle_sensors": {"magnets": list(MAGNETS)},
          "speed_mps": v, "lead_in_s": lead_m / v, "free_decay_s": max(tail_m, 1.0) / v,
          "rates": {"guideway_hz": FS_HZ, "vehicle_hz": FS_HZ, "position_hz": 100,
                    "oversample": OVERSAMPLE},
          "irregularity": {"components": [
              {"psd": "maglev_001", "band_m": [1.0, 20.0], "scale": 1.0},
              {"psd": "maglev_001", "band_m": [0.25, 1.0], "scale": 400.0}], "spacing_m": 0.02},
          "instrument": {
              "anti_alias": {"kind": "butterworth", "order": AA_ORDER, "cutoff_frac": AA_FRAC},
              "vehicle_accel": {"noise_rms": 0.02, "pink_rms": 0.01,
                                "channels": {f"M{m}A": {"offset": b} for m, b in zip(MAGNETS, biases)}},
              "vehicle_gap": {"noise_rms": 5e-6}},
          # nominal design (metadata) differs from the truth the simulator uses
          "design": {"levitation": {"kp_a_per_m": 6500.0, "kv_a_s_per_m": 35.0, "ka_a_s2_per_m": 0.25},
                     "guideway": {"youngs_modulus_pa": 3.9e10}},
          "truth": {"levitation": {"kp_a_per_m": 7095.21, "kv_a_s_per_m": 40.0, "ka_a_s2_per_m": 0.22},
                    "guideway": {"youngs_modulus_pa": 4.379e10}}}
    if speed_profile is not None:
        sc["speed_profile"] = speed_profile
    return sc


def _aa_delay_s() -> float:
    """Low-frequency group delay of the stated anti-alias filter (run at the internal rate)."""
    fs_int = OVERSAMPLE * FS_HZ
    sos = signal.butter(AA_ORDER, AA_FRAC * FS_HZ, fs=fs_int, output="sos")
    _, gd = signal.group_delay(signal.sos2tf(sos), w=[1.0], fs=fs_int)
    return float(gd[0] / fs_int)


def _cd(stream):
    n = stream["data"].shape[0]
    return NS(time_s=(stream["first_index"] + np.arange(n)) / stream["rate_hz"],
              data=np.asarray(stream["data"]), channels=tuple(stream["channels"]),
              sample_rate_hz=stream["rate_hz"])


UNEVEN = [[0.0, 20 / 3.6], [8.0, 20 / 3.6], [16.0, 38 / 3.6], [40.0, 38 / 3.6]]
CASES = {  # case: km/h (nominal), seed, accelerometer biases (M1, M2, M7, M8) [m/s^2],
    #          pass length [m] (constant speed), speed profile [[t_s, v_mps], ...] or None
    "15kmh": (15, 31, (0.03, -0.02, 0.01, 0.05), 120.0, None),
    "25kmh": (25, 32, (-0.04, 0.01, 0.03, -0.02), 140.0, None),
    "40kmh": (40, 33, (0.02, 0.05, -0.03, 0.01), 180.0, None),
    "20-38kmh": (30, 34, (0.01, -0.03, 0.04, -0.05), 0.0, UNEVEN),   # accelerating on the line
}


@functools.lru_cache(maxsize=None)
def _case(name: str) -> dict:
    kmh, seed, biases, pass_m, prof = CASES[name]
    raw = _scenario(kmh, seed, biases, pass_m, prof)
    if prof is not None:                 # 9 s at 20 km/h before the line, 2 s after
        raw.update(lead_in_s=9.0, free_decay_s=2.0)
    sc = load_scenario(raw)
    rec = run_scenario(sc)
    s = rec.streams
    accel, gap, pos = (_cd(s[f"/testline/vehicle/{k}"]) for k in ("accel", "gap", "position"))
    md = metadata_from_dict(rec.metadata, "sim")
    cfg = sc.truth_config()                       # TRUE parameters of the pass
    spans = sc.truth_span_specs(cfg)
    tau = _aa_delay_s()
    ti = profile_for_twin(accel, gap, pos, md, cfg, spans, sensor_delay_s=tau)
    pred, drift, _ = simulate_recorded_pass(cfg, spans, pos, ti.as_twin_input(), accel.time_s,
                                            sensor_delay_s=tau)
    pairs = {m: (f"M{m}A", f"M{m}G") for m in MAGNETS}
    nr = accel_nrmse(accel, pred, ti, cfg, spans, channel_pairs=pairs)
    return dict(kmh=kmh, uneven=prof is not None, sc=sc, rec=rec, accel=accel, gap=gap, pos=pos,
                md=md, cfg=cfg, spans=spans, tau=tau, ti=ti, pred=pred, drift=drift, nrmse=nr,
                biases=biases, pairs=pairs)


def _score(c) -> tuple[float, float, float]:
    ti = c["ti"]
    res = ti.result
    xt, rt = c["rec"].irregularity
    bf = res.band_filter()
    assert bf["order"] == 4 and bf["type"] == "butterworth_bandpass_zero_phase"
    sos = signal.butter(bf["order"], [bf["low_cut_cycles_per_m"], bf["high_cut_cycles_per_m"]],
                        btype="band", fs=1.0 / res.spacing_m, output="sos")
    truth = np.interp(res.position_m, xt, rt)
    truth = signal.sosfiltfilt(sos, truth - truth.mean())
    m = res.valid
    est, tr = res.irregularity_m[m], truth[m]
    corr = float(np.corrcoef(est, tr)[0, 1])
    rel = float(np.sqrt(np.mean((est - tr) ** 2)) / np.sqrt(np.mean(tr ** 2)))
    return corr, rel, float(np.sqrt(np.mean(tr ** 2)))


@pytest.mark.parametrize("name", list(CASES))
def test_unloaded_profile_matches_hidden_truth_in_stated_band(name):
    c = _case(name)
    ti = c["ti"]
    corr, rel, rms = _score(c)
    print(f"\n[{name}] band {ti.min_wavelength_m:.3g}-{ti.max_wavelength_m:.3g} m, "
          f"corr {corr:.4f}, rms error {rel:.3f} of true band rms {rms * 1e3:.3f} mm, "
          f"iterations {ti.iterations} {['%.4f' % h for h in ti.change_history]}")
    assert corr >= 0.95 and rel <= 0.10, (corr, rel)
    # band stated: long end from speed and corner, short end from sampling/grid (point magnets)
    spd = c["pos"].data[:, 1]
    v_band = 20 / 3.6 if c["uneven"] else c["kmh"] / 3.6   # slowest speed (5th percentile)
    assert ti.max_wavelength_m == pytest.approx(v_band / (2 * ti.highpass_hz), rel=0.02)
    # the grid follows the data: one sample step at the top speed (two magnets), at most 2 cm
    assert ti.spacing_m == pytest.approx(min(0.02, spd.max() / FS_HZ), rel=1e-6)
    assert ti.min_wavelength_m == pytest.approx(max(4 * ti.spacing_m, 4 * spd.max() / FS_HZ), rel=0.02)
    assert ti.min_wavelength_m < 0.25            # keeps the short waves that drive the magnets
    # the loaded -> unloaded iteration converged and removed a real girder deflection
    assert ti.converged and 1 <= ti.iterations <= 4
    assert ti.change_history[-1] < 0.01
    assert ti.deflection_rms_m > 2e-5           # girder deflection under the magnets ~0.1 mm
    assert ti.result.kind == "unloaded"
    # the bias of every accelerometer is detected and reported, close to what we put in
    found = {w.channel: w.value for w in ti.warnings if w.kind == "accel_bias"}
    for m, b in zip(MAGNETS, c["biases"]):
        assert abs(found[f"M{m}A"] - b) < 0.01, (m, found)
    # front and rear magnets agree once the deflection is removed
    assert min(cc for _, _, cc in ti.result.agreement) > 0.98


@pytest.mark.parametrize("name", list(CASES))
def test_twin_driven_by_profile_reproduces_magnet_accelerations(name):
    c = _case(name)
    nr = c["nrmse"]
    print(f"\n[{name}] magnet accel NRMSE {nr['nrmse']:.3f} "
          f"({', '.join(f'{k} {v:.3f}' for k, v in nr['per_channel'].items())}) in "
          f"{nr['band_hz'][0]:.2g}-{nr['band_hz'][1]:.3g} Hz over {nr['window_s']:.1f} s")
    # the twin follows the measured position (exactly at constant speed; within mm when the
    # speed changes: the speed channel is interpolated between position samples)
    assert c["drift"] < (5e-3 if c["uneven"] else 1e-6), c["drift"]
    # prediction sits exactly on the recorded accel samples (delay accounted for)
    assert np.allclose(c["pred"].time_s, c["accel"].time_s, atol=1e-9)
    assert nr["nrmse"] <= 0.2, nr
    assert max(nr["per_channel"].values()) <= 0.25, nr
    assert nr["window_s"] > 4.0
    v_max = c["pos"].data[:, 1].max()
    assert nr["band_hz"][1] <= v_max / c["ti"].min_wavelength_m * 1.001


def test_outside_band_and_outside_record_the_result_says_so():
    c = _case("25kmh")
    ti = c["ti"]
    d = ti.to_dict()
    json.dumps(ti.to_dict(include_profile=True), allow_nan=False)     # JSON-ready
    assert d["band"]["max_wavelength_m"] == ti.max_wavelength_m and d["kind"] == "unloaded"
    assert "outside the band" in d["band"]["note"]
    # outside the valid stretch the twin input is exactly zero and flagged invalid
    lo, hi = ti.valid_range_m
    out = (ti.position_m < lo) | (ti.position_m > hi)
    assert out.any() and np.all(ti.irregularity_m[out] == 0.0) and not ti.valid[out].any()
    # the valid stretch ends where the recording's edges (1.5 / f_c) and the trim put it
    x_rec = c["pos"].data[:, 0]
    assert lo > x_rec[0] - 20.124 and hi < x_rec[-1]
    # waves longer than the band are removed, not returned as drift: the result holds < 15 %
    # of the true RMS at 2-6 x max_wavelength
    res = ti.result
    xt, rt = c["rec"].irregularity
    lam = res.max_wavelength_m
    sos = signal.butter(4, [1 / (6 * lam), 1 / (2 * lam)], btype="band", fs=1 / res.spacing_m,
                        output="sos")
    m = res.valid
    tr = np.interp(res.position_m, xt, rt)
    long_true = signal.sosfiltfilt(sos, tr - tr.mean())[m]
    long_est = signal.sosfiltfilt(sos, np.where(m, res.irregularity_m, 0.0))[m]
    assert np.std(long_est) < 0.15 * np.std(long_true), (np.std(long_est), np.std(long_true))


def test_deflection_removal_beats_the_loaded_profile():
    """The twin adds its own girder deflection: fed with the LOADED profile it counts it twice."""
    c = _case("40kmh")
    loaded = profile_for_twin(c["accel"], c["gap"], c["pos"], c["md"], c["cfg"], c["spans"],
                              sensor_delay_s=c["tau"], max_iterations=0)
    assert any(w.kind == "band" and "loaded" in w.message for w in loaded.warnings)
    pred, _, _ = simulate_recorded_pass(c["cfg"], c["spans"], c["pos"], loaded.as_twin_input(),
                                        c["accel"].time_s, sensor_delay_s=c["tau"])
    nr_loaded = accel_nrmse(c["accel"], pred, c["ti"], c["cfg"], c["spans"],
                            channel_pairs=c["pairs"], band_hz=c["nrmse"]["band_hz"])
    print(f"\n[40 km/h] NRMSE loaded {nr_loaded['nrmse']:.3f} vs unloaded {c['nrmse']['nrmse']:.3f}")
    assert c["nrmse"]["nrmse"] < 0.7 * nr_loaded["nrmse"]


def test_user_errors():
    c = _case("40kmh")
    with pytest.raises(UserError, match="highpass_hz"):
        profile_for_twin(c["accel"], c["gap"], c["pos"], c["md"], c["cfg"], c["spans"],
                         highpass_hz=0.0)
    with pytest.raises(UserError, match="metadata_or_offsets"):
        profile_for_twin(c["accel"], c["gap"], c["pos"], 3.0, c["cfg"], c["spans"])
    bad = NS(time_s=c["pos"].time_s, data=c["pos"].data[:, :1], channels=("position_m",))
    with pytest.raises(UserError, match="speed_mps"):
        simulate_recorded_pass(c["cfg"], c["spans"], bad, None, c["accel"].time_s)


def test_the_twin_reads_the_denoised_input_on_a_grid_no_coarser_than_its_step():
    """A wave of 4.5 grid steps sampled, tapered to 0 at both ends, the twin travelling a quarter
    step per time step: read by the twin (linear interpolation, central-difference slope:
    coupling.Irregularity) from the coarse samples it loses over a quarter of its slope against the
    analytic wave; from ``fine_twin_input``'s grid (the twin's travel per step) within 1.5 % and 3 %."""
    from maglev_ros.irregularity.twin_input import fine_twin_input
    from maglev_ros.twin.coupling import Irregularity
    dx, lam = 0.01, 0.045
    x = np.arange(4000) * dx
    env = np.sin(np.pi * x / x[-1]) ** 2                 # slow taper: the wave stays band-limited
    r = 1e-4 * env * np.sin(2 * np.pi * x / lam)
    xf, rf = fine_twin_input(x, r, dx / 4)
    assert xf[1] - xf[0] == pytest.approx(dx / 4) and xf[0] == x[0]
    q = np.linspace(10.0, 30.0, 20001)                   # the middle, where the envelope is ~1
    true_r = 1e-4 * np.interp(q, x, env) * np.sin(2 * np.pi * q / lam)
    true_s = 1e-4 * np.interp(q, x, env) * (2 * np.pi / lam) * np.cos(2 * np.pi * q / lam)

    def amp(y):                                          # fitted amplitude at the wave's frequency
        b = np.column_stack([np.sin(2 * np.pi * q / lam), np.cos(2 * np.pi * q / lam)])
        return float(np.hypot(*np.linalg.lstsq(b, y, rcond=None)[0]))
    coarse, fine = Irregularity.from_samples(x, r), Irregularity.from_samples(xf, rf)
    assert amp(coarse.slope(q)) < 0.75 * amp(true_s)     # what the coarse grid did
    assert amp(fine.elevation(q)) == pytest.approx(amp(true_r), rel=0.015)
    assert amp(fine.slope(q)) == pytest.approx(amp(true_s), rel=0.03)
    for step in (dx, 0.97 * dx, 2 * dx, 0.0):              # the grid is the step or finer, or no step known
        assert np.array_equal(fine_twin_input(x, r, step)[0], x)


def test_a_slow_sampled_pass_keeps_the_short_waves_that_drive_the_magnets():
    """Two magnets at rest over a rail of three short waves (4.5-7.5 samples per wave at 10 m/s and
    250 Hz, 0.13-0.22 x the rate: inside the 0.7 x Nyquist bands the diagnosis compares), no deflection
    removed: the twin input carries each wave at its analytic amplitude within 2 %. A grid of one
    sample step (binning, and a band cut at 4 samples per wave) kept 94, 87 and 63 % of them."""
    from maglev_ros.irregularity.twin_input import upsample_factor, upsampled
    from maglev_ros.twin.design import twin_config
    fs, v, g0 = 250.0, 10.0, 0.010
    offsets = (0.0, 3.0)
    waves_m, amp_m = (0.30, 0.23, 0.18), 5e-5
    t = np.arange(int(14.0 * fs)) / fs
    x_ref = 5.0 + v * t
    rng = np.random.default_rng(7)

    def rail(x):
        return sum(amp_m * np.sin(2 * np.pi * x / lam + k) for k, lam in enumerate(waves_m))
    acc = NS(time_s=t, data=0.005 * rng.standard_normal((t.size, 2)), channels=("M1A", "M2A"), sample_rate_hz=fs)
    gap = NS(time_s=t, data=np.column_stack([g0 + rail(x_ref + o) + 2e-6 * rng.standard_normal(t.size)
                                             for o in offsets]), channels=("M1G", "M2G"), sample_rate_hz=fs)
    tp = np.arange(int(14.0 * 100)) / 100.0
    pos = NS(time_s=tp, data=np.column_stack([5.0 + v * tp, np.full(tp.size, v)]),
             channels=("position_m", "speed_mps"), sample_rate_hz=100.0)
    cfg = twin_config(None)
    assert upsample_factor(acc, pos, v * cfg.numerics.dt_max_s) == round(1.0 / fs / cfg.numerics.dt_max_s)
    ti = profile_for_twin(acc, gap, pos, list(offsets), cfg, None, max_iterations=0, highpass_hz=0.5,
                          channel_pairs={1: ("M1A", "M1G"), 2: ("M2A", "M2G")})
    x, r, _ = ti.denoised_twin_input()
    lo, hi = ti.valid_range_m
    mid = (x > lo + 5.0) & (x < hi - 5.0)
    for lam in waves_m:
        b = np.column_stack([np.sin(2 * np.pi * x[mid] / lam), np.cos(2 * np.pi * x[mid] / lam)])
        got = float(np.hypot(*np.linalg.lstsq(b, r[mid], rcond=None)[0]))
        assert got == pytest.approx(amp_m, rel=0.02), lam
    # the upsampler itself: a sine at 0.35 x the rate against its analytic values, NaN runs kept
    y = np.sin(2 * np.pi * 0.35 * fs * t)
    y[100:110] = np.nan
    up = upsampled(NS(time_s=t, data=y, channels=("a",), sample_rate_hz=fs), 4)
    assert up.sample_rate_hz == 4 * fs and up.data.size == (t.size - 1) * 4 + 1
    assert np.all(np.isnan(up.data[400:437]))
    inner = (up.time_s > 1.0) & (up.time_s < 13.0) & ~((up.time_s > 0.38) & (up.time_s < 0.46))
    err = up.data[inner] - np.sin(2 * np.pi * 0.35 * fs * up.time_s[inner])
    assert np.sqrt(np.mean(err ** 2)) < 0.02 * np.sqrt(0.5)
