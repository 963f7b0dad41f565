"""Node ``recorder``: writes what the graph produces to an MCAP file (Foxglove, rosbags and
``maglev-ros info`` open it).

Parameters:
  path (str, required)            the .mcap file; it grows under a partial name beside it and
                                  gets its name when the node stops (maglev_ros.mcap_recording)
  include_inputs (bool, false)    also the /testline/* streams (the file is then a contract bag
                                  of its own); /testline/metadata is always recorded
  include_diagnostics (bool, true) also /diagnostics (shared by every graph on the domain)
  reliable (bool, false)          subscribe data streams reliable + keep-all: nothing is lost,
                                  and the replay waits for the recorder like for any other
                                  reliable subscriber; default best-effort, which never slows
                                  the graph down
  flush_period_s (float, 5)       end the open chunk this often (a crash loses at most this much)

Other topics are discovered as their first publisher appears, under the node's namespace
(``-r __ns:=/line2`` records /line2/maglev/* only), and recorded under their names without it,
the namespace going into the file's ``maglev_ros`` metadata record. Messages are taken raw
(serialized CDR, never deserialised). A latched topic (every publisher transient local) is
subscribed reliable + transient local, so its last message is recorded however late the recorder
joins; streams best-effort unless ``reliable``; a best-effort publisher always gets a best-effort
subscription. ``qos_overrides./<topic>.subscription.<policy>`` parameters override per topic.
Log time is the receive time on the node's clock (the replay's /clock with ``use_sim_time``;
messages taken before the first /clock get its first value), publish time the header stamp.
SIGINT/SIGTERM: messages already received are taken, the file is finished and renamed.
The contract's topics (metadata; the streams with ``include_inputs``) are subscribed at start,
before their publishers appear, so a replay that starts once every node is up loses no block;
their QoS is checked when a publisher appears (a best-effort one gets a best-effort subscription).
Run protocol (``_lifecycle``): ``ready`` at start, ``done`` for a replayed recording once the file
holds what arrived until its end (an observer holds nothing back).
"""
from __future__ import annotations

import datetime
import sys
from dataclasses import dataclass

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from maglev_ros.contract import DATA_TOPICS, SENSORBLOCK_TYPE, STRING_TYPE, TOPIC_METADATA
from maglev_ros.errors import UserError
from maglev_ros.nodes._common import message_class, rel, run_node

TOPIC_DIAGNOSTICS = "/diagnostics"
# best-effort streams: room for a burst the executor has not taken yet (a full queue drops the oldest)
STREAM_DEPTH = 1000
LATCHED_DEPTH = 100     # one latched message per publisher (maglev/status has one per node)


def subscription_qos(publisher_qos: list, reliable: bool = False, latched: bool = False) -> QoSProfile:
    """The recorder's subscription QoS for a topic offered with ``publisher_qos`` (one profile per
    publisher): compatible with every one of them, transient local when all are latched (their
    last message is delivered to a late joiner only over a reliable link), best-effort for streams
    unless ``reliable`` is asked and no publisher is best-effort. Without publishers (a topic
    subscribed before they appear) ``latched`` says what to expect."""
    best_effort = any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in publisher_qos)
    if publisher_qos:
        latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in publisher_qos)
    if latched:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=LATCHED_DEPTH,
                          reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if reliable and not best_effort:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=STREAM_DEPTH,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                      reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)


def recorded_name(full_name: str, namespace: str) -> str | None:
    """The name a topic of the graph is recorded under (its namespace removed), or None when it
    is outside the node's namespace. /diagnostics is absolute (one aggregator per domain)."""
    if full_name == TOPIC_DIAGNOSTICS:
        return full_name
    ns = namespace.rstrip("/")
    if not ns:
        return full_name
    return full_name[len(ns):] if full_name.startswith(ns + "/") else None


@dataclass
class _Sub:
    sub: object
    recorded: str                   # the name in the file
    msgtype: str
    provisional: bool               # made before any publisher: its QoS is checked when one appears


