"""Drives recordings through running nodes by the graph run protocol and records what they publish.

    python tests/graph_probe.py OUT.json SPEC.json

SPEC: {"nodes": [names], "subscribers": {topic: subscriptions the nodes hold},
       "bags": [paths], "collect": ["pkg/msg/Type:/topic", ...], "timeout_s": S}

Waits until every node says ``ready`` on maglev/status; then per bag k: announces
``recording_start`` k, publishes the bag's metadata (latched) and waits until every node has
acknowledged it, runs ``maglev-ros replay BAG --fast`` (which ends once every reliable
subscriber acknowledged every message), announces ``recording_end`` k (the replay will do both
itself once it speaks the protocol) and waits until every node says ``done`` >= k. Before a
replay the probe adds best-effort subscriptions so that every data topic of the bag has the same
count, ``N``, and the replay is told to wait for N subscribers on every topic: it starts only once
it has matched every node's subscription (no timing). OUT: {"topics": {topic: [messages]},
"ends": [{"index": k, "counts": {topic: messages received by then}}]}.
"""
import json
import subprocess
import sys
import time

import rclpy
from rclpy.duration import Duration
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from maglev_msgs.msg import SensorBlock
from maglev_ros.bag_reader import BagReader
from maglev_ros.contract import TOPIC_METADATA
from maglev_ros.nodes._common import message_class, observer_qos_for, qos_for
from maglev_ros.nodes._lifecycle import GraphWaiter, ReplayEvent
from ros_collect import to_plain

QOS_PAD = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


def main() -> None:
    out, spec = sys.argv[1], json.loads(open(sys.argv[2]).read())
    nodes, timeout = spec["nodes"], float(spec.get("timeout_s", 600))
    rclpy.init()
    node = Node("graph_probe")
    ex = EventsExecutor()
    ex.add_node(node)
    waiter = GraphWaiter(node)
    got = {}
    for item in spec["collect"]:
        msgtype, topic = item.split(":", 1)
        got[topic] = []
        node.create_subscription(message_class(msgtype), topic,
                                 lambda m, t=topic: got[t].append(to_plain(m)), observer_qos_for(topic))
    pub_md = node.create_publisher(String, TOPIC_METADATA, qos_for(TOPIC_METADATA))
    left = waiter.wait(ex, lambda: waiter.not_ready(nodes), timeout)
    assert not left, f"nodes not ready: {left}"
    left = waiter.wait(ex, lambda: [] if pub_md.get_subscription_count() >= len(nodes) else nodes, timeout)
    assert not left, "the nodes' metadata subscriptions not matched"
    ends = []
    pads = {}
    for k, bag in enumerate(spec["bags"]):
        with BagReader(bag) as r:
            topics = [t for t, i in r.topics.items() if t != TOPIC_METADATA and i.is_sensor_block]
            md_json = r.read_metadata_json()
        held = {t: spec["subscribers"].get(t, 0) + pads.get(t, 0) for t in topics}
        n = max(max(held.values()), 1)
        for t in topics:
            for _ in range(n - held[t]):
                node.create_subscription(SensorBlock, t, lambda m: None, QOS_PAD)
                pads[t] = pads.get(t, 0) + 1
        waiter.announce(ReplayEvent("recording_start", k, str(bag)))
        # the replay publishes the metadata latched but does not wait for it to arrive: a node's
        # reader it matched late missed it (the replay had ended), or got it after the recording's
        # end; delivered here first and acknowledged by every node, as a replay should
        pub_md.publish(String(data=md_json))
        assert pub_md.wait_for_all_acked(Duration(seconds=timeout)), f"{bag}: metadata not acknowledged"
        rep = subprocess.Popen([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--fast",
                                "--quiet", "--no-clock", "--wait-subscribers", str(n)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        while rep.poll() is None:
            ex.spin_once(timeout_sec=0.05)
        text = rep.stdout.read()
        assert rep.returncode == 0, text
        waiter.announce(ReplayEvent("recording_end", k, str(bag)))
        t0 = time.monotonic()
        left = waiter.wait(ex, lambda: waiter.not_done(nodes, k), timeout)
        assert not left, f"recording {k} ({bag}): not done after {timeout:g} s: {left}"
        # a node says done once its reliable subscribers acknowledged its results: they are here
        ends.append({"index": k, "bag": str(bag), "wait_s": time.monotonic() - t0,
                     "counts": {t: len(v) for t, v in got.items()}})
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    with open(out, "w") as f:
        json.dump({"topics": got, "ends": ends}, f)


if __name__ == "__main__":
    main()
