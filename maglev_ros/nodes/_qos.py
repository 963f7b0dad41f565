"""Publishers and subscriptions of the graph's topics: relative names, the QoS of the table in
``_common`` (``qos_for``), ROS's per-topic QoS overrides, and subscriptions to sensor streams that
also take a best-effort publisher (a DAQ driver).

- Data streams are reliable + keep-all (``_common.QOS_STREAM``): a replay is paced by its slowest
  subscriber instead of overwriting blocks it has not taken yet.
- Latched topics (``_common.LATCHED_TOPICS``) are reliable, transient-local, depth 1: a late
  subscriber still gets the last message.
- Every publisher and subscription made by :func:`publisher` / :func:`subscription` takes ROS's
  standard overrides of history, depth and reliability from parameters
  ``qos_overrides.<topic>.<publisher|subscription>.<policy>`` (``<topic>`` fully qualified, with
  the node's namespace), e.g. from a params file::

      /**:
        ros__parameters:
          qos_overrides:
            /testline/vehicle/accel:
              subscription:
                reliability: best_effort

- A subscription to a contract sensor stream (:data:`SENSOR_TOPICS`) is a
  :class:`SensorSubscription`: reliable by default, it becomes best effort while every publisher
  of its topic is best effort (as rosbag2's recorder adapts to the offered QoS): a reliable
  reader never matches a best-effort writer, and a DAQ driver publishing with
  ``qos_profile_sensor_data`` would otherwise deliver nothing.
"""
from __future__ import annotations

import copy

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from maglev_ros.contract import DATA_TOPICS
from maglev_ros.nodes._common import qos_for, rel

# sensor streams of the recording contract: a DAQ driver may publish them best effort
SENSOR_TOPICS = frozenset(DATA_TOPICS)


def local_topic(node, name: str) -> str | None:
    """A discovered, fully qualified topic name as the graph's absolute name within ``node``'s
    namespace (``/line1/maglev/modes`` -> ``/maglev/modes`` for a node in ``/line1``), or None for a
    topic outside it."""
    ns = node.get_namespace().rstrip("/")
    if not ns:
        return name
    return name[len(ns):] if name.startswith(ns + "/") else None


def offered_qos(node, fq_topic: str, default: QoSProfile) -> QoSProfile:
    """``default`` adapted to the publishers ``fq_topic`` has now, as rosbag2's recorder does for an
    observer: best effort if any publisher is, transient local only if every one is (a latched
    topic's last message is then delivered)."""
    offered = [p.qos_profile for p in node.get_publishers_info_by_topic(fq_topic)]
    qos = copy.copy(default)
    if offered:
        if any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in offered):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
        qos.durability = DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE
    return qos


def _overrides() -> QoSOverridingOptions:
    return QoSOverridingOptions.with_default_policies()


def publisher(node, msg_type, topic: str, qos: QoSProfile | None = None):
    """``node``'s publisher of ``topic`` (absolute graph name; created relative) with the table's
    QoS (or ``qos``), overridable per topic by parameters."""
    return node.create_publisher(msg_type, rel(topic), copy.copy(qos) if qos is not None else qos_for(topic),
                                 qos_overriding_options=_overrides())


def subscription(node, msg_type, topic: str, callback, qos: QoSProfile | None = None):
    """``node``'s subscription to ``topic`` (absolute graph name; created relative) with the table's
    QoS (or ``qos``), overridable per topic; a :class:`SensorSubscription` for a sensor stream."""
    if topic in SENSOR_TOPICS:
        return SensorSubscription(node, msg_type, topic, callback, qos)
    return node.create_subscription(msg_type, rel(topic), callback,
                                    copy.copy(qos) if qos is not None else qos_for(topic),
                                    qos_overriding_options=_overrides())


def _adapting(node) -> list:
    """The node's adapting sensor subscriptions, checked by ONE timer of the node: a timer per
    subscription made rclpy's EventsExecutor warn ("the number of timers associated with this
    clock is large", from 8 timers on) in nodes that subscribe every stream."""
    subs = getattr(node, "_maglev_sensor_subscriptions", None)
    if subs is None:
        subs = node._maglev_sensor_subscriptions = []

        def check() -> None:
            for s in subs:
                s.adapt()
        node._maglev_sensor_timer = node.create_timer(SensorSubscription.CHECK_PERIOD_S, check)
    return subs


class SensorSubscription:
    """A subscription to a sensor stream that follows the reliability its publishers offer.

    Reliable by default (the replay is paced by it). Checked at creation and every
    ``CHECK_PERIOD_S`` (one timer of the node checks all its sensor subscriptions): when the topic
    has publishers and every one is best effort, the subscription is made again best effort; when
    no best-effort publisher is left, reliable again.
    A switch happens only while the current subscription receives nothing from the topic (a
    reliable reader gets nothing from best-effort writers; a best-effort one switches back once
    they are gone), so it loses no message it would have taken. Reliable and best-effort publishers
    at once: stays reliable and says once that the best-effort ones are not received. A
    reliability set by a QoS override is kept as it is.
    """

    CHECK_PERIOD_S = 1.0

    def __init__(self, node, msg_type, topic: str, callback, qos: QoSProfile | None = None,
                 raw: bool = False) -> None:
        self.node, self.msg_type, self.topic, self.callback = node, msg_type, topic, callback
        self.raw = raw                               # the callback takes the serialised bytes
        self.qos = copy.copy(qos) if qos is not None else qos_for(topic)
        self.sub = node.create_subscription(msg_type, rel(topic), callback, self.qos,
                                            qos_overriding_options=_overrides(), raw=raw)
        # rclpy wrote the overrides into self.qos: an override to best effort matches every publisher
        self.adapts = self.qos.reliability == ReliabilityPolicy.RELIABLE
        self.name = self.sub.topic_name              # fully qualified (namespace, remappings)
        self._warned_mixed = False
        if self.adapts:
            _adapting(node).append(self)
            self.adapt()

    @property
    def reliability(self) -> ReliabilityPolicy:
        return self.sub.qos_profile.reliability

    def adapt(self) -> None:
        offered = [p.qos_profile.reliability for p in self.node.get_publishers_info_by_topic(self.name)]
        best_effort = sum(r == ReliabilityPolicy.BEST_EFFORT for r in offered)
        current = self.reliability
        if current == ReliabilityPolicy.RELIABLE and offered and best_effort == len(offered):
            self._remake(ReliabilityPolicy.BEST_EFFORT,
                         f"every publisher ({len(offered)}) is best effort (sensor-data QoS)")
        elif current == ReliabilityPolicy.BEST_EFFORT and not best_effort:
            self._remake(ReliabilityPolicy.RELIABLE, "no best-effort publisher is left")
        elif current == ReliabilityPolicy.RELIABLE and best_effort and not self._warned_mixed:
            self._warned_mixed = True
            self.node.get_logger().warning(
                f"{self.name}: {best_effort} best-effort publisher(s) beside {len(offered) - best_effort} "
                f"reliable one(s) are not received; set qos_overrides.{self.name}.subscription."
                f"reliability: best_effort to take them all")

    def _remake(self, reliability: ReliabilityPolicy, why: str) -> None:
        qos = copy.copy(self.qos)
        qos.reliability = reliability
        self.node.destroy_subscription(self.sub)
        self.sub = self.node.create_subscription(self.msg_type, self.name, self.callback, qos, raw=self.raw)
        self.node.get_logger().info(f"{self.name}: {why}: subscribing {reliability.name.lower()}")
