"""Publisher/collector for the discrepancy node test (run as a script, talks real DDS).

    python tests/discrepancy_ros_probe.py OUT.json

Publishes 30 s of residual blocks (noise + a 40 Hz burst at 20-23 s) on
/maglev/twin/residual/guideway_accel and the vehicle position (5 m/s), as fast as the node takes
them, and records every MismatchReport on /maglev/mismatch; writes OUT.json.
"""
import json
import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node

from maglev_msgs.msg import MismatchReport, SensorBlock
from maglev_ros.nodes._common import QOS_STREAM, msg_from_block
from maglev_ros.sensor_block import Block


def main() -> None:
    out = sys.argv[1]
    rclpy.init()
    node = Node("discrepancy_probe")
    got = []
    node.create_subscription(MismatchReport, "/maglev/mismatch", lambda m: got.append(
        {"channels": list(m.channels), "t0_s": m.t0_s, "t1_s": m.t1_s, "x0": m.position_start_m,
         "x1": m.position_end_m, "f0_hz": m.f0_hz, "f1_hz": m.f1_hz, "severity": m.severity,
         "explanation": m.explanation}), QOS_STREAM)
    pub = node.create_publisher(SensorBlock, "/maglev/twin/residual/guideway_accel", QOS_STREAM)
    ppos = node.create_publisher(SensorBlock, "/testline/vehicle/position", QOS_STREAM)
    # wait for the node to subscribe
    t_end = time.time() + 30
    while pub.get_subscription_count() == 0 and time.time() < t_end:
        rclpy.spin_once(node, timeout_sec=0.1)
    time.sleep(1.0)
    rng = np.random.default_rng(5)
    fs = 500.0
    t = np.arange(0, 30, 1 / fs)
    x = rng.normal(0, 0.01, t.size) + np.where((t > 20) & (t < 23), 0.3 * np.sin(2 * np.pi * 40.0 * t), 0)
    for a in range(0, t.size, 50):
        st = int(round(t[a] * 1e9))
        ppos.publish(msg_from_block(Block(st, "v", 50.0, ("position_m", "speed_mps"), ("m", "m/s"),
                                          np.array([[5.0 * t[a], 5.0]], np.float32))))
        pub.publish(msg_from_block(Block(st, "g", fs, ("G1A",), ("m/s^2",), x[a:a + 50, None].astype(np.float32))))
        rclpy.spin_once(node, timeout_sec=0.0)
        time.sleep(0.002)
    t_end = time.time() + 10
    while time.time() < t_end and not got:
        rclpy.spin_once(node, timeout_sec=0.1)
    with open(out, "w") as f:
        json.dump(got, f)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
