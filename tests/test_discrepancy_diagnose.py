"""Diagnosis end to end on concealed-effect recordings (known truth), and the online detector."""
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import make_case  # noqa: E402

from maglev_ros.discrepancy.diagnose import diagnose  # noqa: E402
from maglev_ros.discrepancy.online import OnlineDetector  # noqa: E402
from maglev_ros.sensor_block import Block  # noqa: E402
from maglev_ros.twin.design import twin_config  # noqa: E402

FAST = {"n_el": 20, "noise_colour": "pink", "ambient_s": 8.0, "aa": ("cheby", 0.38)}


def test_parameter_changes_only_are_calibrated_not_called_missing_physics():
    derr = {"E": -0.07, "kb": 0.25, "kp": 0.06}
    # without car-body accelerometers (the contract's channels only, like the sample bags)
    case = make_case("clean", None, {}, seed=21, speeds=(24.0, 30.0), variant=FAST | {"body_sensors": False},
                     design_error=derr, n_spans=2)
    rep = diagnose(case.passes, case.ambient).to_dict()
    assert rep["missing_physics"] == []
    assert rep["fit_after"]["nrmse"] == pytest.approx(rep["fit_before"]["nrmse"])
    # nothing found: the twin after is the calibrated one, so every located mismatch stays
    after = [m["after_found_physics"] for m in rep["mismatches"] if "after_found_physics" in m]
    assert after and all(a["flagged_share"] == 1.0 for a in after), after
    truth = twin_config()
    # E of the truth was design * (1 + err): the calibration recovers it within 4 %
    assert rep["updated_parameters"]["youngs_modulus_pa"] == pytest.approx(truth.guideway.youngs_modulus_pa, rel=0.04)
    # every catalogue effect was tried (the levitation-loop ones too); the car body is said untestable
    assert {r["effect"] for r in rep["rejected"]} >= {"girder_stiffness_loss", "ambient_excitation", "sensor_error",
                                                      "bearing_stiffness", "control_delay", "magnet_nonlinearity",
                                                      "carbody_flexibility"}
    assert any(r["effect"] == "carbody_flexibility" and "not testable" in r["why"] for r in rep["rejected"])


@pytest.mark.slow
@pytest.mark.parametrize("effect,params,span", [
    ("girder_stiffness_loss", {"span_index": 1, "loss": 0.3}, "S2"),
    ("bearing_stiffness", {"span_index": 0, "end": 1, "factor": 0.05}, "S1"),
])
def test_structural_effect_is_named_and_placed(effect, params, span):
    case = make_case("s", effect, params, seed=31, speeds=(24.0, 30.0), variant=FAST, n_spans=2)
    rep = diagnose(case.passes, case.ambient).to_dict()
    top = rep["missing_physics"][0]
    assert top["effect"] == effect and top["location"]["span"] == span
    ev = top["evidence"]
    assert ev["heldout_nrmse_after"] < 0.7 * ev["heldout_nrmse_before"] and ev["delta_bic"] < -10


@pytest.mark.slow
def test_attachment_on_a_girder_is_not_called_a_stiffness_loss():
    """A 38 Hz spring-mass (3 % of the span's mass) at 0.4 L of S2 lowers S2's first mode as a stiffness
    loss would; it is out of the catalogue and must not be named (bench: tune 26 covers it)."""
    params = {"span_index": 1, "x_rel_m": 0.4 * 12.384, "freq_hz": 38.0, "mass_ratio": 0.03}
    case = make_case("att", "girder_attachment", params, seed=31, speeds=(24.0, 30.0), variant=FAST, n_spans=2)
    rep = diagnose(case.passes, case.ambient).to_dict()
    assert not any(m["effect"] == "girder_stiffness_loss" for m in rep["missing_physics"])


