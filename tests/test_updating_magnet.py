"""Magnet layer vs the hidden true gains of a simulated pass (irregularity known to the test: this
isolates the gain identification from the irregularity reconstruction; the pipeline test covers
the reconstructed case)."""
from __future__ import annotations

import numpy as np

import sys, os
sys.path.insert(0, os.path.dirname(__file__))
from updating_data import LINE, random_truth, simulate_measurement, twin_config, with_guideway  # noqa: E402
from maglev_ros.updating.magnet_layer import MagnetLayer, make_evidence
from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, MAGNET_PARAMS


def test_magnet_layer_recovers_true_gains_std_and_i0_ridge():
    nom = twin_config()
    tcfg = random_truth(0).config(nom)
    gcfg = with_guideway(nom, **{k: getattr(tcfg.guideway, k) for k in GUIDEWAY_PARAMS})
    m = simulate_measurement(tcfg, 6.944, 3, 3.0, start_position_m=5.0)
    ev = make_evidence(m["time_s"], m["accel"], range(1, 9), m["time_s"], m["position_m"], m["speed_mps"],
                       m["true_irregularity"], m["offsets"], band_hz=(1.0, 80.0), model_fs_hz=500.0)
    up = MagnetLayer(n_samples=8, polish_max_nfev=6, n_particles=30, n_iterations=30).fit(gcfg, LINE, [ev])
    tv = np.array([getattr(tcfg.levitation, k) for k in MAGNET_PARAMS])
    err = np.array(up.values) / tv - 1
    assert up.identifiable[0]                                  # kp always; kv, ka when std <= 2.5 %
    assert np.all(np.abs(err)[np.array(up.identifiable)] < 0.05), err
    assert np.all(np.abs(err) < 0.10), err
    # the stated (sandwich) std covers the error: |estimate - truth| / std of order 1
    z = (np.array(up.values) - tv) / np.array(up.std)
    assert np.all(np.abs(z) < 4.0), z
    assert up.nrmse_updated < 0.5 * up.nrmse_nominal
    combos = {c.expression: c for c in up.identifiability.combinations}
    i0 = nom.levitation.static_current_a
    assert abs(combos["kp/I0"].value / (tv[0] / i0) - 1) < 0.05
    # common scale of (kp, kv, ka, I0) is an exact ridge of the model (found within the forward-
    # difference error of the Jacobian, step 0.01 in log: the weak direction mixes in a little)
    assert len(up.identifiability.ridge_directions) == 1
    assert np.allclose(np.abs(up.identifiability.ridge_directions[0]), 0.5, atol=0.1)
