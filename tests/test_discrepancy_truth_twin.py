"""What the twin with a foreign case's TRUE parameters reproduces (partner simulator, a damaged zone).

1. The rail is reconstructed with the twin that is then driven by it: the girder deflection it
   removes must include the twin's local physics. Built with the line's plain spans, the damaged
   zone's vibration stayed in the rail (error 4 um of 12.5 um at the zone in the 0.25-0.4 m band)
   and the true twin then missed 40 % of the span's first-mode response during the pass.
2. The gaps' slow content is compared through the filters the twin's rail went through (the
   reconstruction's time high-pass and its spatial band edge at the pass speed, zero-phase
   Butterworth, gain (f/fc)^(2n) / (1 + (f/fc)^(2n)) each): below them the twin has no rail. A
   2nd-order high-pass at the corner left the gap's tracking of those waves in its frame means,
   misfit by 0.23 of their scale with the true parameters.
3. A gap sensor's scale and offset are fitted without a drift (not identifiable below the band).

References: the analytic Butterworth gain; the partner simulator's truth (parameters, damaged zone,
true rail, the form of its gap sensor error).
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.discrepancy.evaluate import _fit_items, prepare, rail_band_filters
from maglev_ros.discrepancy.features import without_long_waves

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT.parent / "shared" / "validation" / "partner-sim" / "H06"


def _gain(f_hz, corners):
    return np.prod([(f_hz / c) ** (2 * n) / (1 + (f_hz / c) ** (2 * n)) for c, n in corners])


@pytest.mark.parametrize("f_hz", [0.3, 0.5, 0.8, 1.5, 4.0])
def test_the_filters_pass_a_wave_with_the_butterworth_gain_of_each_corner(f_hz):
    fs = 200.0
    t = np.arange(0, 120.0, 1 / fs)
    corners = ((0.41, 4), (0.45, 4))
    x = 0.01 + 1e-5 * np.sin(2 * np.pi * f_hz * t)
    y = without_long_waves(x, fs, corners)
    mid = slice(t.size // 4, 3 * t.size // 4)   # away from the filter's end transients
    amp = np.sqrt(2) * np.std(y[mid])
    assert amp == pytest.approx(1e-5 * _gain(f_hz, corners), rel=0.02, abs=2e-9)
    assert np.mean(y) == pytest.approx(np.mean(x), abs=2e-7)      # a sensor offset is kept
    assert without_long_waves(x, fs, None) is x


@pytest.fixture(scope="module")
def truth_pass():
    if not CASE.is_dir():
        pytest.skip("partner-sim recordings not found beside the repository (../shared)")
    from maglev_ros.discrepancy.irregularity import with_twin_irregularity
    from maglev_ros.discrepancy.model import CAL_PARAMS, base_spec
    from maglev_ros.discrepancy.recording import load_recording
    truth = json.loads((CASE / "truth.json").read_text())
    rec = load_recording(str(CASE / "pass"))
    spec = base_spec(rec.metadata, 16).with_(cal=tuple(math.log(truth["factors"][k]) for k in CAL_PARAMS))
    (zone,) = [e["parameters"] for e in truth["effects"] if e["effect"] == "girder_stiffness_loss"]
    x0, x1 = zone["zone_m"]
    (s,) = [i for i, sp in enumerate(spec.spans) if sp.start_m <= x0 < sp.start_m + sp.length_m]
    start = spec.spans[s].start_m
    spec = spec.with_(girder_zones=((s, x0 - start, x1 - start, zone["ei_factor"]),))
    return spec, with_twin_irregularity(rec, spec)


def test_the_rail_filters_are_the_reconstructions_band_at_the_pass_speed(truth_pass):
    _, rec = truth_pass
    band = rec.irregularity_info["band"]
    v = float(np.mean(np.abs(rec.speed_mps)))
    (hp, n1), (edge, n2) = rail_band_filters(rec)
    assert hp == band["highpass_hz"] and n1 == n2 == band["filter"]["order"]
    assert edge == pytest.approx(v / band["max_wavelength_m"])


def test_the_true_twin_predicts_the_gaps_frame_means_of_a_foreign_pass(truth_pass):
    spec, rec = truth_pass
    rd = prepare(rec, spec)
    names = []
    items = _fit_items(spec, rd, names_out=names)
    level = [float(np.sqrt(np.sum((am - at) ** 2)) / den) for (am, at, den), nm in zip(items, names)
             if nm[0] == "level"]
    assert len(level) == 2
    # the gaps' own dynamics are fitted to 0.06-0.10 of their scale by the true twin (the transmissibility
    # items); their frame means are no worse
    assert max(level) < 0.12


def test_a_gap_sensors_scale_and_offset_are_recovered_without_a_drift(truth_pass):
    from maglev_ros.discrepancy.catalogue import sensor_hypothesis
    from maglev_ros.discrepancy.fitting import fit_base, fit_sensor
    spec, rec = truth_pass
    g = rec.channels["M8G"]

    def fitted(values):
        rds = [prepare(replace(rec, channels={**rec.channels, "M8G": replace(g, values=values)}), spec)]
        fit = fit_sensor(fit_base(spec, rds, max_nfev=1), sensor_hypothesis("M8G", "m", 5e-6, rec.t1_s - rec.t0_s), rds)
        return math.exp(fit.params[0]), fit.params[1], fit.params[2]
    # the partner's gap sensor error: reads 0.93 g + 0.75 mm (a 50 um shift of the 10 mm mean)
    scale, offset, drift = fitted(0.93 * g.values + 0.00075)
    scale_ok, _, _ = fitted(g.values)
    assert drift == 0.0
    # the true twin's own gap amplitude is a few % above the partner's (scale 0.95 on the sound
    # sensor): the fault is the ratio, within 1 %
    assert scale_ok == pytest.approx(1.0, abs=0.06)
    assert scale / scale_ok == pytest.approx(0.93, abs=0.01)
    g0 = 0.010
    assert g0 + offset == pytest.approx(0.93 * g0 + 0.00075, abs=5e-6)


def test_the_rail_rebuilt_with_the_true_twin_is_the_true_rail_over_the_damaged_zone(truth_pass):
    from scipy import signal
    spec, rec = truth_pass
    x, r = rec.irregularity
    true = np.load(CASE / "irregularity.npz")
    rt = np.interp(x, true["x_m"], true["r_m"])
    dx = float(x[1] - x[0])
    sos = signal.butter(4, [1 / 0.4, 1 / 0.25], btype="band", fs=1 / dx, output="sos")
    (zone,) = [z for z in spec.girder_zones]
    x0 = spec.spans[zone[0]].start_m + zone[1]
    w = (x >= x0 - 1.0) & (x <= spec.spans[zone[0]].start_m + zone[2] + 1.0)
    # the waves a magnet meets at the span's first mode at this speed (0.31 m at 6.9 m/s)
    err = np.std(signal.sosfiltfilt(sos, r - rt)[w])
    assert err < 0.15 * np.std(signal.sosfiltfilt(sos, rt)[w])
