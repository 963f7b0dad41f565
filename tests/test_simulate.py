"""maglev-ros simulate: scenario -> contract bag, instrument chain, truth sidecars, paper plausibility.

References are independent of the simulator: the contract, configured noise levels (sample
statistics), the analytic Butterworth magnitude, the paper's measured values (000: 23.49 Hz,
0.437 mm, 5.35 m/s^2) and the FE model's eigenfrequencies (Guideway.modes()).
"""
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from maglev_ros.bag_reader import BagReader
from maglev_ros.errors import UserError
from maglev_ros.twin.design import line_spans, twin_config
from maglev_ros.twin.guideway import Guideway
from maglev_ros.twin.sensors import AntiAlias, InstrumentChain, NoiseSpec
from maglev_ros.twin.simulate import load_scenario, simulate, truth_paths

ROOT = Path(__file__).resolve().parents[1]
GA, GD, VA, VG, VP = ("/testline/guideway/accel", "/testline/guideway/displacement",
                      "/testline/vehicle/accel", "/testline/vehicle/gap", "/testline/vehicle/position")

NOMINAL = {"guideway": {"youngs_modulus_pa": 3.7e10, "density_kg_m3": 2500.0,
                        "bearing_stiffness_n_per_m": 2.9e10},
           "levitation": {"kp_a_per_m": 6400.0}}
TRUTH = {"guideway": {"youngs_modulus_pa": 4.4e10, "density_kg_m3": 2550.0},
         "levitation": {"kp_a_per_m": 7100.0},
         "spans": {"S2": {"bearing_stiffness_n_per_m": 1.5e10}}}


def small_pass(seed=3, **over):
    sc = {
        "kind": "pass", "seed": seed, "line": {"n_spans": 3, "span_length_m": 12.384, "instrumented_span": "S2"},
        "guideway_sensors": {"sections": 3, "sides": ["left", "right"]},
        "vehicle_sensors": {"magnets": [1, 8]}, "speed_mps": 20.0, "lead_in_s": 1.0, "free_decay_s": 0.5,
        "rates": {"guideway_hz": 1000, "vehicle_hz": 1000, "position_hz": 100, "oversample": 2},
        "instrument": {"guideway_accel": {"noise_rms": 3e-3}, "guideway_displacement": {"noise_rms": 1e-6},
                       "vehicle_accel": {"noise_rms": 0.01}, "vehicle_gap": {"noise_rms": 4e-6}},
        "design": NOMINAL, "truth": TRUTH,
    }
    sc.update(over)
    return sc


@pytest.fixture(scope="module")
def pass_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "pass"
    res = simulate(small_pass(), out)
    return out, res


def test_pass_bag_follows_contract_channels_units_rates(pass_bag):
    out, res = pass_bag
    with BagReader(out) as r:
        issues = r.check()
        assert issues == [], [str(i) for i in issues]          # contract check clean (no warnings either)
        md = r.metadata
        assert md.run_kind == "pass" and md.nominal_speed_mps == 20.0
        assert [s.id for s in md.spans] == ["S1", "S2", "S3"]
        want = {GA: (["G1LV", "G1RV", "G2LV", "G2RV", "G3LV", "G3RV"], "m/s^2", 1000.0),
                GD: (["G2D"], "m", 1000.0), VA: (["M1A", "M8A"], "m/s^2", 1000.0),
                VG: (["M1G", "M8G"], "m", 1000.0), VP: (["position_m", "speed_mps"], None, 100.0)}
        for topic, (chans, unit, rate) in want.items():
            cd = r.read_topic(topic)
            assert list(cd.channels) == chans
            assert cd.sample_rate_hz == rate
            if unit:
                assert set(cd.units) == {unit}
            assert list(md.sensors_on_topic(topic)) == chans
        # sensor geometry: sections at 1/4, 1/2, 3/4 of S2, both sides
        s = md.sensors
        assert s["G2LV"].position_m == pytest.approx(12.384 * 1.5) and s["G2RV"].side == "right"
        assert s["G2LV"].span == "S2" and s["G1LV"].position_m == pytest.approx(12.384 * 1.25)
        pos = r.read_topic(VP)
        v = pos.channel("speed_mps")
        assert np.allclose(v, 20.0)
        # position advances at the speed over the stream time (header stamps are the truth)
        dx = np.diff(pos.channel("position_m").astype(float))
        assert np.allclose(dx, 20.0 / 100.0, atol=2e-5)
        # gaps around the nominal 10 mm (contract: absolute gap)
        gap = r.read_topic(VG).data
        assert np.all(np.abs(gap - 0.010) < 1e-3)
        # all topics start at the same instant
        starts = {t: r.read_topic(t).time_s[0] for t in want}
        assert max(starts.values()) - min(starts.values()) < 1e-9


