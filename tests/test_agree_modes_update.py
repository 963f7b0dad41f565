"""Online equals offline: what modal_id and updater publish at the end of each recording is what
``maglev-ros modes`` and ``maglev-ros update`` give on the replayed bags.

The nodes get the recordings through a real graph (``maglev-ros replay`` of an ambient then a pass
bag, the recording ends announced by the graph run protocol, tests/graph_probe.py); the verbs run
here on the same bags. The samples reach the nodes as the bags hold them (float32, the recorded
CDR bytes) and both sides run the same functions on them, so the comparison is for identical
floats: mode frequencies, damping, their stds, MPC and shapes with ==; the updated parameters with
a relative 1e-9 (the same pipeline in another process: numba or BLAS may order a sum otherwise;
measured difference 0 here, where nodes and verbs run with the same BLAS threads, tests/conftest.py;
with another thread count the update itself moves by ~1e-7: kp 7046.5348 with one OpenBLAS
thread, 7046.5358 with the default, on bags/paper_*). The sample-bag test runs the update with
small swarms and samples (the verb's options, given to both sides alike: the rule is the same,
the cost a quarter; the gains then end at a bound of their range, which both sides reach); the slow
tests run the verb's defaults on the sample bags and on three partner-sim cases.
"""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from frame_data import PARTNER_SIM as PARTNER
from rosgraph import ros_env, stop_processes

HERE = Path(__file__).resolve().parent
BAGS = HERE.parent / "bags"
AMBIENT, PASS = BAGS / "paper_ambient", BAGS / "paper_pass"
# the verb's options for the cheap run, and the updater's parameters that set the same
QUICK = {"samples": 8, "polish_evals": 1, "swarm": [6, 6]}
# what the two nodes subscribe (the probe pads every topic to one count for the replay's wait)
SUBSCRIBERS = {"/testline/guideway/accel": 2, "/testline/vehicle/position": 2,
               "/testline/guideway/displacement": 1, "/testline/vehicle/accel": 1,
               "/testline/vehicle/gap": 1}
REL = 1e-9

pytestmark = pytest.mark.ros


def _node_params(settings: dict | None, history: Path) -> dict:
    upd = ["-p", f"history_path:={history}"]
    if settings:
        upd += ["-p", f"end_samples:={settings['samples']}", "-p", f"end_polish_evals:={settings['polish_evals']}",
                "-p", "end_swarm:=[" + ",".join(str(x) for x in settings["swarm"]) + "]"]
    # the online tracker is not under test here: an update every 20 s of stream keeps it cheap
    return {"modal_id": ["-p", "update_s:=20.0"], "updater": upd}


def run_graph(tmp: Path, bags, settings: dict | None, domain: int) -> dict:
    """modal_id + updater as processes; the bags replayed in order; what they published."""
    env = ros_env(domain)
    params = _node_params(settings, tmp / "history.jsonl")
    procs = [subprocess.Popen([sys.executable, "-m", f"maglev_ros.nodes.{n}", "--ros-args", *params[n]], env=env,
                              stdout=open(tmp / f"{n}.log", "w"), stderr=subprocess.STDOUT)
             for n in ("modal_id", "updater")]
    spec = {"nodes": ["modal_id", "updater"], "subscribers": SUBSCRIBERS, "bags": [str(b) for b in bags],
            "collect": ["maglev_msgs/msg/ModalEstimate:/maglev/modes",
                        "maglev_msgs/msg/TwinParameters:/maglev/twin/parameters"], "timeout_s": 1500}
    (tmp / "spec.json").write_text(json.dumps(spec))
    try:
        probe = subprocess.run([sys.executable, str(HERE / "graph_probe.py"), str(tmp / "probe.json"),
                                str(tmp / "spec.json")], env=env, capture_output=True, text=True, timeout=3600)
        assert probe.returncode == 0, probe.stdout + probe.stderr
    finally:
        stop_processes(*procs)
    got = json.loads((tmp / "probe.json").read_text())
    got["history"] = [json.loads(x) for x in (tmp / "history.jsonl").read_text().splitlines()]
    got["logs"] = {n: (tmp / f"{n}.log").read_text() for n in ("modal_id", "updater")}
    return got


def verb_modes(bag: Path, out: Path) -> dict:
    from maglev_ros.cli import main
    assert main(["modes", str(bag), "--json", str(out)]) == 0
    return json.loads(out.read_text())