@pytest.mark.slow
def test_control_delay_is_named_on_the_vehicle_channels():
    """A 6 ms control delay that the calibrated gains partly absorb: judged on the vehicle channels it
    acts on (the acceptance rule itself: tests/test_discrepancy_acceptance.py; bench: tune 17 and 36)."""
    case = make_case("cd", "control_delay", {"lag_s": 0.006}, seed=51, speeds=(24.0, 30.0), variant=FAST,
                     n_spans=2)
    rep = diagnose(case.passes, case.ambient).to_dict()
    top = rep["missing_physics"][0]
    assert top["effect"] == "control_delay" and top["category"] == "control"
    assert 0.002 < top["parameters"]["delay_s"] < 0.012
    own = top["heldout_on_its_channels"]
    assert own["nrmse_after"] < 0.9 * own["nrmse_before"] and top["evidence"]["delta_bic"] < -10


@pytest.mark.slow
def test_current_saturation_is_named_where_the_demand_is_high():
    """Magnet current saturating at 1.2 x the fast pass's peak demand (the benchmark's tune case 28,
    3 spans): held out on the second half of the training pass too (the time split itself:
    tests/test_discrepancy_fitting.py). On a 2-span line with a smoother rail (peak demand 0.93 A) the
    same headroom gained 7 % on the magnets and was rejected: saturation shows at the demand peaks only."""
    from discrepancy_cases import build_case, case_specs
    case = build_case(28, case_specs("tune")[28], "tune")
    assert case.truth["effect"] == "magnet_nonlinearity"
    rep = diagnose(case.passes, case.ambient).to_dict()
    top = rep["missing_physics"][0]
    assert top["effect"] == "magnet_nonlinearity" and top["category"] == "magnetic_force"
    assert top["parameters"]["current_headroom_a"] == pytest.approx(case.truth["params"]["current_limit_a"], rel=0.2)
    own = top["heldout_on_its_channels"]
    assert own["nrmse_after"] < 0.9 * own["nrmse_before"] and top["evidence"]["delta_bic"] < -10


def test_car_body_bending_is_named_from_the_car_body_accelerometers():
    case = make_case("cb", "carbody_flexibility", {"bend_hz": 7.5}, seed=41, speeds=(24.0, 30.0), variant=FAST,
                     n_spans=2)
    rep = diagnose(case.passes, case.ambient).to_dict()
    top = rep["missing_physics"][0]
    assert top["effect"] == "carbody_flexibility" and top["category"] == "vehicle_structure"
    assert top["parameters"]["bending_frequency_hz"] == pytest.approx(7.5, rel=0.08)
    ev = top["evidence"]
    assert ev["heldout_nrmse_after"] < 0.9 * ev["heldout_nrmse_before"] and ev["delta_bic"] < -10


# ---------------------------------------------------------------------------------------------
def _blocks(x, fs=500.0, block_n=50, name="G1A"):
    for a in range(0, x.size, block_n):
        yield Block(int(round(a / fs * 1e9)), "t", fs, (name,), ("m/s^2",),
                    x[a:a + block_n, None].astype(np.float32))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_online_detector_is_quiet_on_noise(seed):
    rng = np.random.default_rng(seed)
    det = OnlineDetector()
    for b in _blocks(rng.normal(0, 0.01, 500 * 30)):
        det.add_block(b)
    assert det.events == []


def test_online_detector_reports_band_time_and_place_of_a_burst():
    rng = np.random.default_rng(5)
    fs = 500.0
    t = np.arange(0, 30, 1 / fs)
    x = rng.normal(0, 0.01, t.size) + np.where((t > 20) & (t < 23), 0.3 * np.sin(2 * np.pi * 40.0 * t), 0)
    det = OnlineDetector()
    det.add_position(t[::50], 5.0 * t[::50])           # vehicle at 5 m/s
    for b in _blocks(x):
        det.add_block(b)
    assert len(det.events) == 1
    e = det.events[0]
    # triangular bands: a tone also reaches the two neighbouring bands
    assert e.f0_hz <= 40.0 <= e.f1_hz and e.f1_hz - e.f0_hz < 25
    assert 19.0 <= e.t0_s <= 20.5 and 22.5 <= e.t1_s <= 24.0
    assert 95 <= e.position_start_m <= 103 and 112 <= e.position_end_m <= 120
    assert e.severity > 10
