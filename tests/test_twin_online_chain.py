"""The online chain twin -> updater without a ROS graph.

References (independent of the code under test):
- the simulator's own NOISE-FREE response of the same pass (same seed, noise switched off): the
  online twin, given the true parameters and measuring the irregularity itself from the noisy
  vehicle streams, must predict it wherever it declares its vehicle residual valid;
- the measured positions in the bag: a valid vehicle residual may only exist where every magnet
  was over a stretch of rail the vehicle had ALREADY passed (measured), never ahead of it;
- the simulator's true gains: the online magnet layer, triggered by the residual stream, must move
  the published gains toward them.
"""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from maglev_ros.bag_reader import BagReader
from maglev_ros.contract import TOPIC_VEHICLE_POSITION
from maglev_ros.twin.online import GROUP_TOPICS, OnlineTwin, nrmse
from maglev_ros.twin.simulate import simulate, truth_paths

CHEAP = ["line.n_spans=3", "free_decay_s=1.0", "rates.oversample=2", "rates.vehicle_hz=1000",
         "rates.guideway_hz=1000"]
QUIET = ["instrument.guideway_accel.noise_rms=0", "instrument.guideway_displacement.noise_rms=0",
         "instrument.vehicle_accel.noise_rms=0", "instrument.vehicle_gap.noise_rms=0"]


def _read(bag):
    with BagReader(bag) as r:
        return r.metadata, list(r.iter_blocks())


def _truth_params(bag):
    truth = json.loads(truth_paths(bag)[0].read_text())
    return {f"{sec}.{k}": v for sec, d in truth["truth_design"].items() for k, v in d.items()
            if isinstance(v, (int, float))}


@pytest.mark.parametrize("seed,speed_mps,lead_in_s", [(3, 6.944, 3.0), (8, 9.0, 2.5)])
def test_twin_measures_the_irregularity_and_judges_the_vehicle_only_where_covered(tmp_path, seed, speed_mps,
                                                                                 lead_in_s):
    sets = CHEAP + [f"speed_mps={speed_mps}", f"lead_in_s={lead_in_s}"]
    noisy = simulate("paper", tmp_path / "noisy", sets=sets, seed=seed).bag
    quiet = simulate("paper", tmp_path / "quiet", sets=sets + QUIET, seed=seed).bag
    # same pass, same irregularity: only the instrument noise differs
    assert truth_paths(noisy)[1].read_text() == truth_paths(quiet)[1].read_text()
    md, items = _read(noisy)
    _md, quiet_items = _read(quiet)
    ref = {(tp, b.stamp_ns): b for tp, b in quiet_items}
    pos = np.concatenate([b.data for tp, b in items if tp == TOPIC_VEHICLE_POSITION]).astype(float)
    pos_t = np.concatenate([b.times_s() for tp, b in items if tp == TOPIC_VEHICLE_POSITION])
    offs = np.asarray(md.magnet_offsets_m, float)

    tw = OnlineTwin(md, parameters=_truth_params(noisy), dt_max_s=5e-4)
    assert tw.irregularity_source == "vehicle"
    got, newest = [], -np.inf
    for tp, b in items + [(None, None)]:
        outs = tw.finish() if tp is None else tw.on_block(tp, b)
        if tp == TOPIC_VEHICLE_POSITION:
            newest = max(newest, float(b.channel("position_m")[-1]))
        for o in outs:
            got.append((o, list(tw.profile_stretches), tw.n_profile_updates, newest))
    veh = [g for g in got if g[0].group.startswith("vehicle")]
    assert len(veh) == sum(1 for tp, _ in items if tp.startswith("/testline/vehicle/") and tp != TOPIC_VEHICLE_POSITION)
    # nothing is judged before a measured profile exists
    assert not any(o.valid or np.isfinite(o.residual.data).any() for o, _s, n, _x in veh if n == 0)
    n_valid = 0
    for o, stretches, _n, lead_now in veh:
        ok = np.all(np.isfinite(o.residual.data), axis=1)
        assert o.valid == bool(ok.all())
        if not ok.any():
            continue
        x_ref = np.interp(o.measured.times_s()[ok], pos_t, pos[:, 0])
        lo_x, hi_x = x_ref + offs.min(), x_ref + offs.max()
        inside = np.zeros(ok.sum(), bool)
        for lo, hi in stretches:
            assert hi <= lead_now          # the profile is measured rail, behind the leading magnet
            inside |= (lo_x >= lo - 0.06) & (hi_x <= hi + 0.06)
        assert inside.all()                # every magnet over the measured profile
        n_valid += int(ok.sum())
    n_all = sum(o.measured.n_samples for o, *_ in veh)
    assert n_valid > 0.25 * n_all
    for group in ("vehicle_accel", "vehicle_gap"):
        outs = [o for o, *_ in veh if o.group == group]
        ok = np.concatenate([np.all(np.isfinite(o.residual.data), axis=1) for o in outs])
        pred = np.concatenate([o.predicted.data for o in outs])[ok]
        res = np.concatenate([o.residual.data for o in outs])[ok]
        meas = np.concatenate([o.measured.data for o in outs])[ok]
        clean = np.concatenate([ref[(GROUP_TOPICS[o.group], o.measured.stamp_ns)].data for o in outs])[ok]
        cols = [outs[0].measured.channels.index(c) for c in outs[0].predicted.channels]
        e_ref = nrmse(pred - clean[:, cols], clean[:, cols])
        e_res = nrmse(res, meas[:, cols])
        assert np.all(e_ref < 0.2), (group, e_ref)
        assert np.all(e_res < 0.2), (group, e_res)
    # the guideway channels do not wait for the irregularity: a prediction for every block
    n_g = sum(1 for tp, _ in items if tp.startswith("/testline/guideway/"))
    assert sum(1 for o, *_ in got if o.group.startswith("guideway") and o.valid) == n_g


