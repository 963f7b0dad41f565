"""Small shared pieces of the ROS 2 adapters: QoS profiles, the allow-list of message classes,
the edge check of incoming SensorBlocks, clean spin/shutdown."""
from __future__ import annotations

import copy
import importlib
import os
import sys
import threading
from collections import Counter

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Data streams: reliable + keep-all, so a fast replay is slowed by a slow subscriber (DDS flow
# control) instead of overwriting blocks it has not taken yet.
QOS_STREAM = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
# Latched: late subscribers still get the last message (metadata, parameters, profiles).
QOS_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
QOS_CLOCK = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)

# the QoS table: these topics are latched (publisher and subscribers alike), every other topic of
# the graph is a data stream (QOS_STREAM); /clock and /diagnostics have their ROS profiles.
# Per-topic overrides and the sensor streams' best-effort fallback: nodes/_qos.py
LATCHED_TOPICS = ("/testline/metadata", "/maglev/twin/parameters", "/maglev/irregularity",
                  "/maglev/diagnosis", "/maglev/status")


def _allowed_types() -> dict[str, tuple[str, str]]:
    from maglev_ros.sensor_block import MSG_NAMES
    table = {f"maglev_msgs/msg/{n}": ("maglev_msgs.msg", n) for n in MSG_NAMES}
    table.update({"std_msgs/msg/String": ("std_msgs.msg", "String"),
                  "rosgraph_msgs/msg/Clock": ("rosgraph_msgs.msg", "Clock"),
                  "diagnostic_msgs/msg/DiagnosticArray": ("diagnostic_msgs.msg", "DiagnosticArray"),
                  # what DAQ drivers publish per sample (nodes/daq_adapter.py, daq_sim.py)
                  "std_msgs/msg/Float64": ("std_msgs.msg", "Float64"),
                  "std_msgs/msg/Float64MultiArray": ("std_msgs.msg", "Float64MultiArray"),
                  "sensor_msgs/msg/Imu": ("sensor_msgs.msg", "Imu"),
                  "sensor_msgs/msg/Range": ("sensor_msgs.msg", "Range"),
                  "nav_msgs/msg/Odometry": ("nav_msgs.msg", "Odometry")})
    return table


# The message types the nodes publish or subscribe (ours and the standard ones the graph uses).
# A type name read from a bag or the graph only selects an entry here: what is imported is always
# a module named in this table, never a name a recording supplies.
ALLOWED_TYPES = _allowed_types()


# nice increment of a node's background threads (a recording's diagnosis, the magnet layer): the
# threads that take the streams keep precedence when the machine is short of cores
BACKGROUND_NICE = 10


