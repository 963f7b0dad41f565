"""The delay of the vehicle sensors behind the position, measured between passes at different speeds
(maglev_ros.irregularity.sensor_delay).

References: a known shift of one synthetic rail (the profile of a pass at speed v is the rail
shifted by v tau), and, through the whole chain, the low-frequency group delay of the causal
anti-alias filter our concealed-effect generator applies (scipy.signal.group_delay), which no
metadata states."""
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from maglev_ros.irregularity.sensor_delay import PassProfile, SensorDelayEstimator

sys.path.insert(0, str(Path(__file__).parent))


def _rail(rng, length_m=300.0, dx=0.02):
    """A band-limited random rail (waves 0.3-30 m), x and r."""
    x = np.arange(0.0, length_m, dx)
    sos = signal.butter(4, [1 / 30.0, 1 / 0.3], btype="band", fs=1 / dx, output="sos")
    return x, 1e-3 * signal.sosfiltfilt(sos, rng.standard_normal(x.size))


def _profile(x, r, v, tau, name, noise, rng, lam_min=0.1):
    """A pass's loaded profile: the rail v*tau further back along the line, plus measurement noise."""
    y = np.interp(x - v * tau, x, r) + noise * rng.standard_normal(x.size)
    return PassProfile(name, v, x, y, lam_min)


@pytest.mark.parametrize("tau", [0.0015, 0.004])
def test_a_known_shift_between_two_speeds_gives_the_delay(tau):
    rng = np.random.default_rng(7)
    x, r = _rail(rng)
    noise = 0.05 * np.std(r)
    est = SensorDelayEstimator()([_profile(x, r, 40.0, tau, "a", noise, rng),
                                  _profile(x, r, 70.0, tau, "b", noise, rng)])
    assert est.applicable, est.reason
    assert est.delay_s == pytest.approx(tau, abs=max(3 * est.std_s, 0.05 * tau))
    assert est.std_s < 0.2 * tau


def test_no_delay_is_not_significant_and_one_pass_says_why():
    rng = np.random.default_rng(8)
    x, r = _rail(rng)
    noise = 0.05 * np.std(r)
    est = SensorDelayEstimator()([_profile(x, r, 40.0, 0.0, "a", noise, rng),
                                  _profile(x, r, 70.0, 0.0, "b", noise, rng)])
    assert not est.significant and not est.applicable and "no delay measurable" in est.reason
    one = SensorDelayEstimator()([_profile(x, r, 40.0, 0.0, "a", noise, rng)])
    assert one.delay_s is None and "two passes" in one.reason
    assert one.to_dict()["delay_s"] is None


def test_a_position_channel_behind_the_sensors_is_reported_not_applied():
    rng = np.random.default_rng(9)
    x, r = _rail(rng)
    est = SensorDelayEstimator()([_profile(x, r, 40.0, -0.003, "a", 0.0, rng),
                                  _profile(x, r, 70.0, -0.003, "b", 0.0, rng)])
    assert est.significant and not est.applicable and "position channel lags" in est.reason


def test_unrelated_rails_are_not_compared():
    rng = np.random.default_rng(10)
    x, r1 = _rail(rng)
    _, r2 = _rail(rng)
    est = SensorDelayEstimator()([PassProfile("a", 40.0, x, r1, 0.1), PassProfile("b", 70.0, x, r2, 0.1)])
    assert not est.applicable


def test_the_generators_causal_anti_alias_filter_is_measured_from_its_passes():
    """A concealed-effect case whose sampled channels went through a causal 6th-order Chebyshev (the
    blind split's instrument): the two passes' rails measure its group delay, stated nowhere."""
    import discrepancy_cases as dc
    from maglev_ros.discrepancy.irregularity import measure_sensor_delay
    variant = dc.VARIANTS["blind"]
    case = dc.make_case("delay", None, {"magnitude": 0.0}, seed=4242, speeds=(30.0, 60.0), split="blind",
                        variant=variant)
    assert "acquisition" not in case.passes[0].metadata
    est = measure_sensor_delay(case.passes)
    kind, corner = variant["aa"]
    assert kind == "cheby"
    # the filter runs at the generator's 1 kHz before the 2x decimation; the band read is 15-120 Hz
    f_hz = np.linspace(15.0, 120.0, 8)
    _, gd = signal.group_delay(signal.cheby1(6, 0.5, corner), w=f_hz, fs=1000.0)
    lo, hi = float(gd.min()) * 1e-3, float(gd.max()) * 1e-3
    assert est.applicable, est.reason
    assert lo - 3 * est.std_s <= est.delay_s <= hi + 3 * est.std_s, (est.delay_s, lo, hi, est.std_s)