def verb_update(ambient: Path, passes, out: Path, settings: dict | None) -> dict:
    from maglev_ros.cli import main
    argv = ["update", "--ambient", str(ambient), *[a for p in passes for a in ("--pass", str(p))],
            "--out", str(out), "--quiet"]
    if settings:
        argv += ["--samples", str(settings["samples"]), "--polish-evals", str(settings["polish_evals"]),
                 "--swarm", *[str(x) for x in settings["swarm"]]]
    assert main(argv) == 0
    return json.loads(out.read_text())


def whole_recording_estimates(got: dict) -> list[dict]:
    """The modal_id node's end-of-recording estimates, in recording order."""
    return [m for m in got["topics"]["/maglev/modes"] if "whole recording" in m["method"]]


def parameters_after(got: dict, k: int) -> dict:
    """The last TwinParameters received by the end of recording k, by parameter name."""
    n = got["ends"][k]["counts"]["/maglev/twin/parameters"]
    assert n > 0, got["logs"]["updater"][-3000:]
    m = got["topics"]["/maglev/twin/parameters"][n - 1]
    return {name.split(".")[-1]: (v, s, ok) for name, v, s, ok in
            zip(m["names"], m["values"], m["std"], m["identifiable"])}


def assert_same_modes(msg: dict, doc: dict) -> None:
    """A ModalEstimate against a maglev-modes/1 document: the same modes, float for float."""
    live = [(m["id"], m["frequency_hz"], m["damping_ratio"], m["std_frequency_hz"], m["std_damping_ratio"],
             m["mpc"], dict(zip(m["channels"], m["mode_shape"]))) for m in msg["modes"]]
    off = [(m["id"], m["frequency_hz"], m["damping_ratio"], m["std_frequency_hz"], m["std_damping_ratio"],
            m["mpc"], m["mode_shape"]) for m in doc["modes"]]
    assert live == off
    assert all(m["status"] == "identified" for m in msg["modes"])


def assert_same_parameters(live: dict, doc: dict) -> float:
    """Every parameter of the verb's params.json in the published set: value and std within REL;
    returns the largest relative difference seen."""
    worst = 0.0
    for name, p in doc["parameters"].items():
        v, s, _ = live[name]
        worst = max(worst, abs(v / p["value"] - 1) if p["value"] else abs(v))
        if p["std"] is not None and s is not None:
            worst = max(worst, abs(s / p["std"] - 1) if p["std"] else abs(s))
        v, s, ok = live[name]
        assert v == pytest.approx(p["value"], rel=REL), name
        if p["std"] is None:
            assert s is None, name
        else:
            assert s == pytest.approx(p["std"], rel=REL), name
        assert ok == p["identifiable"], name
    return worst


def check_agreement(tmp: Path, ambient: Path, pas: Path, settings: dict | None, got: dict) -> dict:
    est = whole_recording_estimates(got)
    assert len(est) == 2, got["logs"]["modal_id"][-3000:]
    m_amb, m_pass = verb_modes(ambient, tmp / "modes_ambient.json"), verb_modes(pas, tmp / "modes_pass.json")
    assert_same_modes(est[0], m_amb)
    assert_same_modes(est[1], m_pass)
    assert est[0]["method"] == "ssi-cov whole recording"
    assert est[1]["method"] == "ssi-cov whole recording, free decay"
    p_amb = verb_update(ambient, [], tmp / "params_ambient.json", settings)
    p_pass = verb_update(ambient, [pas], tmp / "params.json", settings)
    try:
        worst = max(assert_same_parameters(parameters_after(got, 0), p_amb),
                    assert_same_parameters(parameters_after(got, 1), p_pass))
    except AssertionError as exc:       # what the updater did, for a failure seen on a busy machine
        raise AssertionError(f"{exc}\nreceived: {got['ends']}\n--- updater log ---\n"
                             f"{got['logs']['updater'][-6000:]}") from exc
    # the history holds the recording-end updates as accepted, the pass's last
    ends = [r for r in got["history"] if r["data_used"].get("kind") == "recording end"]
    assert [r["data_used"]["passes"] for r in ends] == [[], [str(pas)]]
    assert ends[-1]["parameters"]["kp_a_per_m"]["value"] == pytest.approx(
        p_pass["parameters"]["kp_a_per_m"]["value"], rel=REL)
    return {"modes": [[(m["frequency_hz"], m["damping_ratio"]) for m in e["modes"]] for e in est],
            "parameters": {n: v["value"] for n, v in p_pass["parameters"].items()},
            "max_rel_diff_parameters": worst}


def test_live_modes_and_update_equal_the_verbs_on_the_sample_bags(tmp_path):
    got = run_graph(tmp_path, [AMBIENT, PASS], QUICK, 60)
    print(json.dumps(check_agreement(tmp_path, AMBIENT, PASS, QUICK, got)))


