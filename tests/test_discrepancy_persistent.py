"""Persistent band misfits: one girder sensor's band response off its peers' (relative to the twin)
in every pass is located on its span and band; model error alone, or a misfit in one pass only, is
not. Synthetic band powers with known truth (a band amplified by a known factor on one sensor)."""
from types import SimpleNamespace as NS

import numpy as np
import pytest

from maglev_ros.discrepancy.localize import persistent_mismatches

L_SPAN = 12.0
EDGES = np.array([0, 3, 6, 10, 14, 18, 22, 26, 31, 37, 44, 52, 62, 74, 88, 105], float)
SENSORS = {"G1A": 6.0, "G1Q": 3.0, "G2A": 18.0, "G2Q": 15.0, "G3A": 30.0, "G3Q": 27.0}


def _rec(rng, boost: dict, own=0.08, common=0.10, n_frames=40):
    """One recording's band powers (frames x bands); ``boost``: {(channel, band): amplitude factor}."""
    nb = EDGES.size - 1
    err_common = np.exp(rng.normal(0, common, nb))
    pm, mp, masks, noise, chans = {}, {}, {}, {}, {}
    for n, x in SENSORS.items():
        twin = 10 ** rng.uniform(-4, -2, nb) * np.ones((n_frames, 1))
        amp = err_common * np.exp(rng.normal(0, own, nb))
        for (c, b), f in boost.items():
            if c == n:
                amp[b] *= f
        pm[n] = twin * amp ** 2 * rng.chisquare(8, (n_frames, nb)) / 8
        mp[n] = twin
        masks[n] = np.ones(nb, bool)
        noise[n] = 1e-3 * twin[0]
        chans[n] = NS(group="guideway_accel", position_m=x)
    md = {"line": {"spans": [{"span_id": f"S{i + 1}", "start_m": i * L_SPAN, "length_m": L_SPAN} for i in range(3)]}}
    rec = NS(channels=chans, metadata=md, t0_s=0.0, t1_s=10.0)
    return NS(rec=rec, pm=pm, masks=masks, noise=noise, grid=NS(edges_hz=EDGES), body_pairs={}, sens_pairs={}), mp


@pytest.mark.parametrize("seed", range(4))
def test_a_band_misfit_of_one_girder_sensor_is_located_on_its_span(seed):
    rng = np.random.default_rng(seed)
    rds, mps = zip(*[_rec(rng, {("G2Q", 5): 1.7}) for _ in range(2)])
    found = persistent_mismatches(list(rds), list(mps))
    assert len(found) == 1
    m = found[0]
    assert m.channels == ("G2Q",) and m.position_m == (12.0, 24.0) and m.frequency_hz == (18.0, 22.0)
    # the amplitude ratio to the peers: 1.7 within the model error's scatter
    assert m.peer_amplitude_ratio == pytest.approx(1.7, rel=0.15)
    assert m.severity > 3.0      # residual power over the noise floor, as for every mismatch


@pytest.mark.parametrize("seed", range(4))
def test_model_error_alone_or_one_pass_only_is_not_persistent(seed):
    rng = np.random.default_rng(50 + seed)
    rds, mps = zip(*[_rec(rng, {}, own=0.12) for _ in range(2)])
    assert persistent_mismatches(list(rds), list(mps)) == []
    rds, mps = zip(_rec(rng, {("G2Q", 5): 1.7}), _rec(rng, {}))
    assert persistent_mismatches(list(rds), list(mps)) == []