def test_metadata_holds_nominal_design_truth_only_in_sidecars(pass_bag):
    out, _ = pass_bag
    with BagReader(out) as r:
        md = r.metadata
        raw = json.dumps(md.raw)
    assert md.design == NOMINAL
    for secret in ("4.4e+10", "44000000000", "7100", "1.5e+10", "15000000000", "2550"):
        assert secret not in raw
    tj, ic = truth_paths(out)
    truth = json.loads(tj.read_text())
    assert truth["truth_design"]["guideway"]["youngs_modulus_pa"] == 4.4e10
    assert truth["truth_design"]["guideway"]["bearing_stiffness_n_per_m"] == 2.9e10   # nominal kept
    assert truth["truth_design"]["levitation"]["kp_a_per_m"] == 7100.0
    s2 = [s for s in truth["truth_spans"] if s["span_id"] == "S2"][0]
    assert s2["props"]["bearing_stiffness_n_per_m"] == 1.5e10
    # true modes of the instrumented span = FE eigenvalues of the truth (independent recomputation)
    cfg = twin_config(truth["truth_design"])
    spans = line_spans({"spans": [{"id": "S2", "start_m": 12.384, "length_m": 12.384,
                                   "bearing_stiffness_n_per_m": 1.5e10}]}, cfg)
    f = Guideway(spans).frequencies_hz(0, 2)
    assert truth["instrumented_span"]["freq_hz"][:2] == pytest.approx(f, rel=1e-9)
    arr = np.genfromtxt(ic, delimiter=",", names=True)
    assert arr["position_m"][0] < -20.0 and np.std(arr["elevation_m"]) > 1e-5


def test_noise_level_as_configured_in_the_quiet_lead_in(pass_bag):
    out, _ = pass_bag
    with BagReader(out) as r:
        ga = r.read_topic(GA)
        gd = r.read_topic(GD)
    t = ga.time_s - ga.time_s[0]
    quiet = t < 0.9          # the vehicle enters the instrumented span at 1.0 s: girder S2 at rest
    for cd, sigma in ((ga, 3e-3), (gd, 1e-6)):
        x = cd.data[quiet]
        est = np.std(x, axis=0)
        n = x.shape[0]
        # sample std of white noise: relative standard error 1/sqrt(2n) per channel
        assert np.all(np.abs(est / sigma - 1) < 5 / math.sqrt(2 * n)), est
        assert abs(np.mean(x)) < 5 * sigma / math.sqrt(x.size)
    # left and right see the same vertical bending once the girder moves (vertical-only model)
    loaded = t > 1.2
    l, rr = ga.channel("G2LV")[loaded], ga.channel("G2RV")[loaded]
    assert np.std(l - rr) == pytest.approx(math.sqrt(2) * 3e-3, rel=0.15)
    assert np.std(l) > 10 * 3e-3


