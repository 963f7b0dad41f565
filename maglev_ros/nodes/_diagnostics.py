"""A node's health on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, the ROS 2 convention).

Every ``period_s`` the node publishes one DiagnosticStatus named after the node: the worst level of
its checks, their messages joined by "; ", their key/values merged. The reports come from a thread
of their own, not an executor timer: a timer's event waits behind every message already queued
(EventsExecutor) and behind a long callback, so a node with a backlog fell silent exactly when its
health mattered. A check is a callable
returning a :class:`Check`; the SensorBlock gate (``_common.BlockGate``) is the first, and further
health checks (lag, NaN, residual health) join with :meth:`NodeDiagnostics.add_check`.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

TOPIC_DIAGNOSTICS = "/diagnostics"
OK, WARN, ERROR, STALE = 0, 1, 2, 3      # DiagnosticStatus levels (the message holds them as bytes)
# the diagnostic_updater's profile: reliable, last 10, volatile
QOS_DIAGNOSTICS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


@dataclass(frozen=True)
class Check:
    level: int = OK
    message: str = ""                    # empty when there is nothing to say
    values: dict = field(default_factory=dict)


class NodeDiagnostics:
    """Publishes the node's DiagnosticStatus on /diagnostics every ``period_s`` (wall time) from a
    daemon thread; :meth:`close` (``run_node`` calls it before destroying the node) stops it."""

    def __init__(self, node, period_s: float = 1.0) -> None:
        self.node = node
        self.period_s = float(period_s)
        self.checks: list[Callable[[], Check]] = []
        self.pub = node.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, QOS_DIAGNOSTICS)
        self._stop = threading.Event()
        self._failed = False
        self._thread = threading.Thread(target=self._run, name=f"diagnostics-{node.get_name()}", daemon=True)
        self._thread.start()

    def add_check(self, check: Callable[[], Check]) -> None:
        self.checks.append(check)

    def status(self) -> DiagnosticStatus:
        results = [c() for c in list(self.checks)]
        st = DiagnosticStatus()
        st.name = self.node.get_name()
        st.hardware_id = self.node.get_fully_qualified_name()
        level = max([r.level for r in results], default=OK)
        st.level = bytes([level])
        st.message = "; ".join(r.message for r in results if r.message) or "ok"
        st.values = [KeyValue(key=str(k), value=str(v)) for r in results for k, v in r.values.items()]
        return st

    def publish(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [self.status()]
        self.pub.publish(msg)

    def _run(self) -> None:
        from rclpy.exceptions import InvalidHandle
        while not self._stop.wait(self.period_s):
            try:
                self.publish()
            except (InvalidHandle, RuntimeError) as exc:
                # the node or its context is going away (InvalidHandle, "context is not valid"), or
                # a check read a container a callback was changing: the next period tries again
                if self._stop.is_set() or "context" in str(exc).lower() or isinstance(exc, InvalidHandle):
                    return
                if not self._failed:
                    self._failed = True
                    self.node.get_logger().warning(f"/diagnostics report skipped: {exc}")

    def close(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(2.0 * self.period_s + 1.0)
