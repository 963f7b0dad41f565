"""The graph's run protocol over a real ROS 2 graph (maglev_ros.nodes._lifecycle): a replay of two
short generated recordings waits for a node's results after each one (events in order, counts in
``recording_end``), the summary node counts each recording and ends on ``finished``, and a node
that never becomes ready or done makes the replay warn and go on after its timeouts.

Two graphs run side by side (their own domains) to keep the file short on a loaded machine."""
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bagfactory import (VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, GUIDEWAY_ACCEL, example_topics,
                        make_metadata, write_contract_bag)
from rosgraph import HERE, stop_processes

pytestmark = pytest.mark.ros

BLOCK_S = 0.1


def _env(base: int) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(base + os.getpid() % 15), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def _recordings(tmp: Path) -> list[tuple[Path, dict]]:
    """Recording 0 lacks the gap and position topics that recording 1 has (new writers mid-run)."""
    out = []
    for k, (duration_s, names) in enumerate([(1.0, (GUIDEWAY_ACCEL, VEHICLE_ACCEL)),
                                             (1.5, (GUIDEWAY_ACCEL, VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION))]):
        topics = {t: v for t, v in example_topics(duration_s=duration_s, seed=k).items() if t in names}
        path = write_contract_bag(tmp / f"rec{k}", make_metadata(topics), topics, block_s=BLOCK_S)
        # blocks of round(BLOCK_S * rate) samples over round(duration * rate) samples, plus the metadata
        counts = {t: math.ceil(round(duration_s * v[2]) / round(BLOCK_S * v[2])) for t, v in topics.items()}
        counts["/testline/metadata"] = 1
        out.append((path, counts))
    return out


def _node(env, module_or_script, params, log_file):
    return subprocess.Popen([sys.executable, *module_or_script, "--ros-args", *params], env=env,
                            stdout=log_file, stderr=subprocess.STDOUT, text=True)