def test_twin_with_a_profile_message_stream_waits_for_it_and_judges_only_covered_vehicle(tmp_path):
    """irregularity_source topic: the profile arrives as messages (an IncrementalProfiler fed the
    same blocks, published every 0.5 s of stream like the irregularity node, point-magnet band)."""
    from maglev_ros.irregularity.profile import IncrementalProfiler, magnet_channel_pairs
    bag = simulate("paper", tmp_path / "p", sets=CHEAP + ["lead_in_s=3.0"], seed=21).bag
    md, items = _read(bag)
    prof = IncrementalProfiler(md.magnet_offsets_m, md.nominal_gap_m, channel_pairs=magnet_channel_pairs(md),
                               band_speed_mps=0.8 * md.nominal_speed_mps, highpass_hz=0.8, spacing_m=0.02,
                               magnet_length_m=0.0)
    keys = {"/testline/vehicle/accel": "accel", "/testline/vehicle/gap": "gap", TOPIC_VEHICLE_POSITION: "position"}
    tw = OnlineTwin(md, parameters=_truth_params(bag), irregularity_source="topic", dt_max_s=5e-4)
    outs, last_pub, n_msgs = [], -np.inf, 0
    for tp, b in items:
        if tp in keys:
            prof.partial_fit(**{keys[tp]: b})
        t = b.times_s()[-1]
        if t - last_pub >= 0.5:
            last_pub = t
            try:
                res = prof.result()
            except Exception:          # noqa: BLE001  (not enough data yet: the node publishes nothing)
                res = None
            if res is not None and np.isfinite(res.irregularity_m).sum() >= 2:
                assert tw.set_irregularity_profile(res.position_m[0], res.spacing_m, res.irregularity_m)
                n_msgs += 1
        outs += [(o, n_msgs) for o in tw.on_block(tp, b)]
    outs += [(o, n_msgs) for o in tw.finish()]
    veh = [(o, n) for o, n in outs if o.group == "vehicle_accel"]
    assert not any(o.valid for o, n in veh if n == 0)          # nothing judged before the first message
    valid = [o for o, _n in veh if o.valid]
    assert len(valid) > 0.25 * len(veh)
    res = np.concatenate([o.residual.data for o in valid])
    meas = np.concatenate([o.measured.data for o in valid])
    assert np.all(nrmse(res, meas) < 0.2), nrmse(res, meas)


KP_NOM, KV_NOM = 6500.0, 35.0
KP_TRUE, KV_TRUE = 1.2 * KP_NOM, 0.85 * KV_NOM


