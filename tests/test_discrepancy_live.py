"""The live diagnosis is the offline one: recordings assembled from the stream equal the bags'
recordings, and the discrepancy node's report equals `diagnose` on the same bags."""
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from discrepancy_cases import make_case, report_science, write_case_bags  # noqa: E402
from rosgraph import ros_env, stop_processes  # noqa: E402

from maglev_ros.bag_reader import BagReader  # noqa: E402
from maglev_ros.discrepancy.diagnose import DiagnoseConfig, diagnose  # noqa: E402
from maglev_ros.discrepancy.live import RecordingAssembler, diagnosis_events  # noqa: E402
from maglev_ros.discrepancy.recording import load_recording  # noqa: E402

HERE = Path(__file__).resolve().parent
SAMPLE = HERE.parent / "bags"


def _stream(paths):
    """Every bag's metadata and blocks, in order, as the replay publishes them."""
    for p in paths:
        with BagReader(p) as b:
            yield "metadata", b.metadata.raw
            yield from b.iter_blocks()


def _same_recording(a, b):
    assert list(a.channels) == list(b.channels) and a.kind == b.kind       # in the same order too
    for n in b.channels:
        assert np.array_equal(a.channels[n].time_s, b.channels[n].time_s)
        assert np.array_equal(a.channels[n].values, b.channels[n].values)
    for k in ("position_time_s", "position_m", "speed_mps"):
        assert np.array_equal(getattr(a, k), getattr(b, k))


def test_recordings_assembled_from_the_stream_equal_the_bags():
    bags = [SAMPLE / "paper_ambient", SAMPLE / "paper_pass"]
    asm, got = RecordingAssembler(), []
    for topic, item in _stream(bags):
        if topic == "metadata":
            done = asm.set_metadata(item)
            got += [done] if done is not None else []
        else:
            asm.add_block(topic, item)
    got.append(asm.finish())
    assert [r.kind for r in got] == ["ambient", "pass"] and asm.finish() is None
    # whichever topic's block arrives first, the channels come in the bag reader's order
    asm = RecordingAssembler()
    items = list(_stream([SAMPLE / "paper_pass"]))
    asm.set_metadata(items[0][1])
    for topic, item in reversed(items[1:]):
        asm.add_block(topic, item)
    _same_recording(asm.finish(), load_recording(SAMPLE / "paper_pass"))
    for r, p in zip(got, bags):
        _same_recording(r, load_recording(p))


def test_report_entries_become_mismatch_events():
    rep = {"missing_physics": [{"effect": "bearing_stiffness", "category": "boundary_condition",
                                "explanation": "x", "location": {"position_m": [21.6, 27.8], "channels": []},
                                "frequency_hz": None, "evidence": {"heldout_nrmse_before": 0.4,
                                                                   "heldout_nrmse_after": 0.2}}],
           "mismatches": [{"channels": ["G1A"], "time_s": [1.0, 2.0], "position_m": None,
                           "frequency_hz": [10.0, 20.0], "severity": 3.0}]}
    ev = diagnosis_events(rep)
    assert [e["effect"] for e in ev] == ["bearing_stiffness", ""]
    assert ev[0]["position_m"] == [21.6, 27.8] and ev[0]["severity"] == pytest.approx(2.0)
    assert np.isnan(ev[0]["frequency_hz"]).all() and np.isnan(ev[1]["position_m"]).all()
    assert ev[1]["frequency_hz"] == [10.0, 20.0] and ev[1]["severity"] == 3.0


@pytest.fixture(scope="module")
def live_case(tmp_path_factory):
    """A small sensor-fault case (two bags) and its offline diagnosis, computed on a thread while the
    tests run the node (both tests compare with the same report)."""
    case = make_case("live", "sensor_error", {"channel": "G2A", "kind": "scale", "value": 1.4}, seed=11,
                     speeds=(24.0, 30.0), variant={"n_el": 20, "noise_colour": "white", "ambient_s": 8.0},
                     n_spans=2)
    amb, passes = write_case_bags(case, tmp_path_factory.mktemp("live") / "bags")
    cfg = DiagnoseConfig(n_top=1, fit_every_effect=False)      # fewer hypotheses: a quicker test
    pool = ThreadPoolExecutor(1)
    offline = pool.submit(lambda: diagnose([load_recording(passes[0])], load_recording(amb), cfg).to_dict())
    yield amb, passes[0], offline
    pool.shutdown(wait=False, cancel_futures=True)