def _replay(env, bags, wait_nodes, extra=()):
    return subprocess.Popen([sys.executable, "-m", "maglev_ros.cli", "replay", *map(str, bags), "--rate", "4",
                             "--quiet", "--wait-nodes", *wait_nodes, "--ros-args", *extra],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("protocol")
    recs = _recordings(tmp)
    probe = [str(HERE / "protocol_probe.py")]
    good, stuck = _env(200), _env(215)
    logs = {name: open(tmp / f"{name}.out", "w") for name in ("probe", "summary", "stuck", "plain")}
    procs = []
    try:
        # graph 1: a probe whose results take 1 s, and the summary (reliable, as the demo runs it)
        procs.append(_node(good, probe, ["-p", f"log:={tmp / 'probe.jsonl'}", "-p", "delay_s:=1.0"],
                           logs["probe"]))
        procs.append(_node(good, ["-m", "maglev_ros.nodes.summary"],
                           ["-p", f"json_out:={tmp / 'summary.json'}", "-p", "reliable:=true",
                            "-p", "idle_s:=0.3", "-p", "settle_s:=0.5"], logs["summary"]))
        summary = procs[-1]
        # graph 2: a probe that never becomes ready nor done, and a node outside the protocol
        procs.append(_node(stuck, probe + ["-r", "__node:=stuck"],
                           ["-p", f"log:={tmp / 'stuck.jsonl'}", "-p", "stuck:=true"], logs["stuck"]))
        procs.append(_node(stuck, probe + ["-r", "__node:=plain"],
                           ["-p", f"log:={tmp / 'plain.jsonl'}", "-p", "protocol:=false"], logs["plain"]))
        # graph 2's replay has short timeouts: its nodes must be up (subscribed) before it starts
        deadline = time.monotonic() + 120
        while not all((tmp / f"{n}.jsonl").exists() for n in ("stuck", "plain")) and time.monotonic() < deadline:
            time.sleep(0.1)
        bags = [p for p, _ in recs]
        rep_good = _replay(good, bags, ["probe", "summary"], ["-p", "wait_timeout_s:=60.0"])
        rep_stuck = _replay(stuck, bags, ["stuck", "plain"],
                            ["-p", "wait_timeout_s:=1.5", "-p", "results_timeout_s:=1.5"])
        out_good, _ = rep_good.communicate(timeout=180)
        out_stuck, _ = rep_stuck.communicate(timeout=180)
        summary.wait(timeout=60)            # it ends by itself once the replay said finished
    finally:
        stop_processes(*procs)
        for f in logs.values():
            f.close()

    def lines(name):
        path = tmp / f"{name}.jsonl"
        return [json.loads(ln) for ln in path.read_text().splitlines()] if path.exists() else []
    return {"recs": recs, "good": (rep_good.returncode, out_good), "stuck": (rep_stuck.returncode, out_stuck),
            "probe": lines("probe"), "stuck_log": lines("stuck"), "summary": json.loads((tmp / "summary.json").read_text()),
            "summary_code": summary.returncode, "summary_out": (tmp / "summary.out").read_text()}


def test_replay_waits_for_each_recordings_results_before_going_on(runs):
    code, out = runs["good"]
    assert code == 0, out
    assert "did not say done" not in out and "starting anyway" not in out, out
    order = [(e["what"], e.get("event"), e["index"]) for e in runs["probe"] if e["what"] != "up"]
    # the node's result for a recording comes before the next recording starts, and before the end
    assert order == [("event", "recording_start", 0), ("event", "recording_end", 0), ("result", None, 0),
                     ("event", "recording_start", 1), ("event", "recording_end", 1), ("result", None, 1),
                     ("event", "finished", 1)], order


def test_recording_end_carries_the_messages_published_per_topic(runs):
    ends = [e for e in runs["probe"] if e.get("event") == "recording_end"]
    assert [e["messages"] for e in ends] == [counts for _, counts in runs["recs"]]
    # the node took every block of the recording before it heard of the end
    results = [e for e in runs["probe"] if e["what"] == "result"]
    assert [r["blocks"] for r in results] == [counts[VEHICLE_ACCEL] for _, counts in runs["recs"]]
    finished = [e for e in runs["probe"] if e.get("event") == "finished"][0]
    assert finished["messages"][GUIDEWAY_ACCEL] == sum(c[GUIDEWAY_ACCEL] for _, c in runs["recs"])


def test_summary_counts_each_recording_and_ends_when_the_replay_finished(runs):
    s = runs["summary"]
    assert runs["summary_code"] == 0, runs["summary_out"][-2000:]
    # not on its 0.3 s idle timer: the probe's 1.5 s of work after each recording had no traffic
    assert s["ended_by"] == "finished" and s["finished"], s
    assert [r["received"] for r in s["recordings"]] == [
        {t: n for t, n in counts.items()} for _, counts in runs["recs"]]
    assert [r["published"] for r in s["recordings"]] == [counts for _, counts in runs["recs"]]
    assert s["topics"]["/maglev/probe"]["messages"] == 2          # both results came before its end
    assert s["nodes"]["probe"]["done"] == 1


def test_summary_digest_is_that_of_the_recorded_messages(runs):
    """The summary's digest of a topic is the digest rule applied to the bags' messages as read back
    with rosbags (what went through the graph is what was recorded)."""
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader

    from maglev_msgs.msg import SensorBlock
    from maglev_ros.nodes.summary import combined_digest, message_digest
    digests = []
    for path, _ in runs["recs"]:
        with Reader(path) as r:
            conns = [c for c in r.connections if c.topic == VEHICLE_ACCEL]
            digests += [message_digest(VEHICLE_ACCEL, "maglev_msgs/msg/SensorBlock", deserialize_message(raw, SensorBlock))
                        for _, _, raw in r.messages(connections=conns)]
    assert runs["summary"]["topics"][VEHICLE_ACCEL]["digest"] == combined_digest(digests)


def test_digest_leaves_out_the_wall_clock_and_sees_any_value():
    """Two publications of the same parameters at different wall times digest alike; a changed value
    or a changed key of the provenance does not; nor does the CDR's uninitialised padding matter."""
    from rclpy.serialization import deserialize_message, serialize_message

    from maglev_msgs.msg import TwinParameters
    from maglev_ros.nodes.summary import message_digest

    def params(stamp_s, time_unix_s, kp=7046.5, fit=0.05):
        m = TwinParameters()
        m.header.stamp.sec = stamp_s
        m.revision, m.names, m.values, m.std = 4, ["kp_a_per_m"], [kp], [float("nan")]
        m.provenance_json = json.dumps({"time_unix_s": time_unix_s, "fit": {"nrmse": fit, "wall_time_s": time_unix_s}})
        # through CDR bytes, as a subscriber gets it
        return deserialize_message(serialize_message(m), TwinParameters)

    def digest(m):
        return message_digest("/maglev/twin/parameters", "maglev_msgs/msg/TwinParameters", m)
    same = digest(params(10, 1.8e9))
    assert digest(params(99, 1.9e9)) == same
    assert digest(params(10, 1.8e9, kp=7046.6)) != same
    assert digest(params(10, 1.8e9, fit=0.06)) != same


def test_a_node_never_ready_nor_done_is_named_and_the_replay_goes_on(runs):
    code, out = runs["stuck"]
    assert code == 0, out
    assert "waited 1.5 s for stuck to be ready (warm); starting anyway" in out, out
    for k in (0, 1):
        assert f"recording {k}: stuck did not say done within 1.5 s" in out, out
    assert "plain: no run-protocol status" in out, out
    assert "did not say done" not in out.replace("stuck did not say done", ""), out
    # the stuck node still got both recordings and the end of the run
    events = [(e["event"], e["index"]) for e in runs["stuck_log"] if e["what"] == "event"]
    assert events == [("recording_start", 0), ("recording_end", 0), ("recording_start", 1),
                      ("recording_end", 1), ("finished", 1)], events
