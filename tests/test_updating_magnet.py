"""Magnet layer vs the hidden true gains of a simulated pass (irregularity known to the test: this
isolates the gain identification from the irregularity reconstruction)."""
from __future__ import annotations

import numpy as np

import sys, os
sys.path.insert(0, os.path.dirname(__file__))
from updating_data import LINE, random_truth, simulate_measurement, twin_config, with_guideway  # noqa: E402
from maglev_ros.updating.magnet_layer import MagnetLayer, MagnetModel, PassEvidence, nrmse
from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, MAGNET_PARAMS


def _evidence(m, speed, fs=500.0):
    t0 = m["time_s"][0]
    x, r = m["true_irregularity"]
    return PassEvidence(m["time_s"] - t0 + 1 / fs, m["accel"], tuple(range(1, 9)), m["time_s"] - t0,
                        m["speed_mps"], m["position_m"][0] - speed / fs, x, r)


def test_magnet_layer_recovers_true_gains_and_i0_ridge():
    nom = twin_config()
    tcfg = random_truth(0).config(nom)
    gcfg = with_guideway(nom, **{k: getattr(tcfg.guideway, k) for k in GUIDEWAY_PARAMS})
    ev = _evidence(simulate_measurement(tcfg, 6.944, 3, 2.0, start_position_m=5.0), 6.944)
    up = MagnetLayer(n_samples=30, polish_max_nfev=15).fit(gcfg, LINE, [ev])
    tv = np.array([getattr(tcfg.levitation, k) for k in MAGNET_PARAMS])
    assert all(up.identifiable)
    assert np.all(np.abs(np.array(up.values) / tv - 1) < 0.05)
    assert up.nrmse_updated < up.nrmse_nominal
    combos = {c.expression: c for c in up.identifiability.combinations}
    i0 = nom.levitation.static_current_a
    assert abs(combos["kp/I0"].value / (tv[0] / i0) - 1) < 0.05
    # common scale of (kp, kv, ka, I0) is an exact ridge of the model
    assert len(up.identifiability.ridge_directions) == 1
    assert np.allclose(np.abs(up.identifiability.ridge_directions[0]), 0.5, atol=0.05)