@pytest.mark.slow
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("case", ["paper", "H01", "H02", "H08"])
def test_live_equals_the_verbs_with_their_defaults(tmp_path, case):
    """The verb's defaults (60 samples, full swarms): the sample bags and a clean, a bearing and a
    sensor case of the partner's simulator (../shared/validation/partner-sim)."""
    if case == "paper":
        ambient, pas = AMBIENT, PASS
    else:
        if not PARTNER.is_dir():
            pytest.skip(f"{PARTNER}: partner-sim recordings not present")
        ambient, pas = PARTNER / case / "ambient", PARTNER / case / "pass"
    got = run_graph(tmp_path, [ambient, pas], None, 70)
    figures = check_agreement(tmp_path, ambient, pas, None, got)
    print(f"{case}: {json.dumps(figures)}")


RECORDING_SCRIPT = r'''
import json, sys
import numpy as np
import rclpy
from std_msgs.msg import String
from maglev_msgs.msg import ModalEstimate, ModalMode
from maglev_ros.nodes._common import msg_from_block, stamp_to_msg
from maglev_ros.nodes._lifecycle import ReplayEvent
from maglev_ros.nodes.updater import UpdaterNode
from maglev_ros.sensor_block import Block

GA = "/testline/guideway/accel"
rclpy.init(args=["x", "--ros-args", "-p", "magnet_layer:=false"])
node = UpdaterNode()
ends, used = [], []
node._end_update = lambda ambient, passes: ends.append([str(b.path) for b in (ambient, *passes)])
node.core.take_modes_job = lambda modes, stamp: used.append(round(stamp, 3))   # the estimates the node hands on
md = json.loads(sys.argv[1])

def metadata(kind, name):
    node._on_metadata(String(data=json.dumps({**md, "run": {**md["run"], "kind": kind}, "description": name})))

def recording(t0_s):
    for k in range(10):                      # 10 blocks of 0.1 s at 100 Hz from t0_s
        b = Block(int(round((t0_s + 0.1 * k) * 1e9)), "g", 100.0, ("G3LV",), ("m/s^2",),
                  np.ones((10, 1), np.float32))
        node._recorded(GA)(msg_from_block(b))

def estimate(stamp_s):
    m = ModalEstimate()
    stamp_to_msg(int(round(stamp_s * 1e9)), m.header)
    m.method = "ssi-cov online"
    mm = ModalMode()
    mm.id, mm.status, mm.frequency_hz = "M1", "tracked", 23.5
    m.modes.append(mm)
    node._on_modes(m)

def event(kind, k, bag):
    node.lifecycle._on_event(String(data=ReplayEvent(kind, k, bag).to_json()))

event("recording_start", 0, "amb")
metadata("ambient", "ambient")
estimate(5.0)                                # before any block of a recording: counts
recording(100.0)
estimate(100.5)                              # within what came: counts
estimate(200.5)                              # outside: not of this recording
event("recording_end", 0, "amb")
estimate(100.7)                              # its recording has ended: dropped
event("recording_start", 1, "pass")
estimate(100.8)                              # the previous recording's, arriving late: dropped
recording(50.0)                              # the pass's blocks come before its metadata ...
estimate(100.9)                              # still the previous one's: dropped
estimate(50.5)                               # this one's: counts
event("recording_end", 1, "pass")            # ... and so does its end: it waits
waiting = node.busy() and node.closed
estimate(50.6)                               # ended: dropped
metadata("pass", "the pass")                 # the pass's metadata completes it, as a pass
while node.busy():
    pass
print(json.dumps({"used": used, "ends": ends, "waited": waiting, "closed": node.closed}))
node.destroy_node()
rclpy.try_shutdown()
'''


def test_updater_takes_each_recording_with_its_own_metadata_and_estimates(tmp_path):
    """DDS orders nothing across topics. An online estimate of the previous recording can reach the
    updater after the next one has begun (another node's output): the updater uses an estimate
    only while its recording is open and when its stamp lies within that recording's guideway
    data. A recording's latched metadata can come after its blocks and even after its end (seen
    once on a loaded machine: a pass was updated as an ambient recording): the end waits for it."""
    from bagfactory import make_metadata
    md = make_metadata({"/testline/guideway/accel": (("G3LV",),)}, kind="pass")
    p = subprocess.run([sys.executable, "-c", RECORDING_SCRIPT, json.dumps(md)], env=ros_env(75),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got == {"used": [5.0, 100.5, 50.5], "ends": [["amb"], ["amb", "pass"]], "waited": True,
                   "closed": True}