class RecorderNode(Node):
    def __init__(self) -> None:
        super().__init__("recorder")

        def p(name, default, text, read_only=True):
            return self.declare_parameter(name, default, ParameterDescriptor(
                description=text, read_only=read_only)).value

        path = p("path", "", "the .mcap file written (renamed into place when the node stops)")
        self.include_inputs = bool(p("include_inputs", False, "also record the /testline/* streams"))
        self.include_diagnostics = bool(p("include_diagnostics", True, "also record /diagnostics"))
        self.reliable = bool(p("reliable", False, "subscribe data streams reliable (the replay then "
                                                  "waits for the recorder too)"))
        flush_period_s = self.declare_parameter("flush_period_s", 5.0, ParameterDescriptor(
            description="end the open chunk this often [s]", dynamic_typing=True, read_only=True)).value
        if not path:
            raise UserError("parameter 'path' is required (-p path:=FILE.mcap)")
        if not str(path).endswith(".mcap"):
            raise UserError(f"parameter 'path' {path}: expected a file name ending in .mcap")
        if isinstance(flush_period_s, bool) or not isinstance(flush_period_s, (int, float)) \
                or not flush_period_s > 0:
            raise UserError(f"parameter 'flush_period_s': expected seconds > 0, got {flush_period_s!r}")
        from maglev_ros.mcap_recording import McapRecording
        self.namespace = self.get_namespace()
        sim = bool(self.get_parameter("use_sim_time").value)
        self.recording = McapRecording(path, flush_period_s=float(flush_period_s), option="path", metadata={
            "namespace": self.namespace, "node": self.get_fully_qualified_name(),
            "include_inputs": self.include_inputs, "include_diagnostics": self.include_diagnostics,
            "reliable": self.reliable, "log_time": "sim time (/clock)" if sim else "system time",
            "started_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})
        self.recording.open()
        self.subs: dict[str, _Sub] = {}         # graph name -> its subscription
        self._pending: list[tuple[str, str, bytes]] = []    # taken before sim time started
        self.exit_code = 0
        self.finished = False
        self.get_logger().info(
            f"recording /maglev/*{' and /testline/*' if self.include_inputs else ''} under "
            f"namespace {self.namespace} to {self.recording.path} (written to "
            f"{self.recording.partial.name} until stopped)")
        # the contract's topics are subscribed now, before their publishers appear: a replay
        # starts once every node is up and subscribed, and the first blocks are then not missed
        for topic in [TOPIC_METADATA] + (list(DATA_TOPICS) if self.include_inputs else []):
            self._subscribe(self.namespace.rstrip("/") + topic, topic,
                            STRING_TYPE if topic == TOPIC_METADATA else SENSORBLOCK_TYPE,
                            subscription_qos([], self.reliable, latched=topic == TOPIC_METADATA),
                            provisional=True)
        # the run protocol: ready now (subscribed to the inputs); done for a recording once its
        # data so far is flushed to the file (an observer: it never holds results back)
        from maglev_ros.nodes._lifecycle import NodeLifecycle
        self.lifecycle = NodeLifecycle(self, ready=True)
        # steady time: under use_sim_time a node-clock timer stops when the replay's /clock does
        self.create_timer(0.25, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # ------------------------------------------------------------------------- discovery
    def _wanted(self, name: str) -> bool:
        if name == TOPIC_DIAGNOSTICS:
            return self.include_diagnostics
        return name.startswith("/maglev/") or name == TOPIC_METADATA or (
            self.include_inputs and name.startswith("/testline/"))

    def _subscribe_new(self) -> None:
        for name, types in self.get_topic_names_and_types():
            known = self.subs.get(name)
            if known is not None and not known.provisional:
                continue
            recorded = recorded_name(name, self.namespace)
            if recorded is None or not self._wanted(recorded):
                continue
            msgtype = next((t for t in types if message_class(t) is not None), None)
            if msgtype is None:
                continue
            pubs = self.get_publishers_info_by_topic(name)
            if not pubs:
                continue        # only subscribers so far: its QoS (latched or not) is not known yet
            qos = subscription_qos([i.qos_profile for i in pubs], self.reliable)
            if known is not None:
                known.provisional = False
                have = known.sub.qos_profile
                if (have.reliability, have.durability) == (qos.reliability, qos.durability) \
                        and known.msgtype == msgtype:
                    self.recording.add_topic(known.recorded, msgtype)
                    continue
                # e.g. a best-effort DAQ driver: a reliable subscription would never match it
                self.get_logger().info(f"{name}: its publishers offer {pubs[0].qos_profile.reliability.name.lower()}"
                                       f", {pubs[0].qos_profile.durability.name.lower()}: subscribing again")
                self.destroy_subscription(known.sub)
                del self.subs[name]
            self._subscribe(name, recorded, msgtype, qos, provisional=False)

    def _subscribe(self, name: str, recorded: str, msgtype: str, qos, provisional: bool) -> None:
        sub_name = name if recorded == TOPIC_DIAGNOSTICS else rel(recorded)
        sub = self.create_subscription(
            message_class(msgtype), sub_name, self._cb(recorded, msgtype), qos, raw=True,
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        self.subs[name] = _Sub(sub, recorded, msgtype, provisional)
        if not provisional:     # in the file from now on, even if nothing comes
            self.recording.add_topic(recorded, msgtype)
        self.get_logger().info(
            f"{'subscribed to' if provisional else 'recording'} {name}"
            + (f" as {recorded}" if recorded != name else "")
            + f" ({msgtype}, {sub.qos_profile.reliability.name.lower()}, "
            f"{sub.qos_profile.durability.name.lower()})")

    # ---------------------------------------------------------------------------- writing
    def _now_ns(self) -> int | None:
        """Receive time on the node's clock; None before the first /clock under sim time."""
        clock = self.get_clock()
        t = clock.now().nanoseconds
        if t == 0 and getattr(clock, "ros_time_is_active", False):
            return None
        return t

    def _write(self, topic: str, msgtype: str, cdr: bytes, log_ns: int | None) -> None:
        if not self.recording.is_open:
            return
        if log_ns is None:
            self._pending.append((topic, msgtype, bytes(cdr)))
            return
        try:
            for t, mt, data in self._pending:
                self.recording.write(t, mt, data, log_ns)
            self._pending.clear()
            self.recording.write(topic, msgtype, cdr, log_ns)
        except (OSError, UserError) as exc:
            self._fail(f"{self.recording.path}: cannot write ({getattr(exc, 'strerror', None) or exc})")

    def _cb(self, topic: str, msgtype: str):
        def on_msg(cdr) -> None:
            self._write(topic, msgtype, cdr, self._now_ns())
        return on_msg

    def _fail(self, why: str) -> None:
        partial = self.recording.abandon()
        self.get_logger().error(f"{why}; recording stopped, what was written is in {partial}")
        self.exit_code = 1
        self.finished = True

    def _tick(self) -> None:
        if not self.recording.is_open:
            return
        self._subscribe_new()
        try:
            self.recording.flush_if_due()
        except OSError as exc:
            self._fail(f"{self.recording.path}: cannot write ({exc.strerror or exc})")

    def on_recording_end(self, index: int) -> None:
        """A replayed recording ended: its data so far goes to the file."""
        if self.recording.is_open:
            try:
                self.recording.flush()
            except OSError as exc:
                self._fail(f"{self.recording.path}: cannot write ({exc.strerror or exc})")

    # ----------------------------------------------------------------------------- ending
    def _drain(self) -> None:
        """Take what the subscriptions received but the executor did not hand out before the stop
        (rclpy's own take, as its executors call it)."""
        for s in self.subs.values():
            sub, topic, msgtype = s.sub, s.recorded, s.msgtype
            while self.recording.is_open:
                try:
                    with sub.handle:
                        taken = sub.handle.take_message(sub.msg_type, True)
                except Exception:  # noqa: BLE001 - a destroyed or failing handle: nothing more to take
                    break
                if taken is None:
                    break
                self._write(topic, msgtype, taken[0], self._now_ns())

    def finish(self) -> None:
        if not self.recording.is_open:
            return
        self._drain()
        if self._pending and self.recording.is_open:   # sim time never started: system time
            import time
            self._write(*self._pending.pop(), self._now_ns() or time.time_ns())
        if not self.recording.is_open:
            return
        try:
            path = self.recording.close()
        except UserError as exc:
            self.get_logger().error(str(exc))
            self.exit_code = 1
            return
        counts = self.recording.counts
        self.get_logger().info(f"wrote {sum(counts.values())} message(s) on {len(counts)} topic(s) "
                               f"to {path}")

    def destroy_node(self) -> None:
        self.finish()
        super().destroy_node()


def main(args=None) -> int:
    return run_node(RecorderNode, args)


if __name__ == "__main__":
    sys.exit(main())
