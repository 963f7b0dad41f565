"""Faults in the node graph (issue 27): malformed SensorBlocks, dead nodes, foreign message types.

- Every node that takes SensorBlocks gets a good block, then malformed blocks of each kind on each
  of its inputs, then good blocks: it stays alive, /diagnostics counts the dropped blocks per kind
  (WARN), it logs once per kind, and what it publishes (or holds, for the updater) equals a run
  fed only the good blocks.
- ``maglev-ros launch monitor`` with the twin killed by SIGKILL mid-run exits non-zero, names the
  twin and how it ended, and stops the other nodes.
- A bag with a ``this/msg/Foo`` topic: the replay skips it with a warning; ``this`` is never
  imported.

The node runs in a subprocess (this file run as a script, see ``harness``): the node object and a
feeder node share one rclpy context, so the feeder can publish a block and wait until the node's
gate has taken it before the next one (the same order of blocks in both runs, no timing).
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BAG = ROOT / "bags" / "paper_pass"

POS, GA, GD = "/testline/vehicle/position", "/testline/guideway/accel", "/testline/guideway/displacement"
VA, VG = "/testline/vehicle/accel", "/testline/vehicle/gap"
RES_GA, RES_VA = "/maglev/twin/residual/guideway_accel", "/maglev/twin/residual/vehicle_accel"

# how each malformed block is made from a good one, and the gate's kind for it
BAD = (("data_length", "drop the last value"), ("bad_rate", "rate 0"), ("bad_rate", "rate nan"),
       ("bad_rate", "rate 1e12"), ("units_mismatch", "one unit short"), ("no_channels", "no channels"),
       ("empty", "no samples"), ("layout_changed", "channels renamed"), ("layout_changed", "rate doubled"))

# node under test: module, class, parameters, SensorBlock inputs, data source, outputs compared
# only at the end (timer-driven publications), and the readiness test after the metadata
CASES = {
    "twin": dict(module="maglev_ros.nodes.twin", cls="TwinNode",
                 params={"seed": 1, "dt_max_s": 5e-4, "idle_flush_s": 1e6},
                 inputs=(POS, GA, GD, VA, VG), source="bag"),
    "irregularity": dict(module="maglev_ros.nodes.irregularity", cls="IrregularityNode",
                         params={"publish_period_s": 1e6}, inputs=(VA, VG, POS), source="bag",
                         final_only=True),
    "modal_id": dict(module="maglev_ros.nodes.modal_id", cls="ModalIdNode",
                     # every window identified (skipping follows the machine's load), and waited for
                     params={"window_s": 1.5, "update_s": 0.5, "skip_when_busy": False}, inputs=(GA,), source="bag"),
    "updater": dict(module="maglev_ros.nodes.updater", cls="UpdaterNode",
                    params={"magnet_layer": False}, inputs=(VA, VG, POS, RES_VA), source="bag"),
    "discrepancy": dict(module="maglev_ros.nodes.discrepancy", cls="DiscrepancyNode",
                        params={}, inputs=(POS, RES_GA), source="burst"),
}


# ------------------------------------------------------------------------------ the harness
def _good_blocks(case: dict) -> tuple[str | None, list]:
    """(metadata JSON, [(topic, Block)]) in stream order for the node's inputs."""
    from maglev_ros.bag_reader import BagReader
    from maglev_ros.sensor_block import Block
    if case["source"] == "burst":
        # residual noise on two channels, a 40 Hz burst at 20-23 s on G1A, a vehicle at 5 m/s:
        # one mismatch report (as in tests/discrepancy_ros_probe.py), in 0.5 s blocks
        rng = np.random.default_rng(5)
        fs, fs_pos, block_s = 500.0, 50.0, 0.5
        t = np.arange(0, 30, 1 / fs)
        x = rng.normal(0, 0.01, (t.size, 2))
        x[:, 0] += np.where((t > 20) & (t < 23), 0.3 * np.sin(2 * np.pi * 40.0 * t), 0)
        tp = np.arange(0, 30, 1 / fs_pos)
        pos = np.stack([5.0 * tp, np.full(tp.size, 5.0)], axis=1).astype(np.float32)
        items = []
        for k in range(int(30 / block_s)):
            st = int(round(k * block_s * 1e9))
            a, ap = int(k * block_s * fs), int(k * block_s * fs_pos)
            items.append((POS, Block(st, "v", fs_pos, ("position_m", "speed_mps"), ("m", "m/s"),
                                     pos[ap:ap + int(block_s * fs_pos)])))
            items.append((RES_GA, Block(st, "g", fs, ("G1A", "G2A"), ("m/s^2",) * 2,
                                        x[a:a + int(block_s * fs)].astype(np.float32))))
        return None, items
    with BagReader(BAG) as r:
        md = r.metadata.to_json()
        wanted = {t for t in case["inputs"] if t.startswith("/testline/")}
        items = [(t, b) for t, b in r.iter_blocks(topics=sorted(wanted), duration_s=2.5)]
    if RES_VA in case["inputs"]:     # the updater's residual input: any vehicle_accel-shaped stream
        items = [x for t, b in items for x in ([(t, b), (RES_VA, b)] if t == VA else [(t, b)])]
    return md, items


