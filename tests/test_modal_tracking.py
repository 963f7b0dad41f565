"""Streaming SSI + mode tracking, and free-decay identification after a vehicle pass."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from maglev_ros.errors import UserError
from maglev_ros.modal.free_decay import identify_free_decay, select_free_decay
from maglev_ros.modal.ssi_cov import Mode, ModalResult, SSICov
from maglev_ros.modal.tracking import ModeTracker, StreamingDecimator, StreamingSSI
from modal_data import (SPAN_M, assert_modes_match, guideway_model, simulate_drifting,
                        simulate_pass)


def test_streaming_decimator_matches_scipy_filter():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((9001, 3))
    dec = StreamingDecimator(4, 3)
    parts, i = [], 0
    while i < x.shape[0]:
        n = int(rng.integers(1, 500))
        parts.append(dec.push(x[i:i + n]))
        i += n
    y = np.concatenate(parts)
    ref = lfilter(dec.h[::-1], 1.0, x, axis=0)[::4]          # independent: direct FIR + downsample
    np.testing.assert_allclose(y, ref[:y.shape[0]], atol=1e-12)
    assert y.shape[0] == ref.shape[0]


def test_streaming_covariances_match_direct_sums():
    """Window covariances kept recursively equal the direct lag sums over the window."""
    rng = np.random.default_rng(1)
    x = rng.standard_normal((5000, 3))
    ssi = SSICov(block_rows=3, orders=range(2, 7, 2), spectrum=False, uncertainty="cluster")
    st = StreamingSSI(ssi, 100.0, ["a", "b", "c"], window_s=10.0, update_s=2.0)
    for k in range(0, 5000, 137):
        st.push(x[k:k + 137])
    sums = sum(c[0] for c in st._chunks)
    n = sum(c[1] for c in st._chunks)
    end = 5000 - st._pending.shape[0]
    win = x[end - n:end]
    for lag in (0, 2, 6):
        ref = sum(np.outer(win[t], x[end - n + t - lag]) for t in range(n))
        np.testing.assert_allclose(sums[lag], ref, rtol=1e-9)


def test_tracking_drift_keeps_id_and_vanishing_mode_is_lost():
    model = guideway_model(None)
    fs = 1000.0
    duration, t_vanish = 150.0, 50.0
    drift_end = model.frequency_hz[0] * 0.985          # -1.5 % over the record
    y = simulate_drifting(model, fs, duration, {0: drift_end}, {3: t_vanish}, seed=7)
    ssi = SSICov(block_rows=30, orders=range(4, 49, 4), decimate_to_hz=500.0, spectrum=False,
                 n_blocks=5, freq_range_hz=(5.0, 150.0))
    st = StreamingSSI(ssi, fs, model.channels, window_s=30.0, update_s=2.0)
    tracker = ModeTracker(max_misses=3)
    ids_m1, lost, updates = set(), [], []
    for k in range(0, y.shape[0], 250):
        for res in st.push(y[k:k + 250]):
            up = tracker.update(res, st.time_s)
            updates.append(up)
            lost += [e for e in up.events if e.kind == "lost"]
            if len(updates) < 2:          # ids are confirmed on the second sighting
                assert up.modes == ()
                continue
            m1 = min(up.modes, key=lambda m: abs(m.frequency_hz - 23.3))
            assert abs(m1.frequency_hz - 23.3) < 0.6
            ids_m1.add(m1.id)
    assert len(updates) > 50
    assert len(ids_m1) == 1                                 # the drifting mode keeps its id
    f_first = updates[1].by_id(next(iter(ids_m1))).frequency_hz
    f_last = updates[-1].by_id(next(iter(ids_m1))).frequency_hz
    assert f_last < f_first - 0.15                          # and the drift is followed
    lost_79 = [e for e in lost if abs(e.frequency_hz - model.frequency_hz[3]) < 1.0]
    assert len(lost_79) == 1
    # excitation stops at 50 s; the 30 s window still holds it until ~80 s
    assert t_vanish < lost_79[0].time_s < t_vanish + 30.0 + 12.0
    assert len(lost) == 1                                   # nothing else is lost
    others = [m for m in updates[-1].modes if abs(m.frequency_hz - model.frequency_hz[3]) > 2]
    assert len(others) >= 5
    assert all(np.isfinite(m.running_std_frequency_hz) for m in updates[-1].modes)


def _result(freqs, shapes):
    modes = tuple(Mode(f"M{k}", f, 0.02, {"a": s[0], "b": s[1]}, 1.0, 0.0, 0.01, 0.001)
                  for k, (f, s) in enumerate(zip(freqs, shapes)))
    return ModalResult(modes, None, None, 100.0, ("a", "b"), complex_shapes=tuple(
        np.array(s, dtype=complex) for s in shapes))


def test_tracker_matching_uses_mac_for_close_modes():
    """Two modes 1 % apart swap frequency order: MAC keeps the ids right."""
    tr = ModeTracker(freq_tol=0.03, min_confirm=1)
    u0 = tr.update(_result([10.0, 10.1], [[1, 0], [0, 1]]), 0.0)
    ids = {m.mode_shape["a"]: m.id for m in u0.modes}
    u1 = tr.update(_result([10.12, 10.02], [[1, 0.05], [0.05, 1]]), 2.0)
    for m in u1.modes:
        assert m.id == ids[round(m.mode_shape["a"])]
    assert [e.kind for e in u0.events] == ["new", "new"] and u1.events == ()
    # a candidate seen once is not reported with min_confirm=2
    tr2 = ModeTracker(min_confirm=2)
    assert tr2.update(_result([10.0], [[1, 0]]), 0.0).modes == ()
    assert len(tr2.update(_result([10.0], [[1, 0]]), 2.0).modes) == 1


def test_streaming_input_errors():
    ssi = SSICov(block_rows=3, orders=range(2, 7, 2))
    with pytest.raises(UserError, match="update_s"):
        StreamingSSI(ssi, 100.0, ["a"], window_s=1.0, update_s=2.0)
    st = StreamingSSI(ssi, 100.0, ["a", "b"], window_s=10.0, update_s=2.0)
    with pytest.raises(UserError, match="block"):
        st.push(np.zeros((10, 3)))


@pytest.mark.parametrize("seed,speed", [(0, 25.0), (1, 35.0), (3, 45.0), (4, 30.0)])
def test_free_decay_after_pass(seed, speed):
    model = guideway_model(seed)
    fs = 500.0
    rear = -12.0
    y, t, pos, t_exit = simulate_pass(model, fs, speed_mps=speed, noise_frac=0.01, seed=seed,
                                      axle_offsets_m=(0.0, -3.0, -6.0, -9.0, rear))
    w_pos = select_free_decay(y, fs, position_m=pos, position_time_s=t, span_end_m=SPAN_M,
                              rear_offset_m=rear)
    assert w_pos.method == "position"
    assert w_pos.start_s == pytest.approx(t_exit + 0.1, abs=2.0 / fs)
    w_env = select_free_decay(y, fs)
    assert w_env.method == "envelope"
    assert t_exit <= w_env.start_s < t_exit + 0.8         # never inside the forced part
    excited = [r for r, (kind, _) in enumerate(model.kinds) if kind in ("vertical", "torsion")]
    for w in (w_pos, w_env):
        res = identify_free_decay(y, fs, w, SSICov(block_rows=40, orders=range(2, 61, 2)),
                                  channels=model.channels)
        assert res.uncertainty == "cluster"
        chk = assert_modes_match(res.modes, model, 150.0, which=excited, freq_tol=0.01)
        assert chk["missing"] == []
        assert chk["freq_rel"] < 0.01
        assert chk["damping_abs"] < 0.01
        assert chk["mac_min"] > 0.98
        # modes not in `which` are real (weakly excited lateral modes), anything else is spurious
        real = model.frequency_hz
        assert all(np.min(np.abs(real - f) / real) < 0.02 for f in chk["spurious"])


def test_free_decay_errors():
    y = np.random.default_rng(0).standard_normal((1000, 3))
    with pytest.raises(UserError, match="never leaves"):
        select_free_decay(y, 100.0, position_m=np.zeros(10), position_time_s=np.arange(10.0),
                          span_end_m=5.0)
    with pytest.raises(UserError, match="span_end_m"):
        select_free_decay(y, 100.0, position_m=np.zeros(10))