def _check_live_report(got, offline, log_text):
    assert len(got["/maglev/diagnosis"]) == 1, log_text
    live = json.loads(got["/maglev/diagnosis"][0]["data"])
    assert live["schema"] == "maglev-diagnosis/1"
    assert report_science(live) == report_science(offline.result(timeout=400))
    # one report per finding, with the physics named
    named = [m for m in got["/maglev/mismatch"] if m["effect"]]
    assert [m["effect"] for m in named] == [m["effect"] for m in live["missing_physics"]]


@pytest.mark.ros
@pytest.mark.slow
def test_the_node_diagnoses_a_replayed_pass_as_the_offline_command_does(tmp_path, live_case):
    """A live stream without the replay's events: a pause ends a recording. Slow (70 s): the graph
    protocol test below checks the same report equality and is what the graph runs by."""
    amb, pass_bag, offline = live_case
    env = ros_env(60)
    log = open(tmp_path / "node.log", "w")
    node = subprocess.Popen([sys.executable, "-m", "maglev_ros.nodes.discrepancy", "--ros-args",
                             "-p", "n_top:=1", "-p", "fit_every_effect:=false", "-p", "recording_idle_s:=1.0"],
                            env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
    out = tmp_path / "got.json"
    coll = subprocess.Popen([sys.executable, str(HERE / "ros_collect.py"), str(out), "400", "2",
                             "std_msgs/msg/String:/maglev/diagnosis",
                             "maglev_msgs/msg/MismatchReport:/maglev/mismatch"], env=env)
    try:
        time.sleep(1.0)
        for bag in (amb, pass_bag):
            r = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", bag, "--fast", "--quiet",
                                "--wait-subscribers", "1"], env=env, capture_output=True, text=True, timeout=120)
            assert r.returncode == 0, r.stderr
            time.sleep(2.5)          # the node sees the recording end (idle 1 s) before the next one
        offline.result(timeout=400)
        coll.wait(timeout=420)
    finally:
        stop_processes(node, coll)
    got = json.loads(out.read_text())
    log.close()
    _check_live_report(got, offline, (tmp_path / "node.log").read_text())


@pytest.mark.ros
def test_under_the_graph_protocol_the_report_is_out_when_the_node_says_done(tmp_path, live_case):
    """Recordings end at the replay's recording_end (no idle wait); the node says done only once
    the diagnosis and its MismatchReports are published, so they are in when the driver goes on."""
    amb, pass_bag, offline = live_case
    env = ros_env(100)
    log = open(tmp_path / "node.log", "w")
    node = subprocess.Popen([sys.executable, "-m", "maglev_ros.nodes.discrepancy", "--ros-args",
                             "-p", "n_top:=1", "-p", "fit_every_effect:=false"],
                            env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
    done, out = tmp_path / "driver.json", tmp_path / "got.json"
    coll = subprocess.Popen([sys.executable, str(HERE / "ros_collect.py"), str(out), "600", f"until:{done}",
                             "std_msgs/msg/String:/maglev/diagnosis",
                             "maglev_msgs/msg/MismatchReport:/maglev/mismatch"], env=env)
    try:
        drv = subprocess.run([sys.executable, str(HERE / "protocol_driver.py"), str(done), "500", "discrepancy",
                              "1", str(amb), str(pass_bag)], env=env, capture_output=True, text=True, timeout=600)
        coll.wait(timeout=60)
    finally:
        stop_processes(node, coll)
    log.close()
    report = json.loads(done.read_text())
    assert drv.returncode == 0 and report["ok"], (report, (tmp_path / "node.log").read_text()[-3000:])
    assert report["statuses"]["discrepancy"]["done"] == 1
    _check_live_report(json.loads(out.read_text()), offline, (tmp_path / "node.log").read_text())


def test_a_stream_in_g_is_assembled_in_si_as_the_bag_readers_do():
    import dataclasses
    from maglev_ros.contract import unit_conversion
    g = unit_conversion("g")[1]
    asm = RecordingAssembler()
    for topic, item in _stream([SAMPLE / "paper_pass"]):
        if topic == "metadata":
            asm.set_metadata(item)
            continue
        if topic == "/testline/vehicle/accel":
            item = dataclasses.replace(item, units=("g",) * len(item.channels),
                                       data=(np.asarray(item.data, np.float64) / g).astype(np.float32))
        asm.add_block(topic, item)
    rec, ref = asm.finish(), load_recording(SAMPLE / "paper_pass")
    for n, c in ref.channels.items():
        # float32 samples in g: the SI values to float32 rounding
        np.testing.assert_allclose(rec.channels[n].values, c.values, rtol=1e-6, atol=1e-6 * np.abs(c.values).max())