def test_update_reads_the_same_delay_from_the_pass_bags(tmp_path):
    """The model updating's evidence (offline ``update`` and the updater node) measures the delay the
    same way from the pass bags, and its rail input then runs that much behind the stamps."""
    import discrepancy_cases as dc
    from maglev_ros.discrepancy.irregularity import measure_sensor_delay
    from maglev_ros.updating.pipeline import _measure_sensor_delay, _signals, read_pass
    case = dc.make_case("delay-bags", None, {"magnitude": 0.0}, seed=4243, speeds=(30.0, 60.0), split="blind",
                        variant=dc.VARIANTS["blind"])
    _, paths = dc.write_case_bags(case, tmp_path)
    recs = [read_pass(p) for p in paths]
    said = []
    _measure_sensor_delay(recs, 0.8, said.append)
    ref = measure_sensor_delay(case.passes)
    assert ref.applicable
    for r in recs:
        assert r.info["sensor_delay"]["applied"]
        assert r.info["sensor_delay_s"] == pytest.approx(ref.delay_s, abs=2 * ref.std_s)
        assert _signals(r)[2] == r.info["sensor_delay_s"]
    assert any("behind the position" in s for s in said)


def test_a_stated_delay_wins_over_the_measured_one():
    """With ``acquisition.<topic>.delay_s`` in the metadata nothing is measured (the diagnosis'
    calibrate stage) and the twin runs the stated delay behind the stamps."""
    from dataclasses import replace
    import discrepancy_cases as dc
    from maglev_ros.discrepancy.diagnose import DiagnoseConfig
    from maglev_ros.discrepancy.irregularity import pass_sensor_delay_s
    from maglev_ros.discrepancy.pipeline.calibrate import _with_measured_delay
    case = dc.make_case("delay-stated", None, {"magnitude": 0.0}, seed=4244, speeds=(30.0, 60.0), split="blind",
                        variant=dc.VARIANTS["blind"])
    measured, d = _with_measured_delay(list(case.passes), DiagnoseConfig())
    assert d["applied"] and all(p.sensor_delay_s == d["delay_s"] for p in measured)
    acq = {"/testline/vehicle/accel": {"delay_s": 0.005}, "/testline/vehicle/position": {"delay_s": 0.001}}
    stated = [replace(p, metadata={**p.metadata, "acquisition": acq}) for p in case.passes]
    same, none = _with_measured_delay(stated, DiagnoseConfig())
    assert none is None and same == stated
    assert pass_sensor_delay_s(replace(stated[0], sensor_delay_s=0.003)) == pytest.approx(0.004)


def test_irregularity_with_a_reference_pass_places_the_rail_where_it_is(tmp_path, monkeypatch, capsys):
    """``maglev-ros irregularity PASS --reference-pass PASS2``: the delay the two passes measure is
    applied, and the profile then matches the generator's true rail better (its 1-6 m waves: the
    shift v x delay of an unstated 3 ms filter at 60 m/s is 18 cm)."""
    import json
    import discrepancy_cases as dc
    from maglev_ros.cli import main
    rail = {}
    orig = dc.guideway_profile

    def keep(*a, **k):
        x, r, info = orig(*a, **k)
        rail["x"], rail["r"] = x, r
        return x, r, info
    monkeypatch.setattr(dc, "guideway_profile", keep)
    case = dc.make_case("delay-cli", None, {"magnitude": 0.0}, seed=4245, speeds=(30.0, 60.0), split="blind",
                        variant=dc.VARIANTS["blind"])
    _, (slow, fast) = dc.write_case_bags(case, tmp_path / "bags")

    def corr(csv):
        rows = [ln.split(",") for ln in csv.read_text().splitlines()
                if ln and not ln.startswith("#") and not ln.startswith("position_m")]
        x = np.array([float(a) for a, _ in rows])
        y = np.array([float(b) if b else np.nan for _, b in rows])
        ok = np.isfinite(y)
        sos = signal.butter(4, [1 / 6.0, 1 / 1.0], btype="band", fs=1 / float(np.median(np.diff(x))), output="sos")
        a = signal.sosfiltfilt(sos, y[ok])
        b = signal.sosfiltfilt(sos, np.interp(x[ok], rail["x"], rail["r"]))
        return float(np.corrcoef(a, b)[0, 1])
    assert main(["irregularity", fast, "--out", str(tmp_path / "plain.csv")]) == 0
    assert main(["irregularity", fast, "--reference-pass", slow, "--out", str(tmp_path / "ref.csv"),
                 "--json", str(tmp_path / "ref.json")]) == 0
    out = capsys.readouterr().out
    d = json.loads((tmp_path / "ref.json").read_text())["sensor_delay"]
    assert d["applied"] and "sensor delay:" in out
    plain, ref = corr(tmp_path / "plain.csv"), corr(tmp_path / "ref.csv")
    assert ref > plain + 0.02 and ref > 0.97, (plain, ref)