def background_thread() -> None:
    """Lower the calling thread's CPU priority by :data:`BACKGROUND_NICE` (Linux keeps a nice value
    per thread; threads it starts inherit it). Work whose result is not paced by the stream runs
    so: under a fast replay on few cores it waits instead of holding back the nodes' stream work.
    Elsewhere, or where the system refuses, the thread keeps its priority."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + BACKGROUND_NICE))
    except (AttributeError, OSError):
        pass


def message_class(msgtype: str):
    """The rclpy class of an allowed type name like ``maglev_msgs/msg/SensorBlock``; None when the
    type is not on :data:`ALLOWED_TYPES` or its package is not installed."""
    entry = ALLOWED_TYPES.get(msgtype)
    if entry is None:
        return None
    module, name = entry
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return None


def rel(topic: str) -> str:
    """The relative form of a contract or suite topic (``/testline/vehicle/accel`` ->
    ``testline/vehicle/accel``): nodes publish and subscribe relative names so that a namespace
    (``--ros-args -r __ns:=/line2``) moves a whole graph; without one they resolve to the same names."""
    return topic.lstrip("/")


def qos_for(topic: str) -> QoSProfile:
    """A fresh copy of the table's profile of ``topic`` (its absolute graph name): rclpy writes QoS
    overrides into the profile it is given."""
    return copy.copy(QOS_LATCHED if topic in LATCHED_TOPICS else QOS_STREAM)


def observer_qos_for(topic: str) -> QoSProfile:
    """``qos_for`` for a subscriber that wants every message (a recorder, a test's collector): a
    latched topic read keep-all, so a burst is never overwritten in its queue before it is taken
    (its writers wait for every reader's acknowledgement before publishing the next)."""
    q = qos_for(topic)
    if topic in LATCHED_TOPICS:
        q.history = HistoryPolicy.KEEP_ALL
    return q


def run_node(node_factory, args=None) -> int:
    """Init rclpy, build the node, spin it with an EventsExecutor, shut down cleanly.

    The node may define ``finished`` (bool attribute) to end the spin on its own.
    """
    import faulthandler
    import signal

    from rclpy.signals import SignalHandlerOptions

    # a crash in native code (DDS, numba, torch) prints every thread's Python stack, not just the signal
    faulthandler.enable()

    # Our own SIGINT/SIGTERM handling: finish the spin loop and shut down in order, instead of
    # rclpy invalidating the context under a running callback.
    rclpy.init(args=args if args is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = None
    code = 0
    stop = {"now": False}

    def on_signal(signum, frame):
        stop["now"] = True
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    try:
        node = node_factory()
        from rclpy.experimental import EventsExecutor
        executor = EventsExecutor()
        executor.add_node(node)
        while rclpy.ok() and not getattr(node, "finished", False) and not stop["now"]:
            executor.spin_once(timeout_sec=0.1)
        code = int(getattr(node, "exit_code", 0))
    except KeyboardInterrupt:
        code = 130
    except Exception as exc:  # one clear line for user mistakes raised while building the node
        from maglev_ros.errors import UserError
        if not isinstance(exc, UserError):
            raise
        print(f"{os.path.basename(sys.argv[0])}: error: {exc}", file=sys.stderr)
        code = 1
    finally:
        abandon = node is not None and hasattr(node, "unfinished_work") and node.unfinished_work()
        if executor is not None:
            executor.shutdown()
        diagnostics = getattr(node, "diagnostics", None)
        if diagnostics is not None and hasattr(diagnostics, "close"):
            diagnostics.close()          # its thread publishes no more on a node being destroyed
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
        if abandon:
            # a worker thread still in native code: end here, without the interpreter's teardown
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    return code


SCAN_BATCH_S = 1.0    # stream seconds of a topic's blocks fed to its health scan at once


class BlockGate:
    """The edge check of every SensorBlock a node takes (:class:`maglev_ros.sensor_block.StreamCheck`).

    ``block(msg, topic)`` returns the core Block, or None for a malformed one, which is dropped,
    counted per kind and topic and logged once per kind; the counts go to ``/diagnostics``
    (WARN once any block was dropped: the node's results then lack those samples).
    """

    def __init__(self, node, diagnostics) -> None:
        from maglev_ros.sensor_block import StreamCheck
        self.node = node
        self.stream = StreamCheck()
        self.accepted = 0
        self.dropped: Counter = Counter()            # kind -> blocks
        self.dropped_on: Counter = Counter()         # topic -> blocks
        self.converted: dict = {}                    # topic -> unit conversions made (logged once)
        self.scans: dict = {}                        # topic -> health.TopicScan of the blocks taken
        self._scan_pending: dict = {}                # topic -> blocks not yet scanned (< SCAN_BATCH_S)
        # the executor feeds the scans, the diagnostics thread flushes and reads them
        self._scan_lock = threading.Lock()
        self._said: set = set()                      # (topic, channel, kind) already logged
        diagnostics.add_check(self.check)
        diagnostics.add_check(self.health_check)

    def new_stream(self) -> None:
        """Call on new metadata: the next block of each topic sets its layout again."""
        self.stream.new_stream()
        with self._scan_lock:
            self.scans.clear()
            self._scan_pending.clear()

    @property
    def seen(self) -> int:
        return self.accepted + sum(self.dropped.values())

    def block(self, msg, topic: str):
        fault = self.stream.fault(topic, msg.channels, msg.units, msg.sample_rate_hz, len(msg.data))
        if fault is None:
            fault = self._to_si(topic, block_from_msg(msg))
            if not isinstance(fault, tuple):
                self.accepted += 1
                return fault
        kind, reason = fault
        if not self.dropped[kind]:
            stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            self.node.get_logger().warning(
                f"{topic}: dropped a malformed SensorBlock stamped {stamp_s:.3f} s: {reason} "
                f"(further '{kind}' blocks are dropped and counted on /diagnostics, not logged)")
        self.dropped[kind] += 1
        self.dropped_on[topic] += 1
        return None

    def _to_si(self, topic: str, block):
        """The block in SI by the contract's unit table, as every verb reads it (maglev_ros.health),
        or the fault ('unit', why) of a unit the table does not know."""
        from maglev_ros.errors import ContractError
        from maglev_ros.health import block_to_si
        try:
            si, conv = block_to_si(topic, block)
        except ContractError as exc:
            return "unit", str(exc)
        if conv and topic not in self.converted:
            self.converted[topic] = conv
            self.node.get_logger().warning(
                f"{topic}: converted to SI by the contract's unit table: "
                + ", ".join(f"{c.channel} {c.unit} -> {c.si_unit}" for c in conv))
        self._scan(topic, si)
        return si

    def _scan(self, topic: str, block) -> None:
        """The verbs' flat / clipped / implausible scan (maglev_ros.health.TopicScan) of the contract's
        sensor streams (a twin's residual is no sensor), fed SCAN_BATCH_S of blocks at a time, and
        whatever is pending when the diagnostics read it: per 0.1 s block its numpy calls on small
        arrays cost each node ~0.25 ms a block."""
        import numpy as np

        from maglev_ros.contract import DATA_TOPICS
        from maglev_ros.health import TopicScan
        if topic not in DATA_TOPICS or not np.isfinite(block.data).all():
            return                     # NaN/inf blocks are the contract check's, as TopicScan.add has it
        with self._scan_lock:
            if topic not in self.scans:
                self.scans[topic] = TopicScan(topic, block.channels, block.sample_rate_hz)
                self._scan_pending[topic] = []
            pending = self._scan_pending[topic]
            pending.append(block.data)
            if sum(len(d) for d in pending) >= SCAN_BATCH_S * max(block.sample_rate_hz, 1.0):
                self._flush_scan(topic)

    def _flush_scan(self, topic: str) -> None:
        """Feed ``topic``'s pending blocks to its scan (under ``_scan_lock``)."""
        import numpy as np
        pending = self._scan_pending[topic]
        if pending:
            self.scans[topic].add(np.concatenate(pending) if len(pending) > 1 else pending[0])
            pending.clear()

    def health_check(self):
        """Channels the sensor-health scan calls flat, clipped or implausible so far: WARN naming
        them (a node cannot leave a channel out of a model already built; the operator is told)."""
        from maglev_ros.nodes._diagnostics import OK, WARN, Check
        with self._scan_lock:
            for topic in self.scans:
                self._flush_scan(topic)
            found = [i for scan in self.scans.values() for i in scan.issues()]
        for i in found:
            if (i.topic, i.channel, i.kind) not in self._said:
                self._said.add((i.topic, i.channel, i.kind))
                self.node.get_logger().warning(f"{i.topic} [{i.channel}]: {i.message}")
        if not found:
            return Check(OK, "", {})
        return Check(WARN, "sensor health: " + "; ".join(f"{i.channel} {i.kind}" for i in found),
                     {f"health {i.channel}": i.message for i in found})

    def check(self):
        from maglev_ros.nodes._diagnostics import OK, WARN, Check
        from maglev_ros.sensor_block import BLOCK_FAULT_KINDS
        n = sum(self.dropped.values())
        values = {"blocks_accepted": self.accepted, "blocks_dropped": n}
        values.update({f"dropped_{k}": self.dropped[k] for k in (*BLOCK_FAULT_KINDS, "unit")})
        values.update({f"dropped_on {t}": c for t, c in sorted(self.dropped_on.items())})
        if not n:
            return Check(OK, "", values)
        kinds = ", ".join(f"{k} {c}" for k, c in sorted(self.dropped.items()))
        return Check(WARN, f"dropped {n} malformed SensorBlock(s) ({kinds})", values)


def block_from_msg(msg):
    """rclpy SensorBlock -> core :class:`maglev_ros.sensor_block.Block` (no copy of the samples).

    Only for a block that passed :class:`BlockGate` (its shape is not checked here)."""
    import numpy as np

    from maglev_ros.sensor_block import Block
    nch = len(msg.channels)
    data = np.frombuffer(msg.data, dtype=np.float32) if len(msg.data) else np.zeros(0, np.float32)
    return Block(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
                 msg.header.frame_id, float(msg.sample_rate_hz), tuple(msg.channels),
                 tuple(msg.units), data.reshape(-1, max(nch, 1)))


def msg_from_block(block):
    """Core Block -> rclpy SensorBlock."""
    import numpy as np

    from maglev_msgs.msg import SensorBlock
    msg = SensorBlock()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(block.stamp_ns), 1_000_000_000)
    msg.header.frame_id = block.frame_id
    msg.sample_rate_hz = float(block.sample_rate_hz)
    msg.channels = list(block.channels)
    msg.units = list(block.units)
    msg.data = np.ascontiguousarray(block.data, dtype=np.float32).ravel()
    return msg


def stamp_to_msg(stamp_ns: int, header) -> None:
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
