"""End to end over a real ROS 2 graph: the replay node in one process, a subscriber in another.

Every block must arrive once, in order, with stamps and payload intact; the latched metadata
must reach the (late-joining) subscriber; /clock must drive a ``use_sim_time`` node.
"""
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.bag_writer import BagWriter
from maglev_ros.sensor_block import Block
from rosgraph import domain_id

pytestmark = pytest.mark.ros
HERE = Path(__file__).resolve().parent
T0_NS = 1_700_000_000_123_456_789


def _metadata(n_ch):
    sensors = {f"G{i}": {"topic": "/testline/guideway/accel", "quantity": "acceleration",
                         "direction": "vertical", "span": "S1", "position_m": 1.5 * i,
                         "side": "left"} for i in range(n_ch)}
    sensors["position_m"] = {"topic": "/testline/vehicle/position", "quantity": "position"}
    sensors["speed_mps"] = {"topic": "/testline/vehicle/position", "quantity": "speed"}
    return {"schema": "maglev-testline/1", "line": {"spans": [{"id": "S1", "start_m": 0.0,
            "length_m": 24.768}]}, "sensors": sensors,
            "vehicle": {"magnet_offsets_m": [0.0, -1.548], "nominal_gap_m": 0.01},
            "run": {"kind": "pass", "nominal_speed_mps": 6.944}}


@pytest.fixture()
def ros_env(tmp_path):
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id(100))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONPATH"] = str(HERE.parent) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _write_bag(path, n_blocks=300, n_ch=17, fs=2000.0, block_n=200, seed=1):
    rng = np.random.default_rng(seed)
    meta = _metadata(n_ch)
    chans = tuple(f"G{i}" for i in range(n_ch))
    expected = {"/testline/guideway/accel": [], "/testline/vehicle/position": []}
    with BagWriter(path, meta) as w:
        for k in range(n_blocks):
            stamp = T0_NS + int(round(k * block_n / fs * 1e9))
            d = rng.standard_normal((block_n, n_ch)).astype(np.float32)
            w.write_block("/testline/guideway/accel",
                          Block(stamp, "guideway", fs, chans, ("m/s^2",) * n_ch, d))
            expected["/testline/guideway/accel"].append((stamp, hashlib.sha256(d.tobytes()).hexdigest()))
            if k % 2 == 0:  # position at 100 Hz in 0.2 s blocks
                pos = np.column_stack([np.linspace(0, 1, 20) + k, np.full(20, 6.944)]).astype(np.float32)
                w.write_block("/testline/vehicle/position",
                              Block(stamp, "vehicle", 100.0, ("position_m", "speed_mps"),
                                    ("m", "m/s"), pos))
                expected["/testline/vehicle/position"].append(
                    (stamp, hashlib.sha256(pos.tobytes()).hexdigest()))
    return meta, expected


def test_replay_delivers_every_block_once_in_order_and_drives_sim_time(tmp_path, ros_env):
    bag = tmp_path / "rec"
    meta, expected = _write_bag(bag)
    out = tmp_path / "probe.json"
    topics = list(expected)
    probe = subprocess.Popen([sys.executable, str(HERE / "ros_probe.py"), str(out), "60", *topics],
                             env=ros_env)
    try:
        rep = subprocess.run(
            [sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--rate", "50",
             "--quiet", "--wait-subscribers", "1"],
            env=ros_env, capture_output=True, text=True, timeout=120)
        assert rep.returncode == 0, rep.stderr
        probe.wait(timeout=90)
    finally:
        if probe.poll() is None:
            probe.kill()
    rec = json.loads(out.read_text())
    for topic, exp in expected.items():
        got = rec["blocks"][topic]
        assert [(b["stamp_ns"], b["sha"]) for b in got] == exp, topic  # once, in order, intact
    assert json.loads(rec["metadata"]) == meta                        # latched metadata arrived
    g = rec["blocks"]["/testline/guideway/accel"][0]
    assert g["rate"] == 2000.0 and g["units"] == ["m/s^2"] * 17 and g["n"] == 200 * 17
    # /clock: monotonic, spans the recording, and the use_sim_time node's clock follows it
    clock = np.array(rec["clock"], dtype=np.int64)
    assert clock.size > 10 and np.all(np.diff(clock) >= 0)
    assert clock[0] >= T0_NS and clock[-1] >= expected["/testline/guideway/accel"][-1][0]
    sim = np.array([b["sim_now_ns"] for b in rec["blocks"]["/testline/guideway/accel"]])
    stamps = np.array([s for s, _ in expected["/testline/guideway/accel"]])
    assert np.all(sim > 0)                          # sim time came from /clock, not wall time
    assert np.median(np.abs(sim - stamps)) < 0.5e9  # and tracks the data stamps (bag time)


def test_echo_prints_blocks_from_a_replay(tmp_path, ros_env):
    bag = tmp_path / "rec"
    _write_bag(bag, n_blocks=60)
    echo = subprocess.Popen([sys.executable, "-m", "maglev_ros.cli", "echo",
                             "/testline/vehicle/position", "--count", "3", "--timeout", "60"],
                            env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag),
                              "--rate", "10", "--quiet", "--wait-subscribers", "1"],
                             env=ros_env, capture_output=True, text=True, timeout=120)
        assert rep.returncode == 0, rep.stderr
        out, err = echo.communicate(timeout=60)
    finally:
        if echo.poll() is None:
            echo.kill()
    assert echo.returncode == 0, err
    assert out.count("SensorBlock vehicle") == 3
    assert "speed_mps [m/s] mean=+6.944" in out


def test_replay_rejects_a_rate_outside_range_in_one_line(tmp_path, ros_env):
    bag = tmp_path / "rec"
    _write_bag(bag, n_blocks=4)
    rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--rate", "500"],
                         env=ros_env, capture_output=True, text=True, timeout=60)
    assert rep.returncode == 1
    assert rep.stderr.strip().count("\n") == 0 and "rate 500" in rep.stderr
    assert "Traceback" not in rep.stderr


def test_replay_missing_bag_is_one_line_error(tmp_path, ros_env):
    rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(tmp_path / "nope")],
                         env=ros_env, capture_output=True, text=True, timeout=60)
    assert rep.returncode == 1 and "no such bag" in rep.stderr and "Traceback" not in rep.stderr