def _malformed(msg, how: str):
    if how == "drop the last value":
        msg.data = msg.data[:-1]
    elif how == "rate 0":
        msg.sample_rate_hz = 0.0
    elif how == "rate nan":
        msg.sample_rate_hz = float("nan")
    elif how == "rate 1e12":
        msg.sample_rate_hz = 1e12
    elif how == "rate doubled":
        msg.sample_rate_hz = 2 * msg.sample_rate_hz
    elif how == "channels renamed":
        msg.channels = [f"{c}_other" for c in msg.channels]
    elif how == "one unit short":
        msg.units = list(msg.units)[:-1]
    elif how == "no channels":
        msg.channels, msg.units = [], []
    elif how == "no samples":
        msg.data = np.zeros(0, np.float32)
    return msg


def _feed(case: dict, faulty: bool) -> list:
    """[(topic, msg, kind)]: the good blocks (kind None); with ``faulty``, after each input's first
    good block every malformed kind on that input, made from its next block (one value short is
    no fault on a one-channel topic: not made there)."""
    from maglev_ros.nodes._common import msg_from_block
    _md, items = _good_blocks(case)
    out, n_good, corrupted = [], {}, set()
    for topic, blk in items:
        if faulty and n_good.get(topic) == 1 and topic not in corrupted:
            corrupted.add(topic)
            out += [(topic, _malformed(msg_from_block(blk), how), kind) for kind, how in BAD
                    if kind != "data_length" or len(blk.channels) > 1]
        n_good[topic] = n_good.get(topic, 0) + 1
        out.append((topic, msg_from_block(blk), None))
    return out


def _ready(name: str, node) -> bool:
    return {"twin": lambda: node.core is not None, "irregularity": lambda: node.profiler is not None,
            "modal_id": lambda: bool(node.wanted), "updater": lambda: node.line is not None,
            "discrepancy": lambda: RES_GA in node.subs}[name]()


def _end_of_stream(name: str, node) -> None:
    """What the node does when its input stops (its idle timer / shutdown), done now."""
    if name == "twin":
        node.idle_flush_s = 0.0
        node._idle()
    elif name == "irregularity":
        node.flush_live()
    elif name == "discrepancy":
        for ev in node.detector.flush():
            node._publish(ev)


def _state(name: str, node) -> dict:
    """What the node holds from its blocks when it has published nothing yet (the updater's window)."""
    if name != "updater":
        return {}
    return {t: [[b.stamp_ns, hashlib.sha256(np.ascontiguousarray(b.data).tobytes()).hexdigest()] for b in bs]
            for t, bs in node.core._buf.items()}