@pytest.fixture(scope="module")
def gains_pass(tmp_path_factory):
    """A pass whose true levitation gains differ from the nominal design (kp +20 %, kv -15 %);
    guideway truth = design, so only the magnet layer has something to find."""
    sets = CHEAP + ["lead_in_s=4.0", "truth.guideway.youngs_modulus_pa=3.9e10",
                    "truth.guideway.density_kg_m3=2500.0", "truth.guideway.bearing_stiffness_n_per_m=3.0e10",
                    f"truth.levitation.kp_a_per_m={KP_TRUE}", f"truth.levitation.kv_a_s_per_m={KV_TRUE}",
                    "truth.levitation.ka_a_s2_per_m=0.25"]
    bag = simulate("paper", tmp_path_factory.mktemp("gains") / "pass", sets=sets, seed=5).bag
    return _read(bag)


def test_updater_runs_the_magnet_layer_once_on_valid_residuals_and_moves_gains_to_truth(gains_pass, tmp_path):
    from maglev_ros.updating.magnet_layer import MagnetLayer
    from maglev_ros.updating.online import OnlineUpdater
    md, items = gains_pass
    design = md.raw["design"]["levitation"]
    assert design["kp_a_per_m"] == KP_NOM and design["kv_a_s_per_m"] == KV_NOM
    hist = tmp_path / "hist.jsonl"
    # a cheap magnet-layer configuration (16 LHS samples, 8 LM evaluations, 250 Hz model; ~20 s CPU)
    # instead of the node's default (30 / 15 / 500 Hz; ~33 s CPU on this pass, same accuracy class)
    up = OnlineUpdater(hist, magnet_layer=MagnetLayer(n_samples=16, polish_max_nfev=8), magnet_fs_hz=250.0)
    up.set_metadata(md.raw)
    tw = OnlineTwin(md, dt_max_s=5e-4)        # nominal gains: the twin the updater corrects
    pubs, n_invalid, n_valid = [], 0, 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)      # no "Mean of empty slice" & co.
        def twin_outputs():
            for tp, b in items:
                up.on_vehicle_block(tp, b)
                yield from tw.on_block(tp, b)
            yield from tw.finish()
        for o in twin_outputs():
            if True:
                if o.group != "vehicle_accel":
                    continue
                n_valid += o.valid
                n_invalid += not o.valid
                pub = up.on_residual(o.residual)       # invalid (NaN) blocks included: must be skipped
                if pub is not None:
                    pubs.append(pub)
    assert n_invalid > 0 and n_valid > 0
    assert any("not valid yet" in line for line in up.log)
    # said once per reason (again only after the layer ran), not once per invalid block
    assert sum("not valid yet" in line for line in up.log) <= 1 + len(pubs) < n_invalid
    assert len(pubs) == 1, up.log
    vals = dict(zip(pubs[0].names, pubs[0].values))
    ident = dict(zip(pubs[0].names, pubs[0].identifiable))
    # kp: the gain the magnet accelerations are most sensitive to, checked whatever the layer's
    # identifiability flag says; kv when the layer declares it identifiable
    for name, nom, true in (("levitation.kp_a_per_m", KP_NOM, KP_TRUE), ("levitation.kv_a_s_per_m", KV_NOM, KV_TRUE)):
        if name == "levitation.kp_a_per_m" or ident[name]:
            assert abs(vals[name] - true) <= 0.5 * abs(nom - true), (name, vals[name], true)
    # residuals the twin computed before adopting revision 1 are not judged
    assert up.revision == 1 == pubs[0].revision
    tw.set_parameters(list(pubs[0].names), list(pubs[0].values), source_revision=pubs[0].revision)
    assert tw.frame_id == "twin rev 1"
    from maglev_ros.sensor_block import Block
    b = [b for tp, b in items if tp == "/testline/vehicle/accel"][-1]
    old = Block.from_arrays(b.stamp_ns, b.sample_rate_hz, b.channels, b.units, 0.5 * b.data, "twin rev 0")
    assert up.residual_ready(old) is None and "twin revision 0" in up.log[-1]
    rec = [json.loads(line) for line in hist.read_text().splitlines()]
    assert len(rec) == 1 and rec[0]["data_used"]["kind"] == "vehicle window"
    assert rec[0]["data_used"]["residual_nrmse"] > up.nrmse_trigger
    assert rec[0]["fit"]["nrmse_after"] < rec[0]["fit"]["nrmse_before"]