def test_anti_alias_filter_blocks_tone_above_nyquist():
    fs_out, over = 2000.0, 4
    fs_int = fs_out * over
    n = int(fs_int * 4)
    t = np.arange(n) / fs_int
    f_hi, f_lo = 1700.0, 100.0         # 1700 Hz aliases to 300 Hz at 2 kHz
    x = np.column_stack([np.sin(2 * np.pi * f_hi * t), np.sin(2 * np.pi * f_lo * t)])

    def amp(y, f):
        y = y[len(y) // 2:]
        tt = np.arange(len(y)) / fs_out
        return 2 * abs(np.mean(y * np.exp(-2j * np.pi * f * tt)))

    ch = InstrumentChain(["hi", "lo"], fs_out, over, AntiAlias("butterworth", 8, 0.4), NoiseSpec())
    y = ch.process(x)
    assert y.shape == (n // over, 2)
    def butter_mag(f):   # analytic magnitude of the bilinear-transformed 8th-order Butterworth
        r = math.tan(math.pi * f / fs_int) / math.tan(math.pi * 0.4 * fs_out / fs_int)
        return 1 / math.sqrt(1 + r ** 16)

    alias = amp(y[:, 0], fs_out - f_hi)
    assert alias < 1e-3 and alias == pytest.approx(butter_mag(f_hi), rel=0.05)   # > 60 dB down
    assert amp(y[:, 1], f_lo) == pytest.approx(butter_mag(f_lo), rel=2e-3)
    # without the filter the same tone folds into the band at full amplitude (the test is sensitive)
    raw = InstrumentChain(["hi"], fs_out, over, AntiAlias("none"), NoiseSpec()).process(x[:, :1])
    assert amp(raw[:, 0], fs_out - f_hi) > 0.99
    # Bessel option (linear phase, gentle roll-off): > 20 dB down at 0.85 fs with the same corner
    yb = InstrumentChain(["hi"], fs_out, over, AntiAlias("bessel", 8, 0.4), NoiseSpec()).process(x[:, :1])
    assert 1e-3 < amp(yb[:, 0], fs_out - f_hi) < 0.1


def test_chain_streams_in_chunks_and_noise_spectra():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((40_000, 2)) + 0.01
    a = InstrumentChain(["a", "b"], 1000.0, 4, noise=NoiseSpec(gain=1.02, offset=0.5)).process(x)
    c = InstrumentChain(["a", "b"], 1000.0, 4, noise=NoiseSpec(gain=1.02, offset=0.5))
    b = np.concatenate([c.process(x[i:i + 3333]) for i in range(0, len(x), 3333)])
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    # white + 1/f noise: total RMS and a -1 log-log slope of the 1/f part
    ch = InstrumentChain(["n"], 1000.0, 1, AntiAlias("none"), NoiseSpec(pink_rms=0.2, pink_min_hz=0.05), rng=5)
    y = ch.process(np.zeros((400_000, 1)))[:, 0]
    assert np.std(y) == pytest.approx(0.2, rel=0.15)
    f, p = signal.welch(y, fs=1000.0, nperseg=2 ** 15)
    sel = (f > 1) & (f < 100)
    slope = np.polyfit(np.log(f[sel]), np.log(p[sel]), 1)[0]
    assert slope == pytest.approx(-1.0, abs=0.15)


@pytest.mark.parametrize("seed", [1, 2])
def test_paper_scenario_matches_the_papers_measured_values(tmp_path, seed):
    sets = ["lead_in_s=0.5", "free_decay_s=0.3", "rates.guideway_hz=1000", "rates.vehicle_hz=1000",
            "rates.oversample=2", "guideway_sensors.sides=[left]"]
    res = simulate("paper", tmp_path / "p", sets=sets, seed=seed)
    truth = json.loads(Path(res.truth_json).read_text())
    # FE first vertical mode of the simulated (true) span vs the paper's 23.49 Hz
    cfg = twin_config(truth["truth_design"])
    f1 = Guideway(line_spans({"spans": [{"id": "S3", "start_m": 0.0, "length_m": 12.384}]}, cfg)).frequencies_hz(0, 1)[0]
    assert f1 == pytest.approx(23.5, abs=0.7)
    with BagReader(res.bag) as r:
        assert [i for i in r.check() if i.severity == "error"] == []
        disp = r.read_topic(GD).channel("G3D")
        acc = r.read_topic(VA).data
    assert 0.3e-3 < np.max(np.abs(disp)) < 0.6e-3          # 000: 0.437 mm measured
    assert np.min(disp) < -0.3e-3                           # the girder deflects downward (contract)
    assert 2.0 < np.max(np.abs(acc)) < 8.0                  # 000: 5.35 m/s^2 measured


def test_ambient_spectrum_peaks_at_fe_frequencies(tmp_path):
    res = simulate("paper-ambient", tmp_path / "amb", sets=["duration_s=60"], seed=5)
    truth = json.loads(Path(res.truth_json).read_text())
    cfg = twin_config(truth["truth_design"])
    with BagReader(res.bag) as r:
        assert r.check() == []
        assert set(r.sensor_topics) == {GA} and r.metadata.run_kind == "ambient"
        cd = r.read_topic(GA)
    fe = Guideway(line_spans({"spans": [{"id": "S3", "start_m": 0.0, "length_m": 12.384}]}, cfg)).modes()
    f_fe = fe.freq_hz[:2]
    fs = cd.sample_rate_hz
    assert cd.time_s[-1] - cd.time_s[0] == pytest.approx(60.0, abs=0.01)
    for ch, f_mode in (("G3LV", f_fe[0]), ("G2LV", f_fe[1])):
        # ~60 averages of 2 s segments; peak by parabolic interpolation of the log-PSD
        f, p = signal.welch(cd.channel(ch), fs=fs, nperseg=1024)
        band = np.flatnonzero((f > 0.5 * f_mode) & (f < 1.5 * f_mode))
        k = band[np.argmax(p[band])]
        a, b, c = np.log(p[k - 1:k + 2])
        f_peak = f[k] + 0.5 * (a - c) / (a - 2 * b + c) * (f[1] - f[0])
        assert f_peak == pytest.approx(f_mode, rel=0.015)
    # the first-mode peak stands far above the noise floor near 60 Hz
    f, p = signal.welch(cd.channel("G3LV"), fs=fs, nperseg=4096)
    assert p[np.argmin(abs(f - f_fe[0]))] > 100 * np.median(p[(f > 55) & (f < 65)])


def test_effect_and_scenario_errors(tmp_path):
    with pytest.raises(UserError, match="unknown scenario key"):
        load_scenario(small_pass(foo=1) if False else {**small_pass(), "foo": 1})
    with pytest.raises(UserError, match="effects\\[0\\]"):
        load_scenario({**small_pass(), "effects": [{"name": "warp_drive"}]})
    with pytest.raises(UserError, match="rates.oversample"):
        load_scenario("paper", sets=["rates.oversample=0"])
    with pytest.raises(UserError, match="KEY=VALUE"):
        load_scenario("paper", sets=["speed_mps"])
    sc = load_scenario("paper", sets=["truth.guideway.youngs_modulus_pa=4.0e10", "irregularity.components.1.scale=10"])
    assert sc.raw["truth"]["guideway"]["youngs_modulus_pa"] == 4.0e10
    assert sc.raw["irregularity"]["components"][1]["scale"] == 10
    # ambient_excitation effect: the instrumented girder moves during the lead-in
    sc = {**small_pass(), "effects": [{"name": "ambient_excitation", "force_rms_n": 50.0}],
          "instrument": {"guideway_accel": {"noise_rms": 1e-4}}, "free_decay_s": 0.1}
    res = simulate(sc, tmp_path / "eff")
    with BagReader(res.bag) as r:
        ga = r.read_topic(GA)
    quiet = (ga.time_s - ga.time_s[0]) < 0.9
    assert np.std(ga.data[quiet]) > 20 * 1e-4
    assert json.loads(Path(res.truth_json).read_text())["effects"][0]["name"] == "ambient_excitation"


def test_cli_simulate_and_one_line_errors(tmp_path):
    exe = [sys.executable, "-m", "maglev_ros.cli", "simulate"]
    out = tmp_path / "cli"
    p = subprocess.run(exe + ["paper-ambient", "--out", str(out), "--seed", "4", "--set", "duration_s=5"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "ambient" in p.stdout and (tmp_path / "cli.truth.json").is_file()
    assert json.loads((tmp_path / "cli.truth.json").read_text())["seed"] == 4
    p = subprocess.run(exe + ["nosuch", "--out", str(tmp_path / "x")], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert p.returncode == 1 and "no such scenario" in p.stderr and "Traceback" not in p.stderr
    assert p.stderr.count("\n") == 1
    with pytest.raises(UserError, match="already exists"):
        simulate("paper-ambient", out)


def test_sample_bags_are_small_and_clean():
    bags = ROOT / "bags"
    total = sum(f.stat().st_size for f in bags.rglob("*") if f.is_file())
    assert total < 10e6, f"bags/ holds {total / 1e6:.1f} MB"
    for name, limit in (("paper_pass", 8e6), ("paper_pass2", 8e6), ("paper_ambient", 4e6)):
        b = bags / name
        if not b.exists():
            pytest.skip(f"{b} not generated (run bags/make_sample_bags.py)")
        size = sum(f.stat().st_size for f in b.rglob("*") if f.is_file())
        assert size < limit
        with BagReader(b) as r:
            assert [i for i in r.check() if i.severity == "error"] == []
        assert (bags / f"{name}.truth.json").is_file()


def test_speed_profile_drives_the_vehicle(tmp_path):
    prof = [[0.0, 15.0], [2.0, 25.0], [10.0, 25.0]]
    res = simulate(small_pass(speed_profile=prof, free_decay_s=0.2), tmp_path / "prof")
    with BagReader(res.bag) as r:
        pos = r.read_topic(VP)
    t = pos.time_s - (pos.time_s[0] - 1 / 100.0)          # stream time since the simulation start
    v = pos.channel("speed_mps")
    np.testing.assert_allclose(v, np.interp(t, [p[0] for p in prof], [p[1] for p in prof]), rtol=1e-5)
    x = pos.channel("position_m").astype(float)
    # the vehicle covers the integral of the speed profile (trapezoid on the recorded grid)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    np.testing.assert_allclose(x - x[0], dist, atol=2e-3)
