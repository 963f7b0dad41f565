"""The MCAP recorder: schema texts, the file's life (partial name, rename, crash recovery), the
subscription QoS, and a real graph recorded and read back with rosbags and the mcap library."""
import dataclasses
import json
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from bagfactory import example_topics, make_metadata, write_contract_bag
from maglev_ros.sensor_block import MSG_NAMES, Block, block_to_msg, serialize, typestore

HERE = Path(__file__).resolve().parent
OURS = [f"maglev_msgs/msg/{n}" for n in MSG_NAMES]
STANDARD = ["std_msgs/msg/String", "diagnostic_msgs/msg/DiagnosticArray"]


def plain(x):
    """A rosbags message as nested dicts/lists (the shape tests/ros_collect.to_plain gives)."""
    if dataclasses.is_dataclass(x):       # the type's fields (not rosbags' constants, __msgtype__)
        return {name: plain(getattr(x, name)) for name, _ in typestore().fielddefs[x.__msgtype__][1]}
    if isinstance(x, np.ndarray):
        return [plain(v) for v in x.tolist()]
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def nested_types(store, msgtype, seen=None):
    """Every message type ``msgtype`` uses, recursively (from the type store's field defs)."""
    seen = set() if seen is None else seen
    for _, (kind, spec) in store.fielddefs[msgtype][1]:
        sub = spec if kind == 2 else (spec[0][1] if kind in (3, 4) and spec[0][0] == 2 else None)
        if isinstance(sub, str) and sub not in seen:
            seen.add(sub)
            nested_types(store, sub, seen)
    return seen


# ----------------------------------------------------------------------------- schema text
@pytest.mark.parametrize("msgtype", OURS + STANDARD)
def test_schema_text_is_the_msg_file_with_every_dependency_once(msgtype):
    from rosbags.typesys import get_types_from_msg

    from maglev_ros.msg_definitions import DELIMITER, message_definition, msg_file_text
    text = message_definition(msgtype)
    store = typestore()
    sections = text.split(f"\n{DELIMITER}\n")
    assert sections[0] == msg_file_text(msgtype)
    names = [s.split("\n", 1)[0] for s in sections[1:]]
    assert all(n.startswith("MSG: ") for n in names)
    qualified = {n[5:].replace("/", "/msg/", 1) if n.count("/") == 1 else n[5:] for n in names}
    assert len(names) == len(qualified) == len(nested_types(store, msgtype))
    assert qualified == nested_types(store, msgtype)
    # what rosbags (the reader Foxglove-like tools use here) parses from it is the type it knows
    parsed = get_types_from_msg(text, msgtype)
    for t in {msgtype} | qualified:
        assert [f[0] for f in parsed[t][1]] == [f[0] for f in store.fielddefs[t][1]], t


# ----------------------------------------------------------------------------- the file
def _sensorblock(stamp_ns, k):
    blk = Block.from_arrays(stamp_ns, 100.0, ("M1G", "M2G"), ("m", "m"),
                            np.full((4, 2), 0.01 + k, np.float32), "vehicle")
    return serialize(block_to_msg(blk), "SensorBlock")


