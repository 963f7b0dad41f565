"""Node ``discrepancy``: watches the twin's residual stream and publishes mismatch reports.

Subscribes every /maglev/twin/residual/<group> (SensorBlock; topics discovered from the graph),
/testline/vehicle/position and the measured streams ``measured_topics`` (for the relative
allowance; channels matched by name); publishes maglev_msgs/MismatchReport on /maglev/mismatch
when ``discrepancy.online.OnlineDetector`` closes an incident (one report per incident: all its
channels, its time/position span, the union band; per-channel bands in ``detail_json``), and
flushes the open incident when the node shuts down. The report's header stamp is the stream time
at which the incident was concluded (monotonic; a late-arriving channel's earlier incident says
"reported late"), its t0_s/t1_s the incident itself. Thin adapter: the logic is in the core.
Parameters (see the core's docstring): ``threshold`` (10, residual power / noise floor),
``frame_s`` (0.5), ``hop_s`` (0.25), ``min_frames`` (2), ``max_s`` (5, longest incident),
``merge_gap_s`` (1, runs closer than this are one incident), ``allowance_factor`` (4, x the learned
peak residual of earlier passes), ``learn_rate`` (0.1), ``learn_rate_reported`` (1),
``rel_allowance`` (0.1, tolerated residual / measured amplitude; 0 = off), ``measured_topics``.
"""
from __future__ import annotations

import sys

from rclpy.node import Node

from maglev_msgs.msg import MismatchReport, SensorBlock
from maglev_ros.contract import DATA_TOPICS, TOPIC_VEHICLE_POSITION
from maglev_ros.discrepancy.online import OnlineDetector
from maglev_ros.nodes._common import QOS_STREAM, BlockGate, run_node, stamp_to_msg
from maglev_ros.nodes._diagnostics import NodeDiagnostics

TOPIC_MISMATCH = "/maglev/mismatch"
RESIDUAL_PREFIX = "/maglev/twin/residual/"
# the measured streams the twin's residual groups are computed from
MEASURED_TOPICS = tuple(t for t in DATA_TOPICS if t != TOPIC_VEHICLE_POSITION)


class DiscrepancyNode(Node):
    def __init__(self) -> None:
        super().__init__("discrepancy")
        def num(name, default):
            return float(self.declare_parameter(name, default).value)
        self.detector = OnlineDetector(
            frame_s=num("frame_s", 0.5), hop_s=num("hop_s", 0.25), threshold=num("threshold", 10.0),
            min_frames=int(self.declare_parameter("min_frames", 2).value), max_s=num("max_s", 5.0),
            merge_gap_s=num("merge_gap_s", 1.0), allowance_factor=num("allowance_factor", 4.0),
            learn_rate=num("learn_rate", 0.1), learn_rate_reported=num("learn_rate_reported", 1.0),
            rel_allowance=num("rel_allowance", 0.1))
        measured = list(self.declare_parameter("measured_topics", list(MEASURED_TOPICS)).value or [])
        self.pub = self.create_publisher(MismatchReport, TOPIC_MISMATCH, QOS_STREAM)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        self.subs = {}
        self.create_subscription(SensorBlock, TOPIC_VEHICLE_POSITION, self._on_position, QOS_STREAM)
        if self.detector.rel_allowance > 0:
            for topic in measured:
                if topic:
                    self.create_subscription(SensorBlock, topic, self._on_measured(topic), QOS_STREAM)
        self.create_timer(0.5, self._discover)
        self._discover()

    def _discover(self) -> None:
        for name, types in self.get_topic_names_and_types():
            if name.startswith(RESIDUAL_PREFIX) and name not in self.subs and "maglev_msgs/msg/SensorBlock" in types:
                self.subs[name] = self.create_subscription(SensorBlock, name, self._on_residual(name), QOS_STREAM)

    def _on_position(self, msg) -> None:
        b = self.gate.block(msg, TOPIC_VEHICLE_POSITION)
        if b is not None and "position_m" in b.channels:
            self.detector.add_position(b.times_s(), b.data[:, b.channels.index("position_m")])

    def _on_measured(self, topic: str):
        def cb(msg) -> None:
            b = self.gate.block(msg, topic)
            if b is not None:
                self.detector.add_measured_block(b)
        return cb

    def _on_residual(self, topic: str):
        def cb(msg) -> None:
            b = self.gate.block(msg, topic)
            if b is None:
                return
            for ev in self.detector.add_block(b):
                self._publish(ev)
        return cb

    def _publish(self, ev) -> None:
        out = MismatchReport()
        # stamped when concluded (monotonic; the incident's own interval is t0_s..t1_s)
        stamp_to_msg(int(round(ev.reported_s * 1e9)), out.header)
        out.header.frame_id = "testline"
        out.channels = list(ev.channels)
        out.t0_s, out.t1_s = float(ev.t0_s), float(ev.t1_s)
        out.position_start_m, out.position_end_m = float(ev.position_start_m), float(ev.position_end_m)
        out.f0_hz, out.f1_hz = float(ev.f0_hz), float(ev.f1_hz)
        out.severity = float(ev.severity)
        out.effect, out.category, out.explanation = ev.effect, ev.category, ev.explanation
        out.detail_json = ev.detail_json
        self.pub.publish(out)

    def destroy_node(self):
        """Shutdown: publish the incident still open (end of stream) before going away."""
        try:
            for ev in self.detector.flush():
                self._publish(ev)
        except Exception as exc:  # never block the shutdown
            self.get_logger().warning(f"flush on shutdown failed: {exc}")
        return super().destroy_node()


def main(args=None) -> int:
    return run_node(DiscrepancyNode, args)


if __name__ == "__main__":
    sys.exit(main())