def _run_once(name: str, faulty: bool) -> dict:
    import importlib

    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    from maglev_msgs.msg import SensorBlock
    from maglev_ros.nodes._common import QOS_STREAM, qos_for
    from maglev_ros.nodes._diagnostics import QOS_DIAGNOSTICS
    from maglev_ros.nodes._lifecycle import WARMING
    from ros_collect import to_plain

    case = CASES[name]
    node = getattr(importlib.import_module(case["module"]), case["cls"])()
    feeder = Node("feeder")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(feeder)
    published: dict[str, list] = {}
    for pub in list(node.publishers):
        # the run protocol's status carries the node's own counts (of every block, bad ones too)
        if pub.topic_name in ("/parameter_events", "/diagnostics", "/maglev/status"):
            continue

        def record(msg, _pub=pub, _orig=pub.publish):
            # the message's fields, not its CDR bytes (alignment padding is not zeroed)
            plain = json.dumps(to_plain(msg), sort_keys=True)
            published.setdefault(_pub.topic_name, []).append(hashlib.sha256(plain.encode()).hexdigest())
            _orig(msg)
        pub.publish = record
    diag = {}

    def on_diag(msg):
        for st in msg.status:
            if st.name == node.get_name():
                diag.update(level=st.level[0], message=st.message, values={kv.key: kv.value for kv in st.values})
    feeder.create_subscription(DiagnosticArray, "/diagnostics", on_diag, QOS_DIAGNOSTICS)

    def spin_until(cond, what, timeout_s=90.0):
        end = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > end:
                raise RuntimeError(f"{name}: timed out waiting for {what} (last status: {diag})")
            ex.spin_once(timeout_sec=0.01)

    md, _ = _good_blocks(case)
    if md is not None:
        feeder.create_publisher(String, "/testline/metadata", qos_for("/testline/metadata")).publish(String(data=md))
    pubs = {t: feeder.create_publisher(SensorBlock, t, QOS_STREAM) for t in case["inputs"]}
    spin_until(lambda: _ready(name, node) and all(p.get_subscription_count() for p in pubs.values()),
               "the node to take the metadata and subscribe")
    # warm (its kernels loaded): a node still warming says WARN on /diagnostics, which is not the blocks'
    lifecycle = getattr(node, "lifecycle", None)
    spin_until(lambda: lifecycle is None or lifecycle.status.state != WARMING, "the node to be warm", 300.0)
    feed = _feed(case, faulty)
    for k, (topic, msg, _kind) in enumerate(feed, start=1):
        pubs[topic].publish(msg)
        spin_until(lambda: node.gate.seen >= k, f"block {k} on {topic}")
    _end_of_stream(name, node)
    if name == "modal_id":
        spin_until(lambda: not node.busy(), "the modal worker to identify every window", 300.0)
    n_good = sum(1 for *_, kind in feed if kind is None)
    spin_until(lambda: diag.get("values", {}).get("blocks_accepted") == str(n_good)
               and diag["values"]["blocks_dropped"] == str(len(feed) - n_good), "/diagnostics with the counts")
    out = {"published": {t: v[-1:] if case.get("final_only") else v for t, v in published.items()},
           "state": _state(name, node), "diag": dict(diag), "n_good": n_good,
           "injected": [[topic, kind] for topic, _msg, kind in feed if kind is not None]}
    ex.remove_node(node)
    ex.remove_node(feeder)
    node.destroy_node()
    feeder.destroy_node()
    ex.shutdown()
    return out


def harness(out: str) -> None:
    """Run every node of CASES fed good blocks only, then (a new instance) good and malformed ones;
    a node whose callback raised (it would have died) is recorded with its traceback."""
    import traceback

    import rclpy

    from maglev_ros.launch_graph import ros_param_args
    res = {}
    for name, case in CASES.items():
        rclpy.init(args=["harness", "--ros-args", *ros_param_args(case["params"])])
        try:
            res[name] = {"clean": _run_once(name, False), "faulty": _run_once(name, True)}
        except Exception:  # noqa: BLE001  (the test reports it)
            res[name] = {"error": traceback.format_exc()}
        finally:
            rclpy.try_shutdown()
    Path(out).write_text(json.dumps(res))


# ------------------------------------------------------------------------------------ tests
def _env(base: int) -> dict:
    from rosgraph import ros_env
    return ros_env(base)


@pytest.fixture(scope="module")
def fed_nodes(tmp_path_factory):
    """The harness run once for every node (one process: the imports are paid once)."""
    out = tmp_path_factory.mktemp("fed") / "res.json"
    p = subprocess.run([sys.executable, __file__, str(out)], env=_env(190), capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(out.read_text()), p.stderr


@pytest.mark.ros
@pytest.mark.parametrize("name", list(CASES))
def test_a_node_drops_malformed_blocks_reports_them_and_its_results_are_unchanged(name, fed_nodes):
    res, log = fed_nodes
    assert "error" not in res[name], res[name].get("error")      # alive: no callback raised
    clean, faulty = res[name]["clean"], res[name]["faulty"]
    injected = faulty["injected"]
    assert {t for t, _ in injected} == set(CASES[name]["inputs"]) and faulty["n_good"] == clean["n_good"]
    # results on the good blocks: identical to the run without the bad ones, and not vacuous
    assert faulty["published"] == clean["published"]
    assert faulty["state"] == clean["state"]
    assert any(clean["published"].values()) or any(clean["state"].values())
    # /diagnostics: one status for the node, WARN with the counts per kind; OK without bad blocks
    assert clean["diag"]["level"] == 0 and clean["diag"]["values"]["blocks_dropped"] == "0", clean["diag"]
    d = faulty["diag"]
    assert d["level"] == 1, d
    for kind in {k for k, _ in BAD}:
        assert d["values"][f"dropped_{kind}"] == str(sum(1 for _, k in injected if k == kind)), d
    for topic in CASES[name]["inputs"]:
        assert d["values"][f"dropped_on {topic}"] == str(sum(1 for t, _ in injected if t == topic)), d
    assert d["values"]["blocks_dropped"] == str(len(injected)), d
    # logged once per kind, not per block
    logged = [ln for ln in log.splitlines() if f"[{name}]:" in ln and "dropped a malformed SensorBlock" in ln]
    assert sorted(ln.split("further '")[1].split("'")[0] for ln in logged) == sorted({k for k, _ in BAD})


def _children_named(ppid: int) -> dict[str, int]:
    """{node module tail: pid} of the launcher's node processes (from /proc)."""
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) != ppid:
            continue
        for a in cmd:
            if a.startswith(b"maglev_ros.nodes."):
                found[a.decode().rsplit(".", 1)[1]] = int(d.name)
    return found