def test_file_appears_whole_and_a_crash_leaves_a_recoverable_partial(tmp_path):
    from mcap.reader import make_reader

    from maglev_ros.mcap_recording import McapRecording, recover
    target = tmp_path / "out.mcap"
    rec = McapRecording(target, flush_period_s=1e-9).open()
    for k in range(3):
        rec.write("/maglev/twin/residual/vehicle_gap", "maglev_msgs/msg/SensorBlock",
                  _sensorblock(5_000_000_000 + k, k), log_time_ns=9_000_000_000 + k)
        assert rec.flush_if_due()
    rec.write("/maglev/twin/residual/vehicle_gap", "maglev_msgs/msg/SensorBlock", _sensorblock(7, 3), 8)
    assert not target.exists() and rec.partial.exists()
    # a crash now: the open chunk (4th message) and the summary never reach the file; a crash
    # while a chunk is written leaves it torn anywhere
    data = rec.partial.read_bytes()
    logs = [9_000_000_000, 9_000_000_001, 9_000_000_002]
    for n in [len(data)] + list(range(len(data) // 3, len(data), 11)):
        torn = tmp_path / "torn.partial"
        torn.write_bytes(data[:n])
        kept = recover(torn, tmp_path / "recovered.mcap")
        with open(tmp_path / "recovered.mcap", "rb") as f:
            msgs = [m for _, _, m in make_reader(f).iter_messages()]
        got = [m.log_time for m in msgs]
        assert got == logs[:len(got)] and kept.get("/maglev/twin/residual/vehicle_gap", 0) == len(got)
        if n == len(data):
            assert got == logs
            assert [m.publish_time for m in msgs] == [5_000_000_000 + k for k in range(3)]  # header stamps
    path = rec.close()
    assert path == target and target.exists() and not rec.partial.exists()
    with open(target, "rb") as f:
        r = make_reader(f)
        assert r.get_header().profile == "ros2"
        assert [m.log_time for _, _, m in r.iter_messages()] == [8] + logs


def test_target_directory_is_checked_first(tmp_path):
    from maglev_ros.errors import UserError
    from maglev_ros.mcap_recording import McapRecording
    with pytest.raises(UserError, match="does not exist"):
        McapRecording(tmp_path / "no" / "x.mcap", option="path").open()


# ------------------------------------------------------------------------------ QoS, names
def test_subscription_qos_matches_every_publisher_and_holds_streams_only_when_asked():
    from rclpy.qos import (DurabilityPolicy as D, QoSCompatibility, QoSProfile,
                           ReliabilityPolicy as R, qos_check_compatible)

    from maglev_ros.nodes.recorder import subscription_qos
    pubs = {(r, d): QoSProfile(depth=10, reliability=r, durability=d)
            for r in (R.RELIABLE, R.BEST_EFFORT) for d in (D.VOLATILE, D.TRANSIENT_LOCAL)}
    import itertools
    for n in (1, 2):
        for keys in itertools.combinations(pubs, n):
            for reliable in (False, True):
                sub = subscription_qos([pubs[k] for k in keys], reliable)
                for k in keys:
                    assert qos_check_compatible(pubs[k], sub)[0] != QoSCompatibility.ERROR, (keys, reliable)
                latched = all(d == D.TRANSIENT_LOCAL for _, d in keys)
                assert (sub.durability == D.TRANSIENT_LOCAL) == latched
                if not latched and not reliable:
                    assert sub.reliability == R.BEST_EFFORT     # never holds a replay back
                if latched and all(r == R.RELIABLE for r, _ in keys):
                    assert sub.reliability == R.RELIABLE        # late joiners get the last message
    # subscribed before any publisher: a stream matches any publisher unless reliable is asked,
    # a latched topic (the contract's metadata) every reliable latched one
    for latched in (False, True):
        for reliable in (False, True):
            sub = subscription_qos([], reliable, latched=latched)
            ok = [k for k, q in pubs.items() if qos_check_compatible(q, sub)[0] != QoSCompatibility.ERROR]
            if latched:
                assert (R.RELIABLE, D.TRANSIENT_LOCAL) in ok and sub.durability == D.TRANSIENT_LOCAL
            elif not reliable:
                assert len(ok) == 4


def test_recorded_names_drop_the_namespace():
    from maglev_ros.nodes.recorder import recorded_name
    assert recorded_name("/maglev/modes", "/") == "/maglev/modes"
    assert recorded_name("/line2/maglev/modes", "/line2") == "/maglev/modes"
    assert recorded_name("/maglev/modes", "/line2") is None
    assert recorded_name("/line22/maglev/modes", "/line2") is None
    assert recorded_name("/diagnostics", "/line2") == "/diagnostics"


# --------------------------------------------------------------------------- a real graph
def _read_mcap(path):
    """(header, summary, [(topic, schema, message)], metadata records) with the mcap library."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        r = make_reader(f)
        header, summary = r.get_header(), r.get_summary()
        msgs = [(c.topic, s, m) for s, c, m in r.iter_messages(log_time_order=False)]
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    return header, summary, msgs, meta


@pytest.mark.ros
def test_graph_recorded_and_read_back_by_rosbags_mcap_and_info(tmp_path, capsys):
    from rosbags.highlevel import AnyReader

    from maglev_ros.bag_reader import BagReader
    from maglev_ros.cli import main as cli
    from maglev_ros.mcap_recording import header_stamp_ns
    from rosgraph import ros_env, stop_processes

    env = ros_env(190)
    topics = example_topics(duration_s=0.6)
    bag = write_contract_bag(tmp_path / "in", make_metadata(topics), topics, block_s=0.1,
                             t0_ns=1_700_000_000_000_000_000)
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    py = sys.executable
    node = [py, "-m", "maglev_ros.nodes.recorder", "--ros-args"]
    recorders = [
        subprocess.Popen(node + ["-p", f"path:={a}", "-p", "include_inputs:=true", "-p", "reliable:=true",
                                 "-p", "use_sim_time:=true"], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True),
        subprocess.Popen(node + ["-r", "__ns:=/line2", "-p", f"path:={b}", "-p", "reliable:=true"],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)]
    pubs = []
    try:
        t_wall0 = time.time_ns()
        pubs = [subprocess.Popen([py, str(HERE / "recorder_publish.py"), str(tmp_path / f"sent{tag}.json"),
                                  ns, str(tag), str(diag)], env=env)
                for ns, tag, diag in (("/", 1, 2), ("/line2", 2, 0))]
        rep = subprocess.run([py, "-m", "maglev_ros.cli", "replay", str(bag), "--fast", "--quiet",
                              "--wait-subscribers", "1"], env=env, capture_output=True, text=True, timeout=150)
        assert rep.returncode == 0, rep.stderr
        for p in pubs:
            assert p.wait(timeout=150) == 0
    finally:
        stop_processes(*pubs)
        stop_processes(*recorders)
    logs = [r.stdout.read() for r in recorders]
    assert [r.returncode for r in recorders] == [0, 0], logs
    t_wall1 = time.time_ns()
    sent = {tag: json.loads((tmp_path / f"sent{tag}.json").read_text()) for tag in (1, 2)}
    assert sent[1]["acked"] and sent[2]["acked"]
    for path, tag in ((a, 1), (b, 2)):
        assert not list(tmp_path.glob(f".{path.name}.*.partial")), "partial file left behind"

    # --- rosbags: every topic with its count and the published field values
    with BagReader(bag) as r:
        bag_raw = {}
        for topic, _, _, cdr in r.iter_raw():
            bag_raw.setdefault(topic, []).append(bytes(cdr))
    for path, tag in ((a, 1), (b, 2)):
        expected = {"/" + t.lstrip("/"): m for t, m in sent[tag]["sent"].items()}
        expected["/diagnostics"] = sent[1]["sent"]["/diagnostics"]       # one aggregator per domain
        got, raw = {}, {}
        with AnyReader([path], default_typestore=typestore()) as ar:
            for c, _, data in ar.messages():
                raw.setdefault(c.topic, []).append(bytes(data))
                if c.topic in expected:
                    got.setdefault(c.topic, []).append(plain(ar.deserialize(data, c.msgtype)))
        for t in expected:
            assert got.get(t) == expected[t], (path.name, t, got.get(t), expected[t])
        assert got.keys() == expected.keys(), path.name
        inputs = {t: v for t, v in raw.items() if t.startswith("/testline/")}
        # nothing else but the run protocol's status and (with a replay) its recording events
        assert set(raw) - (set(expected) | set(inputs)) <= {"/maglev/status", "/maglev/replay/events"}, path.name
        assert "/maglev/status" in raw, path.name
        if tag == 1:      # the replay's CDR bytes, untouched, in order (DDS may pad to 4 bytes)
            assert inputs.keys() == bag_raw.keys()
            for t, want in bag_raw.items():
                assert len(inputs[t]) == len(want), t
                for got_cdr, cdr in zip(inputs[t], want):
                    assert got_cdr[:len(cdr)] == cdr and set(got_cdr[len(cdr):]) <= {0}, t
                    assert len(got_cdr) - len(cdr) < 4, t
        else:             # the /line2 recorder saw nothing of the root graph's inputs
            assert inputs == {}

    # --- the mcap library: profile, zstd chunks, ros2msg schemas, cdr, counts, times
    for path, tag in ((a, 1), (b, 2)):
        header, summary, msgs, meta = _read_mcap(path)
        assert header.profile == "ros2"
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
        assert counts == dict(Counter(t for t, _, _ in msgs))
        assert meta["maglev_ros"]["namespace"] == ("/" if tag == 1 else "/line2")
        store = typestore()
        for topic, schema, m in msgs:
            if schema.name == "std_msgs/msg/String":
                assert m.publish_time == m.log_time
                continue
            st = store.deserialize_cdr(m.data, schema.name).header.stamp
            assert m.publish_time == st.sec * 1_000_000_000 + st.nanosec, topic
        logs_t = [m.log_time for _, _, m in msgs]
        if tag == 1:      # sim time: the replay's clock, never before the recording starts
            stamps = [header_stamp_ns(c) for k, v in bag_raw.items() if k != "/testline/metadata"
                      for c in v]
            assert min(stamps) <= min(logs_t) and max(logs_t) <= max(stamps)
        else:             # system time
            assert t_wall0 <= min(logs_t) and max(logs_t) <= t_wall1

    # --- our own reader: a recording with its inputs is a contract bag
    capsys.readouterr()
    code = cli(["info", str(a), "--json"])
    out = capsys.readouterr().out
    rep = json.loads(out)
    assert code == 0, [i["message"] for i in rep["issues"] if i["severity"] == "error"]
    with BagReader(bag) as r:
        want = {t: i.count for t, i in r.topics.items()}
    counts = {t["topic"]: t["count"] for t in rep["topics"]}
    assert {t: counts.get(t) for t in want} == want


# ----------------------------------------------------------------------- maglev-ros launch
@pytest.mark.parametrize("argv, says", [
    (["--record", "{tmp}/x.txt"], "expected a file name ending in .mcap"),
    (["--record", "{tmp}/no/x.mcap"], "does not exist"),
    (["--record-inputs"], "without --record"),
])
def test_launch_record_mistakes_are_one_line(tmp_path, capsys, argv, says):
    from maglev_ros.cli import main as cli
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert cli(["launch", "monitor", "--out", str(tmp_path), *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err and err.startswith("maglev-ros launch: error: --record")


@pytest.mark.ros
def test_launch_record_writes_what_the_graph_carried(tmp_path):
    from rosbags.highlevel import AnyReader

    from maglev_ros.bag_reader import BagReader
    from rosgraph import ros_env

    topics = example_topics(duration_s=0.4)
    bag = write_contract_bag(tmp_path / "in", make_metadata(topics), topics, block_s=0.1,
                             t0_ns=1_700_000_000_000_000_000)
    rec = tmp_path / "graph.mcap"
    # the monitor graph with a summary node in place of its processing nodes (their start-up
    # costs minutes here): it subscribes every topic, so the replay's wait for a subscriber on
    # each data topic does not wait for the recorder, which must still miss no block
    script = ("import sys; from maglev_ros import launch_graph as g; from maglev_ros.cli import main; "
              "g.GRAPHS['monitor'] = [n for n in g.GRAPHS['monitor'] if n.needs_bag] + "
              "[g.NodeSpec('summary', 'maglev_ros.nodes.summary', params={'idle_s': 120.0})]; "
              "sys.exit(main(sys.argv[1:]))")
    run = subprocess.run([sys.executable, "-c", script, "launch", "monitor", "--bag", str(bag), "--fast",
                          "--linger", "0", "--out", str(tmp_path / "o"), "--record", str(rec),
                          "--record-inputs", "--record-reliable"],
                         env=ros_env(185), capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    with BagReader(bag) as r:
        want = {t: i.count for t, i in r.topics.items()}
    with AnyReader([rec], default_typestore=typestore()) as ar:
        got = Counter(c.topic for c, _, _ in ar.messages())
    # every input the replay published, and the run protocol's status and recording events
    assert {t: got[t] for t in want} == want
    assert set(got) - set(want) <= {"/maglev/status", "/maglev/replay/events", "/diagnostics"}
