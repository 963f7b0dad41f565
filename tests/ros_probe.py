"""Subscriber process for the end-to-end tests (run as a script, talks real DDS).

    python tests/ros_probe.py OUT.json SECONDS TOPIC [TOPIC ...]

Subscribes the topics (SensorBlock; the metadata latched), records for each message the header
stamp, channels and a checksum of the payload, and, from a ``use_sim_time`` node, the ROS time
seen when each message arrives. Writes OUT.json after SECONDS or when the replay's /clock has
stopped for 2 s after data arrived.
"""
import hashlib
import json
import sys
import time

import numpy as np
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from maglev_msgs.msg import SensorBlock
from maglev_ros.nodes._common import QOS_CLOCK, qos_for


def main() -> None:
    out, seconds, topics = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
    rclpy.init()
    node = Node("probe", parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, True)])
    rec = {"blocks": {t: [] for t in topics}, "metadata": None, "clock": []}
    last = {"t": None}

    def on_block(topic):
        def cb(msg):
            data = np.asarray(msg.data, dtype=np.float32)
            rec["blocks"][topic].append({
                "stamp_ns": msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
                "channels": list(msg.channels), "units": list(msg.units),
                "rate": msg.sample_rate_hz, "n": int(data.size),
                "sha": hashlib.sha256(data.tobytes()).hexdigest(),
                "sim_now_ns": node.get_clock().now().nanoseconds,
            })
            last["t"] = time.monotonic()
        return cb

    for t in topics:
        node.create_subscription(SensorBlock, t, on_block(t), qos_for(t))
    node.create_subscription(String, "/testline/metadata",
                             lambda m: rec.__setitem__("metadata", m.data), qos_for("/testline/metadata"))

    def on_clock(m):
        rec["clock"].append(m.clock.sec * 1_000_000_000 + m.clock.nanosec)
        last["t"] = time.monotonic()
    node.create_subscription(Clock, "/clock", on_clock, QOS_CLOCK)
    ex = EventsExecutor()
    ex.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
        if last["t"] is not None and time.monotonic() - last["t"] > 2.0:
            break
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    with open(out, "w") as f:
        json.dump(rec, f)


if __name__ == "__main__":
    main()