@pytest.mark.ros
def test_launch_reports_a_node_killed_mid_run_and_exits_non_zero(tmp_path):
    env = _env(190)
    p = subprocess.Popen([sys.executable, "-m", "maglev_ros.cli", "launch", "monitor", "--bag", str(BAG),
                          "--rate", "1", "--linger", "60", "--out", str(tmp_path / "out")],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         start_new_session=True)
    lines: list[str] = []
    twin_up = threading.Event()

    def read():
        for ln in p.stdout:
            lines.append(ln)
            if "[twin]" in ln and "twin built" in ln:
                twin_up.set()
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 180
        while not twin_up.wait(1.0) and p.poll() is None and time.monotonic() < deadline:
            pass                                # a graph that ended early fails now, not after 180 s
        assert twin_up.is_set(), "".join(lines)[-3000:]      # the replay is under way
        nodes = _children_named(p.pid)
        assert {"twin", "replay", "updater"} <= set(nodes), nodes
        os.kill(nodes["twin"], signal.SIGKILL)
        code = p.wait(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    reader.join(10)
    text = "".join(lines)
    assert code == 1, text[-3000:]
    # one line from the launcher as it stops the graph, one error line from the CLI; no other node failed
    assert [ln for ln in text.splitlines() if ln.startswith("[launch]")] == [
        "[launch] node twin ended (killed by SIGKILL) while the graph was running: stopping the graph"], text[-3000:]
    assert text.rstrip().splitlines()[-1] == ("maglev-ros launch: error: node twin ended (killed by SIGKILL) "
                                              "while the graph was running")
    # the rest were stopped: none of the graph's processes is left
    left = []
    for node, pid in nodes.items():
        try:
            if f"maglev_ros.nodes.{node}".encode() in Path(f"/proc/{pid}/cmdline").read_bytes():
                left.append(node)
        except OSError:
            pass
    assert left == [], left


def _bag_with_a_foreign_type(path: Path) -> None:
    """A contract bag plus a topic of type this/msg/Foo (importing ``this`` prints the Zen of Python)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg

    from bagfactory import SENSORBLOCK_TYPE, example_topics, foreign_typestore, make_metadata
    from maglev_ros.sensor_block import Block, block_to_msg
    topics = {VA: example_topics(0.5)[VA]}          # 1000 samples: 5 blocks of 200
    store = foreign_typestore()
    store.register(get_types_from_msg("string data", "this/msg/Foo"))
    channels, units, rate, data = topics[VA]
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        meta = w.add_connection("/testline/metadata", "std_msgs/msg/String", typestore=store)
        foo = w.add_connection("/foreign/zen", "this/msg/Foo", typestore=store)
        blocks = w.add_connection(VA, SENSORBLOCK_TYPE, typestore=store)
        w.write(meta, 0, store.serialize_cdr(store.types["std_msgs/msg/String"](
            data=json.dumps(make_metadata(topics))), "std_msgs/msg/String"))
        for k in range(0, len(data), 200):
            st = int(k / rate * 1e9)
            blk = Block.from_arrays(st, rate, channels, units, data[k:k + 200], "vehicle")
            w.write(blocks, st + 1, store.serialize_cdr(block_to_msg(blk, store), SENSORBLOCK_TYPE))
            w.write(foo, st + 2, store.serialize_cdr(store.types["this/msg/Foo"](data="x"), "this/msg/Foo"))


@pytest.mark.ros
def test_replay_skips_a_type_not_on_the_allow_list_and_never_imports_it(tmp_path):
    bag = tmp_path / "foreign"
    _bag_with_a_foreign_type(bag)
    code = ("import sys\nfrom maglev_ros.cli import main\n"
            f"rc = main(['replay', {str(bag)!r}, '--fast', '--quiet'])\n"
            "print('IMPORTED this:', 'this' in sys.modules)\nsys.exit(rc)\n")
    p = subprocess.run([sys.executable, "-c", code], env=_env(190), capture_output=True, text=True, timeout=120)
    text = p.stdout + p.stderr
    assert p.returncode == 0, text[-3000:]
    assert "IMPORTED this: False" in p.stdout
    assert "Beautiful is better than ugly" not in text
    warned = [ln for ln in text.splitlines() if "/foreign/zen" in ln]
    assert len(warned) == 1 and "this/msg/Foo" in warned[0], text[-3000:]
    assert "published 5 messages" in text          # the SensorBlocks still go out


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    harness(sys.argv[1])
