"""Two graphs side by side on one ROS domain, each in its own namespace (``maglev_ros.launcher``
with ``namespace``, as ``maglev-ros launch monitor --namespace``): each replays its own recording
into its own irregularity node at the same time, and each namespace's topics carry only its own
recording (message counts and stamps as its bag has them, the profile from its own pass); nothing
appears on the un-namespaced topics, while /diagnostics stays one absolute topic for both.

The graphs are replay + irregularity + summary (the cheapest node that publishes, and the counter
``maglev-ros demo`` uses); a spy node in the test process watches the un-namespaced names.
"""
import io
import json
import threading

import pytest

from bagfactory import (METADATA_TOPIC, VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, make_metadata,
                        write_contract_bag)
from irregularity_data import make_recording
from maglev_ros import launch_graph
from maglev_ros.bag_reader import BagReader
from maglev_ros.launch_graph import NodeSpec
from maglev_ros.launcher import launch
from rosgraph import ros_context, ros_env

pytestmark = pytest.mark.ros

LINES = {"/line1": dict(length_m=55.0, speed_kmh=25.0, seed=1, t0_ns=1000 * 10**9),
         "/line2": dict(length_m=80.0, speed_kmh=30.0, seed=2, t0_ns=5000 * 10**9)}


def _bag(path, length_m, speed_kmh, seed, t0_ns):
    rec = make_recording(speed_kmh, seed, "constant", length_m=length_m, fs_hz=500.0)
    topics = {topic: (cd.channels, cd.units, cd.sample_rate_hz, cd.data)
              for topic, cd in ((VEHICLE_ACCEL, rec.accel), (VEHICLE_GAP, rec.gap), (VEHICLE_POSITION, rec.position))}
    md = make_metadata(topics, n_spans=12, magnet_offsets_m=rec.magnet_offsets_m,
                       nominal_speed_mps=rec.info["speed_mps"])
    return write_contract_bag(path, md, topics, t0_ns=t0_ns)


def test_two_namespaced_graphs_run_side_by_side_without_crosstalk(tmp_path, monkeypatch):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    from maglev_msgs.msg import IrregularityProfile, SensorBlock
    from maglev_ros.nodes._common import QOS_STREAM, qos_for

    env = ros_env(120)
    bags, flows, expected = {}, {}, {}
    for ns, spec in LINES.items():
        bags[ns] = _bag(tmp_path / ns.strip("/"), **spec)
        with BagReader(bags[ns]) as r:
            expected[ns] = {t: i.count for t, i in r.topics.items()}
            expected[ns]["span_s"] = (r.start_time_s, r.start_time_s + r.duration_s)
        flows[ns] = tmp_path / f"{ns.strip('/')}.json"
    monkeypatch.setitem(launch_graph.GRAPHS, "_ns", [
        NodeSpec("replay", "maglev_ros.nodes.replay", needs_bag=True),
        NodeSpec("irregularity", "maglev_ros.nodes.irregularity", params={"publish_period_s": 0.5},
                 runs_until_stopped=True),
        NodeSpec("summary", "maglev_ros.nodes.summary", params={"idle_s": 60.0}),
    ])
    with ros_context(env) as ctx:
        spy = Node("spy", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(spy)
        seen = {t: 0 for t in (VEHICLE_ACCEL, VEHICLE_POSITION, METADATA_TOPIC, "/maglev/irregularity")}
        diag_from = set()
        for topic, cls in ((VEHICLE_ACCEL, SensorBlock), (VEHICLE_POSITION, SensorBlock),
                           (METADATA_TOPIC, String), ("/maglev/irregularity", IrregularityProfile)):
            spy.create_subscription(cls, topic, lambda m, t=topic: seen.__setitem__(t, seen[t] + 1), qos_for(topic))
        spy.create_subscription(DiagnosticArray, "/diagnostics",
                                lambda m: diag_from.update(s.hardware_id for s in m.status), QOS_STREAM)
        spinner = threading.Thread(target=ex.spin, daemon=True)
        spinner.start()
        logs, codes = {}, {}

        def run(ns):
            logs[ns] = io.StringIO()
            codes[ns] = launch("_ns", bag=str(bags[ns]), env=env, linger_s=4.0, out=logs[ns], namespace=ns,
                               overrides={"replay": {"rate": 4.0, "progress": False, "wait_subscribers": 2},
                                          "summary": {"json_out": str(flows[ns]), "reliable": True}})
        threads = [threading.Thread(target=run, args=(ns,)) for ns in LINES]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=300)
        ex.shutdown()
        spinner.join(10)
        spy.destroy_node()
    for ns in LINES:
        assert codes.get(ns) == 0, logs[ns].getvalue()
        flow = json.loads(flows[ns].read_text())["topics"]
        lo, hi = expected[ns]["span_s"]
        for topic in (VEHICLE_ACCEL, VEHICLE_GAP, VEHICLE_POSITION, METADATA_TOPIC):
            assert flow[topic]["messages"] == expected[ns][topic], (ns, topic, logs[ns].getvalue())
        for topic in (VEHICLE_ACCEL, VEHICLE_POSITION):
            assert lo - 1e-6 <= flow[topic]["first_stamp_s"] and flow[topic]["last_stamp_s"] <= hi, (ns, topic)
        prof = flow["/maglev/irregularity"]
        assert prof["messages"] >= 1 and lo <= prof["last_stamp_s"] <= hi + 1.0, (ns, prof, logs[ns].getvalue())
        assert "starting anyway" not in logs[ns].getvalue()
    # the two recordings differ, and so do the namespaces' flows
    assert expected["/line1"][VEHICLE_ACCEL] != expected["/line2"][VEHICLE_ACCEL]
    assert seen == dict.fromkeys(seen, 0), seen
    assert {"/line1/irregularity", "/line2/irregularity"} <= diag_from, diag_from
