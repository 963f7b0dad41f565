"""The DAQ simulator -> adapter -> live twin over a real ROS 2 graph.

daq_sim publishes 2 s of the sample pass (19 channels at 2 kHz and position/speed at 200 Hz:
38.4 k samples/s, 36 400 messages on 10 driver topics: Float64MultiArray in g and mm, Imu with
gravity, Range, Odometry) as fast as the reliable subscribers take it; the SensorBlocks the
adapter publishes, collected here, must hold every sample of the bag (read here with BagReader,
the reference), at its stamp, in SI, in the metadata's channel order; the twin must publish
predictions from them. Waits on conditions only (no timing)."""
import json
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.bag_reader import BagReader
from maglev_ros.contract import DATA_TOPICS
from maglev_ros.daq_stream.sim import source_from_bag, write_config
from rosgraph import ros_context, ros_env, spin_until, stop_processes

pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "bags" / "paper_pass"
START_S, DURATION_S = 2.0, 2.0


def _reference():
    """topic -> (sample stamps ns, float32 data, channels, units) of the bag's window, read directly."""
    with BagReader(BAG) as r:
        items = [(t, b) for t, b in r.iter_blocks() if t in DATA_TOPICS]
    t_lo = min(b.stamp_ns for _, b in items) + int(START_S * 1e9)
    t_hi = t_lo + int(DURATION_S * 1e9)
    ref = {}
    for topic in {t for t, _ in items}:
        blocks = [b for t, b in items if t == topic]
        st = np.concatenate([b.stamp_ns + np.round(np.arange(b.n_samples) * 1e9 / b.sample_rate_hz).astype(np.int64)
                             for b in blocks])
        data = np.concatenate([b.data for b in blocks])
        keep = (st >= t_lo) & (st < t_hi)
        ref[topic] = (st[keep], data[keep], blocks[0].channels, blocks[0].units, blocks[0].sample_rate_hz)
    return ref


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    import rclpy
    from rclpy.experimental import EventsExecutor
    from std_msgs.msg import String

    from maglev_msgs.msg import SensorBlock
    from maglev_ros.nodes._common import QOS_LATCHED, qos_for, rel
    from maglev_ros.nodes._lifecycle import QOS_STATUS_READER, TOPIC_STATUS, NodeStatus
    from maglev_ros.twin.online import GROUP_TOPICS, PREDICTED_PREFIX

    tmp = tmp_path_factory.mktemp("daq")
    meta, mapping = write_config(source_from_bag(BAG, START_S, DURATION_S), tmp)
    ref = _reference()
    env = ros_env(61)
    got = defaultdict(list)
    status = {}
    with ros_context(env) as ctx:
        node = rclpy.create_node("daq_test", context=ctx)
        for t in ref:
            node.create_subscription(SensorBlock, rel(t), lambda m, t=t: got[t].append(m), qos_for(t))
        for g in GROUP_TOPICS:
            t = PREDICTED_PREFIX + g
            node.create_subscription(SensorBlock, rel(t), lambda m, t=t: got[t].append(m), qos_for(t))
        node.create_subscription(String, "testline/metadata", lambda m: got["meta"].append(m.data), QOS_LATCHED)

        def on_status(m):
            st = NodeStatus.from_json(m.data)
            if st is not None:
                status[st.node] = st
        node.create_subscription(String, TOPIC_STATUS, on_status, QOS_STATUS_READER)
        ex = EventsExecutor(context=ctx)
        ex.add_node(node)
        py = [sys.executable, "-m"]
        twin = subprocess.Popen(py + ["maglev_ros.nodes.twin", "--ros-args", "-p", "idle_flush_s:=2.0"],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        # every contract topic: this test's subscriber and the twin's before the drivers' data is taken
        adapter = subprocess.Popen(py + ["maglev_ros.nodes.daq_adapter", "--ros-args", "-p", f"mapping:={mapping}",
                                         "-p", f"metadata:={meta}", "-p", "wait_subscribers:=2",
                                         # unpaced and reliable, one driver topic may lag the others by
                                         # seconds; nothing is lost, so no block need go without it
                                         "-p", "max_wait_s:=60.0",
                                         # a reliable writer's retransmission can stall a topic for
                                         # seconds under load: no hand-out of open blocks on a pause
                                         "-p", "idle_flush_s:=0.0"],
                                   env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        sim = subprocess.Popen(py + ["maglev_ros.nodes.daq_sim", "--ros-args", "-p", f"bag:={BAG}",
                                     "-p", f"start_s:={START_S}", "-p", f"duration_s:={DURATION_S}", "-p", "rate:=0.0",
                                     "-p", "reliable:=true", "-p", "restamp:=false", "-p", "wait_subscribers:=1"],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        expected = {t: len(r[0]) * len(r[2]) for t, r in ref.items()}

        def samples(t):
            return sum(len(m.data) for m in got[t])
        failed = None
        try:
            spin_until(ex, lambda: all(samples(t) >= n for t, n in expected.items()),
                       "every sample of the simulator in the adapter's blocks", timeout_s=300)
            spin_until(ex, lambda: sum(len(got[PREDICTED_PREFIX + g]) for g in GROUP_TOPICS) > 0
                       and "daq_adapter" in status and json.loads(status["daq_adapter"].detail or "{}").get("samples")
                       == sum(expected.values()), "the twin's predictions and the adapter's counts", timeout_s=600)
            assert sim.wait(timeout=120) == 0
        except AssertionError as exc:
            failed = exc
        finally:
            stop_processes(sim, adapter, twin)
            ex.shutdown()
            node.destroy_node()
    logs = {name: p.stdout.read() for name, p in (("sim", sim), ("adapter", adapter), ("twin", twin))}
    if failed is not None:
        # what arrived, the adapter's last counts and every node's last words: a stall under load says where
        got_n = {t: f"{samples(t)}/{n}" for t, n in expected.items()}
        counts = status["daq_adapter"].detail if "daq_adapter" in status else None
        tails = "\n".join(f"--- {k} ---\n{v[-1500:]}" for k, v in logs.items())
        pytest.fail(f"{failed}; samples {got_n}; adapter status {counts}\n{tails}")
    return ref, got, status, logs, meta


def test_every_sample_arrives_at_its_stamp_in_si(run):
    ref, got, _status, logs, _meta = run
    for topic, (stamps, data, channels, units, rate) in ref.items():
        msgs = sorted(got[topic], key=lambda m: (m.header.stamp.sec, m.header.stamp.nanosec))
        assert msgs, topic
        n_block = int(round(0.1 * rate))
        st_all, rows = [], []
        for m in msgs:
            assert tuple(m.channels) == channels and tuple(m.units) == units, topic
            assert m.sample_rate_hz == rate
            block = np.asarray(m.data, dtype=np.float32).reshape(-1, len(channels))
            assert len(block) == n_block, topic
            stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            st_all.append(stamp + np.round(np.arange(len(block)) * 1e9 / rate).astype(np.int64))
            rows.append(block)
        st_all, rows = np.concatenate(st_all), np.concatenate(rows)
        np.testing.assert_array_equal(st_all, stamps, err_msg=topic)            # none lost, none doubled
        assert not np.isnan(rows).any(), topic
        # the bag's float32 values, back from g / mm / specific force to SI within a float32 step
        np.testing.assert_allclose(rows, data, rtol=2e-7, atol=1e-12 + 2e-7 * np.abs(data).max(), err_msg=topic)


def test_the_twin_predicts_and_the_adapter_counts_nothing_lost(run):
    ref, got, status, logs, meta = run
    from maglev_ros.twin.online import GROUP_TOPICS, PREDICTED_PREFIX
    assert got["meta"] and json.loads(got["meta"][-1]) == json.loads(Path(meta).read_text())
    predicted = {g: got[PREDICTED_PREFIX + g] for g in GROUP_TOPICS}
    assert sum(map(len, predicted.values())) > 0, logs["twin"][-3000:]
    first_in = min(r[0][0] for r in ref.values())
    for g, msgs in predicted.items():
        for m in msgs:          # predictions are stamped inside the streamed window
            stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            assert first_in <= stamp < first_in + DURATION_S * 1e9
    counts = json.loads(status["daq_adapter"].detail)
    assert counts["samples"] == sum(len(r[0]) * len(r[2]) for r in ref.values())
    assert counts["missing"] == counts["late"] == counts["duplicate"] == counts["off_grid"] == counts["gaps"] == 0
    assert counts["rate_mismatch"] == [] and counts["malformed"] == 0
    # one message per sample: the guideway multi-array, each Imu and Range, the odometry
    per_channel = sum(len(ref[t][0]) * len(ref[t][2]) for t in ("/testline/vehicle/accel", "/testline/vehicle/gap"))
    assert counts["messages"] == len(ref["/testline/guideway/accel"][0]) + per_channel + len(
        ref["/testline/vehicle/position"][0])


def test_best_effort_driver_stream_values_stay_at_their_stamps(tmp_path):
    """A driver with sensor-data QoS (best effort) at real time: the adapter takes it best effort;
    whatever the transport drops under load, every value it publishes is the bag's at that stamp
    (NaN where a sample never came), never shifted; its counts add up to the samples sent."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from std_msgs.msg import String

    from maglev_msgs.msg import SensorBlock
    from maglev_ros.nodes._common import qos_for, rel
    from maglev_ros.nodes._lifecycle import QOS_STATUS_READER, TOPIC_STATUS, NodeStatus
    start, duration = 5.0, 1.0
    meta, mapping = write_config(source_from_bag(BAG, start, duration), tmp_path)
    with BagReader(BAG) as r:
        items = [(t, b) for t, b in r.iter_blocks() if t in DATA_TOPICS]
    first = min(b.stamp_ns for _, b in items)
    t_lo, t_hi = first + int(start * 1e9), first + int((start + duration) * 1e9)
    ref = {}
    for t, b in items:
        st = b.stamp_ns + np.round(np.arange(b.n_samples) * 1e9 / b.sample_rate_hz).astype(np.int64)
        for s, row in zip(st, b.data):
            if t_lo <= s < t_hi:
                ref[(t, int(s))] = row
    env = ros_env(62)
    got, status = defaultdict(list), {}
    with ros_context(env) as ctx:
        node = rclpy.create_node("daq_be_test", context=ctx)
        for t in DATA_TOPICS:
            node.create_subscription(SensorBlock, rel(t), lambda m, t=t: got[t].append(m), qos_for(t))

        def on_status(m):
            st = NodeStatus.from_json(m.data)
            if st is not None and st.node == "daq_adapter" and st.detail:
                status["counts"] = json.loads(st.detail)
        node.create_subscription(String, TOPIC_STATUS, on_status, QOS_STATUS_READER)
        ex = EventsExecutor(context=ctx)
        ex.add_node(node)
        py = [sys.executable, "-m"]
        adapter = subprocess.Popen(py + ["maglev_ros.nodes.daq_adapter", "--ros-args", "-p", f"mapping:={mapping}",
                                         "-p", f"metadata:={meta}", "-p", "wait_subscribers:=1"],
                                   env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        sim = subprocess.Popen(py + ["maglev_ros.nodes.daq_sim", "--ros-args", "-p", f"bag:={BAG}",
                                     "-p", f"start_s:={start}", "-p", f"duration_s:={duration}", "-p", "rate:=1.0",
                                     "-p", "restamp:=false", "-p", "wait_subscribers:=1"],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            spin_until(ex, lambda: sim.poll() is not None, "the simulator's end", timeout_s=300)
            assert sim.returncode == 0
            sent = sum(len(v) for v in ref.values())
            # the idle flush hands out the rest: every sample sent is then in a block or was never received
            spin_until(ex, lambda: status.get("counts", {}).get("blocks", 0) > 0
                       and sum(len(m.data) for t in DATA_TOPICS for m in got[t])
                       == status["counts"]["samples"] + status["counts"]["missing"], "the adapter's last blocks",
                       timeout_s=120)
        finally:
            stop_processes(sim, adapter)
            ex.shutdown()
            node.destroy_node()
    log = adapter.stdout.read()
    assert "best_effort" in log, log[-2000:]          # it followed the drivers' QoS
    counts = status["counts"]
    assert counts["late"] == counts["duplicate"] == counts["off_grid"] == 0 and counts["rate_mismatch"] == []
    assert 0 < counts["samples"] <= sent
    n_values = 0
    for t in DATA_TOPICS:
        for m in got[t]:
            block = np.asarray(m.data, dtype=np.float32).reshape(-1, len(m.channels))
            stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            for i, row in enumerate(block):
                s = stamp + int(round(i * 1e9 / m.sample_rate_hz))
                want = ref[(t, s)]                     # a stamp of the bag's grid, nowhere else
                have = ~np.isnan(row)
                np.testing.assert_allclose(row[have], want[have], rtol=2e-7, atol=1e-9)
                n_values += int(have.sum())
    assert n_values == counts["samples"]


def test_a_mapping_mistake_stops_the_node_with_one_line(tmp_path):
    import yaml
    meta, mapping = write_config(source_from_bag(BAG, 0.0, 0.05), tmp_path)
    doc = yaml.safe_load(mapping.read_text())
    doc["channels"]["M1A"]["field"] = "linear_acceleration.q"
    mapping.write_text(yaml.safe_dump(doc))
    p = subprocess.run([sys.executable, "-m", "maglev_ros.nodes.daq_adapter", "--ros-args", "-p", f"mapping:={mapping}",
                        "-p", f"metadata:={meta}"], env=ros_env(63), capture_output=True, text=True, timeout=120)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert f"{mapping}: mapping key channels.M1A.field: expected a numeric field of sensor_msgs/msg/Imu" in lines[0]
