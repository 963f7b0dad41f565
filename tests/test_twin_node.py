"""Online twin (core) and the ``twin`` node over a real ROS 2 graph.

Reference: a noise-free pass simulated with a finer time step (internal 8 kHz) from known true
parameters and irregularity; the twin, given that truth, must reproduce the measured channels.
"""
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.bag_reader import BagReader
from maglev_ros.errors import UserError
from maglev_ros.twin.online import OnlineTwin, nrmse
from maglev_ros.twin.simulate import simulate, truth_paths
from rosgraph import domain_id

ROOT = Path(__file__).resolve().parents[1]
QUIET = ["instrument.anti_alias=none", "instrument.guideway_accel.noise_rms=0",
         "instrument.guideway_displacement.noise_rms=0", "instrument.vehicle_accel.noise_rms=0",
         "instrument.vehicle_gap.noise_rms=0"]
BASE = ["line.n_spans=3", "lead_in_s=0.5", "free_decay_s=1.0", "speed_mps=15",
        "rates.guideway_hz=2000", "rates.vehicle_hz=2000", "rates.oversample=4"]


@pytest.fixture(scope="module")
def quiet_pass(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "quiet"
    simulate("paper", out, sets=BASE + QUIET, seed=11)
    tj, ic = truth_paths(out)
    truth = json.loads(tj.read_text())
    irr = np.genfromtxt(ic, delimiter=",", names=True)
    with BagReader(out) as r:
        md = r.metadata
        items = list(r.iter_blocks())
    params = {f"{sec}.{k}": v for sec, d in truth["truth_design"].items() for k, v in d.items()
              if isinstance(v, (int, float))}
    return out, md, items, params, (irr["position_m"], irr["elevation_m"])


def _by_group(outs):
    R, M = defaultdict(list), defaultdict(list)
    for o in outs:
        cols = [o.measured.channels.index(c) for c in o.predicted.channels]
        assert o.predicted.stamp_ns == o.measured.stamp_ns == o.residual.stamp_ns
        assert o.predicted.sample_rate_hz == o.measured.sample_rate_hz
        assert o.predicted.units == tuple(o.measured.units[c] for c in cols)
        R[o.group].append(o.residual.data)
        M[o.group].append(o.measured.data[:, cols])
    return {g: (np.concatenate(R[g]), np.concatenate(M[g])) for g in R}


def test_twin_with_true_parameters_and_irregularity_reproduces_the_pass(quiet_pass):
    _out, md, items, params, irr = quiet_pass
    # the generator's internal step (8 kHz): with no anti-alias filter the recording holds the girder's
    # modes up to 2 kHz, folded; a twin reproduces them sample by sample only at that step
    tw = OnlineTwin(md, irregularity=irr, parameters=params, dt_max_s=1.25e-4)
    outs = tw.feed(items)
    n_meas = defaultdict(int)
    for topic, _b in items:
        n_meas[topic] += 1
    groups = _by_group(outs)
    # one prediction + residual per measured block of every group
    assert {g: len([o for o in outs if o.group == g]) for g in groups} == {
        "guideway_accel": n_meas["/testline/guideway/accel"],
        "guideway_displacement": n_meas["/testline/guideway/displacement"],
        "vehicle_accel": n_meas["/testline/vehicle/accel"], "vehicle_gap": n_meas["/testline/vehicle/gap"]}
    for g, (res, meas) in groups.items():
        e = nrmse(res, meas)
        assert np.all(e < 0.05), (g, e)
    assert tw.n_resync == 0


def test_nominal_twin_misses_and_adopting_truth_fixes_it(quiet_pass):
    _out, md, items, params, irr = quiet_pass
    nominal = _by_group(OnlineTwin(md, irregularity=irr).feed(items))
    e_nom = nrmse(*nominal["guideway_displacement"])[0]
    assert e_nom > 0.05                        # nominal (softer) design: visibly wrong deflection
    tw = OnlineTwin(md, irregularity=irr)
    half = len(items) // 2
    first = tw.feed(items[:half])
    adopted = tw.set_parameters(list(params), list(params.values()))
    assert adopted["guideway.youngs_modulus_pa"] == params["guideway.youngs_modulus_pa"]
    assert tw.revision == 1
    later = _by_group(tw.feed(items[half:]))
    res, meas = later["guideway_displacement"]
    tail = slice(len(res) // 3, None)          # after the restart transient
    assert nrmse(res[tail], meas[tail])[0] < 0.3 * e_nom
    assert first
    with pytest.raises(UserError, match="warp"):
        tw.set_parameters(["warp.factor"], [1.0])
    with pytest.raises(UserError, match="youngs_modulus_pa"):
        tw.set_parameters(["guideway.youngs_modulus_pa"], [-1.0])
    tw.set_parameters(["spans.S2.bearing_stiffness_n_per_m"], [2.0e10])
    assert tw.spans[1]["bearing_stiffness_n_per_m"] == 2.0e10


def test_random_irregularity_never_judges_the_vehicle_and_a_topic_profile_does(quiet_pass):
    _out, md, items, params, irr = quiet_pass
    outs = OnlineTwin(md, parameters=params, irregularity_source="random", seed=3).feed(items)
    veh = [o for o in outs if o.group.startswith("vehicle")]
    assert veh and not any(o.valid for o in veh)
    assert all(np.isnan(o.residual.data).all() for o in veh)
    assert all(o.valid for o in outs if o.group.startswith("guideway"))
    tw2 = OnlineTwin(md, parameters=params, irregularity_source="topic")
    x, r = irr
    assert tw2.set_irregularity_profile(x[0], x[1] - x[0], r)
    outs2 = tw2.feed(items)
    valid = [o for o in outs2 if o.group == "vehicle_gap" and o.valid]
    assert len(valid) > 0.5 * len([o for o in outs2 if o.group == "vehicle_gap"])
    res = np.concatenate([o.residual.data for o in valid])
    meas = np.concatenate([o.measured.data for o in valid])
    assert np.all(nrmse(res, meas) < 0.05)
    # the twin measuring its own profile ignores the irregularity node's message
    assert not OnlineTwin(md).set_irregularity_profile(x[0], x[1] - x[0], r)


def test_ambient_record_residual_is_the_measured_vibration(tmp_path):
    res = simulate("paper-ambient", tmp_path / "amb", sets=["duration_s=3"])
    with BagReader(res.bag) as r:
        md, items = r.metadata, list(r.iter_blocks())
    outs = OnlineTwin(md).feed(items)
    assert len(outs) == len(items)
    pred = np.concatenate([o.predicted.data for o in outs])
    meas = np.concatenate([o.measured.data for o in outs])
    assert np.max(np.abs(pred)) < 1e-9
    np.testing.assert_allclose(np.concatenate([o.residual.data for o in outs]), meas, atol=1e-7)


PROBE = r'''
import json, sys, time
import rclpy
from rclpy.node import Node
from rclpy.experimental import EventsExecutor
from maglev_msgs.msg import SensorBlock
from maglev_ros.nodes._common import QOS_STREAM
out, timeout, expect = sys.argv[1], float(sys.argv[2]), json.loads(sys.argv[3])
rclpy.init()
node = Node("twin_probe")
rec = {t: [] for t in expect}
def cb(topic):
    def f(msg):
        rec[topic].append([msg.header.stamp.sec * 1000000000 + msg.header.stamp.nanosec, list(msg.channels),
                           len(msg.data), all(v == v for v in msg.data)])
    return f
for t in expect:
    node.create_subscription(SensorBlock, t, cb(t), QOS_STREAM)
ex = EventsExecutor(); ex.add_node(node)
end = time.monotonic() + timeout
while time.monotonic() < end and any(len(rec[t]) < n for t, n in expect.items()):
    ex.spin_once(timeout_sec=0.05)
json.dump(rec, open(out, "w"))
ex.shutdown(); node.destroy_node(); rclpy.try_shutdown()
'''


@pytest.mark.ros
def test_twin_node_publishes_prediction_for_every_block_and_only_valid_residuals(quiet_pass, tmp_path):
    bag, md, items, _params, _irr = quiet_pass
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id(150))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    groups = {"/testline/guideway/accel": "guideway_accel", "/testline/guideway/displacement": "guideway_displacement",
              "/testline/vehicle/accel": "vehicle_accel", "/testline/vehicle/gap": "vehicle_gap"}
    measured = defaultdict(list)
    for topic, b in items:
        if topic in groups:
            measured[groups[topic]].append(b.stamp_ns)
    expect = {}
    for g, stamps in measured.items():
        expect[f"/maglev/twin/predicted/{g}"] = len(stamps)
        # vehicle residuals only where the measured irregularity covers every magnet
        expect[f"/maglev/twin/residual/{g}"] = 0 if g.startswith("vehicle") else len(stamps)
    (tmp_path / "probe.py").write_text(PROBE)
    out = tmp_path / "probe.json"
    twin = subprocess.Popen([sys.executable, "-m", "maglev_ros.nodes.twin", "--ros-args", "-p", "seed:=1"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    probe = subprocess.Popen([sys.executable, str(tmp_path / "probe.py"), str(out), "90", json.dumps(expect)], env=env)
    try:
        rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--rate", "5",
                              "--wait-subscribers", "1", "--quiet"], env=env, capture_output=True, text=True,
                             timeout=120)
        assert rep.returncode == 0, rep.stderr
        probe.wait(timeout=100)
    finally:
        for p in (probe, twin):
            if p.poll() is None:
                p.terminate()
        try:
            twin_log = twin.communicate(timeout=20)[0]
        except subprocess.TimeoutExpired:
            twin.kill()
            twin_log = twin.communicate()[0]
    rec = json.loads(out.read_text())
    for g, stamps in measured.items():
        for kind in ("predicted", "residual"):
            got = rec[f"/maglev/twin/{kind}/{g}"]
            if kind == "residual" and g.startswith("vehicle"):
                assert set(s for s, *_ in got) <= set(stamps) and all(f for *_, f in got), (g, twin_log[-2000:])
            else:
                assert [s for s, *_ in got] == stamps, (kind, g, twin_log[-2000:])
    ch = rec["/maglev/twin/predicted/guideway_accel"][0][1]
    assert ch == list(md.sensors_on_topic("/testline/guideway/accel"))
