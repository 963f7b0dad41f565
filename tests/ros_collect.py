"""Collector process for node tests: subscribes topics of any installed type and dumps them.

    python tests/ros_collect.py OUT.json SECONDS IDLE_S pkg/msg/Type:/topic [...]

Each message becomes a dict of its fields (arrays as lists, nested messages as dicts). Stops
after SECONDS, or IDLE_S after the last message once something arrived. IDLE_S given as
``until:FILE``: stops 1 s after FILE exists instead (a driver says the graph is done).
"""
import os
import array
import json
import sys
import time

import numpy as np
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

from maglev_ros.nodes._common import message_class, observer_qos_for


def to_plain(msg):
    if hasattr(msg, "get_fields_and_field_types"):
        return {f: to_plain(getattr(msg, f)) for f in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)):
        return [to_plain(v) for v in msg]
    if isinstance(msg, (array.array, np.ndarray)):
        return [float(v) if np.isfinite(v) else None for v in msg]
    if isinstance(msg, float) and not np.isfinite(msg):
        return None
    return msg


def main():
    out, seconds = sys.argv[1], float(sys.argv[2])
    until = sys.argv[3][len("until:"):] if sys.argv[3].startswith("until:") else None
    idle = float("inf") if until else float(sys.argv[3])
    seen_until = None
    specs = [a.split(":", 1) for a in sys.argv[4:]]
    rclpy.init()
    node = Node("collect")
    got = {topic: [] for _, topic in specs}
    last = {"t": None}
    for msgtype, topic in specs:
        def cb(msg, topic=topic):
            got[topic].append(to_plain(msg))
            last["t"] = time.monotonic()
        node.create_subscription(message_class(msgtype), topic, cb, observer_qos_for(topic))
    ex = EventsExecutor()
    ex.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
        if last["t"] is not None and time.monotonic() - last["t"] > idle:
            break
        if until is not None and seen_until is None and os.path.exists(until):
            seen_until = time.monotonic()
        if seen_until is not None and time.monotonic() - seen_until > 1.0:
            break
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    with open(out, "w") as f:
        json.dump(got, f)


if __name__ == "__main__":
    main()