def test_updater_waits_with_one_reason_for_windows_that_lack_what_the_layer_needs(gains_pass, tmp_path):
    from maglev_ros.sensor_block import Block
    from maglev_ros.updating.online import OnlineUpdater
    md, items = gains_pass
    up = OnlineUpdater(tmp_path / "h.jsonl", magnet_min_s=1.0, nrmse_trigger=0.0, max_window_s=1.5)
    up.set_metadata(md.raw)
    acc = [b for tp, b in items if tp == "/testline/vehicle/accel"][:20]

    def residuals_never_run_the_layer(u) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            for b in acc:
                res = Block.from_arrays(b.stamp_ns, b.sample_rate_hz, b.channels, b.units, 0.5 * b.data, "twin")
                assert u.on_residual(res) is None

    # residual blocks but no gap stream buffered: the layer must not run, and says why once
    for b in acc:
        up.on_vehicle_block("/testline/vehicle/accel", b)
    residuals_never_run_the_layer(up)
    assert sum("/testline/vehicle/gap not buffered" in line for line in up.log) == 1, up.log
    # a stationary vehicle: no moving window
    up2 = OnlineUpdater(tmp_path / "h2.jsonl", magnet_min_s=1.0, nrmse_trigger=0.0, max_window_s=1.5)
    up2.set_metadata(md.raw)
    for tp, b in items[:200]:
        if tp == TOPIC_VEHICLE_POSITION:
            d = np.array(b.data, float)
            d[:, list(b.channels).index("speed_mps")] = 0.0
            d[:, list(b.channels).index("position_m")] = 10.0
            b = Block.from_arrays(b.stamp_ns, b.sample_rate_hz, b.channels, b.units, d, b.frame_id)
        up2.on_vehicle_block(tp, b)
    residuals_never_run_the_layer(up2)
    assert sum("slower than" in line for line in up2.log) == 1, up2.log
    assert not (tmp_path / "h2.jsonl").exists() or not (tmp_path / "h2.jsonl").read_text().strip()


def test_online_twin_predicts_the_car_body_accelerometers(tmp_path):
    """Car-body accelerometers (optional topic /testline/vehicle/body_accel) of a pass from the
    concealed-effect generator (its own mesh, step, anti-alias filter; rigid car body; the
    twin given the truth's design values): the online twin's rigid body prediction follows them
    where it declares them valid above 3 Hz (correlation > 0.95) (the body's heave/pitch below follow rail waves longer
    than the vehicle measures well; the diagnosis also compares the body above 3 Hz)."""
    from scipy import signal
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from discrepancy_cases import make_case, write_recording_bag
    from maglev_ros.contract import TOPIC_BODY_ACCEL
    derr = {"E": 0.0, "kb": 0.0, "kp": 0.0}
    case = make_case("body", None, {}, seed=12, speeds=(24.0,), variant={"n_el": 20, "ambient_s": 2.0},
                     design_error=derr, n_spans=2)
    write_recording_bag(case.passes[0], tmp_path / "pass")
    md, items = _read(tmp_path / "pass")
    assert "B1A" in md.sensors_on_topic(TOPIC_BODY_ACCEL)
    tw = OnlineTwin(md, dt_max_s=5e-4)
    outs = [o for tp, b in items for o in tw.on_block(tp, b)] + tw.finish()
    body = [o for o in outs if o.group == "body_accel"]
    assert body and any(o.valid for o in body)
    ok = np.concatenate([np.all(np.isfinite(o.residual.data), axis=1) for o in body])
    pred = np.concatenate([o.predicted.data for o in body])[ok]
    meas = np.concatenate([o.measured.data for o in body])[ok]
    assert ok.sum() > 500
    sos = signal.butter(4, 3.0, "highpass", fs=body[0].measured.sample_rate_hz, output="sos")
    for j, name in enumerate(body[0].predicted.channels):
        r = np.corrcoef(signal.sosfiltfilt(sos, pred[:, j]), signal.sosfiltfilt(sos, meas[:, j]))[0, 1]
        assert r > 0.95, (name, r)
