"""Node ``discrepancy``: watches the twin's residual stream and publishes mismatch reports.

Subscribes every /maglev/twin/residual/<group> (SensorBlock; topics discovered from the graph)
and /testline/vehicle/position; publishes maglev_msgs/MismatchReport on /maglev/mismatch when
``discrepancy.online.OnlineDetector`` closes a mismatch. Thin adapter: the logic is in the core.
Parameters: ``threshold`` (10, residual power / noise floor), ``frame_s`` (0.5), ``hop_s`` (0.25).
"""
from __future__ import annotations

import sys

from rclpy.node import Node

from maglev_msgs.msg import MismatchReport, SensorBlock
from maglev_ros.discrepancy.online import OnlineDetector
from maglev_ros.nodes._common import QOS_STREAM, block_from_msg, run_node, stamp_to_msg

TOPIC_MISMATCH = "/maglev/mismatch"
RESIDUAL_PREFIX = "/maglev/twin/residual/"


class DiscrepancyNode(Node):
    def __init__(self) -> None:
        super().__init__("discrepancy")
        self.detector = OnlineDetector(
            frame_s=float(self.declare_parameter("frame_s", 0.5).value),
            hop_s=float(self.declare_parameter("hop_s", 0.25).value),
            threshold=float(self.declare_parameter("threshold", 10.0).value))
        self.pub = self.create_publisher(MismatchReport, TOPIC_MISMATCH, QOS_STREAM)
        self.subs = {}
        self.create_subscription(SensorBlock, "/testline/vehicle/position", self._on_position, QOS_STREAM)
        self.create_timer(0.5, self._discover)
        self._discover()

    def _discover(self) -> None:
        for name, types in self.get_topic_names_and_types():
            if name.startswith(RESIDUAL_PREFIX) and name not in self.subs and "maglev_msgs/msg/SensorBlock" in types:
                self.subs[name] = self.create_subscription(SensorBlock, name, self._on_residual, QOS_STREAM)

    def _on_position(self, msg) -> None:
        b = block_from_msg(msg)
        if "position_m" in b.channels:
            self.detector.add_position(b.times_s(), b.data[:, b.channels.index("position_m")])

    def _on_residual(self, msg) -> None:
        for ev in self.detector.add_block(block_from_msg(msg)):
            out = MismatchReport()
            stamp_to_msg(int(ev.t1_s * 1e9), out.header)
            out.header.frame_id = "testline"
            out.channels = list(ev.channels)
            out.t0_s, out.t1_s = float(ev.t0_s), float(ev.t1_s)
            out.position_start_m, out.position_end_m = float(ev.position_start_m), float(ev.position_end_m)
            out.f0_hz, out.f1_hz = float(ev.f0_hz), float(ev.f1_hz)
            out.severity = float(ev.severity)
            out.effect, out.category, out.explanation = ev.effect, ev.category, ev.explanation
            out.detail_json = ev.detail_json
            self.pub.publish(out)


def main(args=None) -> int:
    return run_node(DiscrepancyNode, args)


if __name__ == "__main__":
    sys.exit(main())
