"""The ambient background measured on a pass's quiet stretches (evaluate.RecData.background) and the
ambient_excitation form built on it, against the generator's drawn ambient level."""
import math

import numpy as np
import pytest

from discrepancy_cases import make_case
from maglev_ros.discrepancy import catalogue as cat
from maglev_ros.discrepancy.evaluate import ambient_powers, prepare
from maglev_ros.discrepancy.model import base_spec

LEVEL = 0.02     # m/s^2 RMS over the guideway accelerometers (the generator's definition)


@pytest.fixture(scope="module")
def prepared():
    out = {}
    for effect, params in (("ambient_excitation", {"rms_mps2": LEVEL}), (None, {})):
        case = make_case("bg", effect, params, seed=21, speeds=(24.0, 30.0), n_spans=2)
        rec = case.passes[0]
        out[effect] = (rec, prepare(rec, base_spec(rec.metadata)))
    return out


def _rms_over_accels(rec, rd):
    acc = [n for n in rec.names("guideway_accel") if n in rd.background]
    assert acc, "no guideway accelerometer had quiet frames"
    return math.sqrt(np.mean([np.sum(rd.background[n]) for n in acc]))


def test_background_of_a_pass_with_ambient_vibration_is_its_level(prepared):
    rec, rd = prepared["ambient_excitation"]
    # the off-mode part of the ambient sits in the power-law noise floor, so the measured background
    # holds most of the level, not more
    assert 0.7 * LEVEL < _rms_over_accels(rec, rd) < 1.15 * LEVEL


def test_background_of_a_clean_pass_is_small(prepared):
    rec, rd = prepared[None]
    assert _rms_over_accels(rec, rd) < 0.15 * LEVEL


def test_the_measured_form_carries_the_background_by_one_factor(prepared):
    rec, rd = prepared["ambient_excitation"]
    h = cat.ambient_background_hypothesis(rec.names("guideway_accel"), rd.background, "in pass 1",
                                          frozenset(rec.names("guideway_accel")))
    spec = h.apply(base_spec(rec.metadata), np.array([math.log10(0.5)]))
    amb = ambient_powers(spec, rd)
    for n, bg in rd.background.items():
        np.testing.assert_allclose(amb[n], 0.5 * bg, rtol=1e-12)
    _, params = h.describe(np.array([0.0]), spec)
    n = next(iter(rd.background))
    assert params["ambient_rms_mps2"][n] == pytest.approx(math.sqrt(np.sum(rd.background[n])))


def test_each_pass_brings_its_own_background(prepared):
    """Ambient vibration changes between recordings: the form fitted on one pass (level 0.02 m/s^2)
    gives another pass with twice that ambient (another recording) the level it measured itself."""
    rec, rd = prepared["ambient_excitation"]
    h = cat.ambient_background_hypothesis(rec.names("guideway_accel"), rd.background, "in pass 1",
                                          frozenset(rec.names("guideway_accel")))
    spec = h.apply(base_spec(rec.metadata), np.array([0.0]))
    other = make_case("bg2", "ambient_excitation", {"rms_mps2": 2 * LEVEL}, seed=22, speeds=(24.0, 30.0),
                      n_spans=2).passes[0]
    rd2 = prepare(other, base_spec(other.metadata))
    amb = ambient_powers(spec, rd2)
    acc = [n for n in other.names("guideway_accel") if n in rd2.background and n in amb]
    assert acc
    rms = math.sqrt(np.mean([np.sum(amb[n]) for n in acc]))
    assert 0.7 * 2 * LEVEL < rms < 1.15 * 2 * LEVEL


def test_a_diagnosis_names_the_measured_ambient_at_its_level():
    """End to end on a small ambient case (the generator's drawn level is the reference): the report names
    ambient_excitation; when the measured form is the one carried, its RMS is the drawn level's order and the
    HTML report shows its parameters."""
    from maglev_ros.discrepancy.diagnose import diagnose
    from maglev_ros.discrepancy.report_html import render
    case = make_case("bg-e2e", "ambient_excitation", {"rms_mps2": LEVEL}, seed=21, speeds=(24.0, 30.0), n_spans=2,
                     variant={"n_el": 20, "noise_colour": "white", "ambient_s": 8.0, "body_sensors": False})
    d = diagnose(case.passes, case.ambient)
    rep = d.to_dict()
    (amb,) = [m for m in rep["missing_physics"] if m["effect"] == "ambient_excitation"]
    rms = amb["parameters"]["ambient_rms_mps2"]
    assert 0.5 * LEVEL < math.sqrt(np.mean(np.square(list(rms.values())))) < 1.5 * LEVEL
    assert rep["fit_after"]["nrmse"] < rep["fit_before"]["nrmse"]
    html = render(d)
    if "measured_on" in amb["parameters"]:
        assert "level_factor" in html
