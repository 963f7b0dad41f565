"""Observer process of bench_keepup.py: a probe node that watches a running graph from outside.

    python bench/keepup_probe.py OUT.json [--namespace NS] [--reliable] [--max-s S]

Subscribes (the graph's known outputs from its start, other topics as discovered every 0.5 s)
every SensorBlock, ModalEstimate, IrregularityProfile, MismatchReport, TwinParameters and
std_msgs/String topic under ``NS/testline/`` and ``NS/maglev/``, and ``/diagnostics``. For each message it keeps the DDS publish time (``source_timestamp``: when
the writer sent it), the probe's receive time, the writer's sequence number and the header stamp
(SensorBlocks also their last sample's time); /diagnostics keeps each node's ``blocks_accepted``.
Nothing is deserialised that a header or counter does not need (raw CDR for the large messages).
It also records which nodes publish and subscribe each topic. Writes OUT.json on SIGINT/SIGTERM or after S s.

Default QoS is best effort + volatile: the probe matches reliable and best-effort writers and never
holds a replay back (a lost message shows as a gap in the writer's sequence numbers);
``--reliable`` makes it a reliable subscriber (it then takes part in the back-pressure).
"""
from __future__ import annotations

import argparse
import json
import signal
import struct
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rclpy  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

from maglev_ros.nodes._common import LATCHED_TOPICS, message_class  # noqa: E402
from maglev_ros.nodes.summary import KNOWN_TOPICS  # noqa: E402
from maglev_ros.sensor_block import SensorBlockDecoder  # noqa: E402

SENSOR_BLOCK = "maglev_msgs/msg/SensorBlock"
STRING = "std_msgs/msg/String"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
# header-first messages whose stamp is all we need (read from the CDR bytes)
STAMPED = {"maglev_msgs/msg/ModalEstimate", "maglev_msgs/msg/IrregularityProfile",
           "maglev_msgs/msg/MismatchReport"}
PARAMETERS = "maglev_msgs/msg/TwinParameters"
STRING_KEEP_CHARS = 4096            # a longer String (the diagnosis report) is kept as its length only
_I32U32 = struct.Struct("<iI")


def observer_qos(reliable: bool, latched: bool) -> QoSProfile:
    """Best effort matches every writer and never back-pressures; transient local gets a latched
    writer's last message even when it was published before the probe matched."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000 if not latched else 100,
                      reliability=ReliabilityPolicy.RELIABLE if (reliable or latched) else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def header_stamp_ns(raw: bytes) -> int:
    """Header stamp of a little-endian CDR message whose first field is std_msgs/Header."""
    sec, nsec = _I32U32.unpack_from(raw, 4)
    return sec * 1_000_000_000 + nsec


class Probe:
    def __init__(self, node, namespace: str, reliable: bool) -> None:
        self.node = node
        self.ns = namespace.rstrip("/")
        self.reliable = reliable
        self.topics: dict[str, dict] = {}        # topic -> {"type", "rows": [...], ...}
        self.subs = {}
        self.subscribers: dict[str, set] = {}    # topic -> node names subscribing it
        self.publishers: dict[str, set] = {}     # topic -> node names publishing it
        self.diagnostics: dict[str, list] = {}   # node name -> [[recv_ns, blocks_accepted], ...]
        self.subs["/diagnostics"] = node.create_subscription(
            message_class(DIAGNOSTICS), "/diagnostics", self._on_diagnostics,
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                       reliability=ReliabilityPolicy.BEST_EFFORT if not reliable else ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE))
        node.create_timer(0.5, self.discover)
        self.discover()

    def wanted(self, name: str) -> bool:
        return name.startswith(self.ns + "/testline/") or name.startswith(self.ns + "/maglev/")

    def discover(self) -> None:
        me = self.node.get_name()
        for name, types in self.node.get_topic_names_and_types():
            if not self.wanted(name):
                continue
            subs = {i.node_name for i in self.node.get_subscriptions_info_by_topic(name)} - {me}
            self.subscribers.setdefault(name, set()).update(subs)
            pubs = self.node.get_publishers_info_by_topic(name)
            self.publishers.setdefault(name, set()).update(i.node_name for i in pubs)
            if name in self.subs or not pubs:
                continue
            msgtype = next((t for t in types if t in (SENSOR_BLOCK, STRING, PARAMETERS) or t in STAMPED), None)
            if msgtype is not None:
                latched = any(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
                self.subscribe(name, msgtype, latched)

    def subscribe(self, name: str, msgtype: str, latched: bool) -> None:
        entry = self.topics[name] = {"type": msgtype, "latched": latched, "rows": []}
        self.subs[name] = self.node.create_subscription(
            message_class(msgtype), name, self._callback(name, entry, msgtype),
            observer_qos(self.reliable, latched), raw=msgtype != PARAMETERS)

    def _callback(self, name: str, entry: dict, msgtype: str):
        rows = entry["rows"]
        if msgtype == SENSOR_BLOCK:
            dec = SensorBlockDecoder()

            def cb(raw, info) -> None:
                b = dec.decode(raw)
                if b is None:
                    return
                n = b.data.size // max(len(b.channels), 1)
                last = b.stamp_ns + int(round((n - 1) * 1e9 / b.sample_rate_hz)) if b.sample_rate_hz > 0 else b.stamp_ns
                rows.append([info["source_timestamp"], info["received_timestamp"],
                             info["publication_sequence_number"], b.stamp_ns, last])
            return cb
        if msgtype in STAMPED:
            def cb(raw, info) -> None:
                rows.append([info["source_timestamp"], info["received_timestamp"],
                             info["publication_sequence_number"], header_stamp_ns(raw)])
            return cb
        if msgtype == STRING:
            cls = message_class(STRING)

            def cb(raw, info) -> None:
                text = deserialize_message(raw, cls).data
                rows.append([info["source_timestamp"], info["received_timestamp"],
                             info["publication_sequence_number"],
                             text if len(text) <= STRING_KEEP_CHARS else len(text)])
            return cb

        def on_parameters(msg, info) -> None:       # rare: deserialised, the provenance says its data
            rows.append([info["source_timestamp"], info["received_timestamp"],
                         info["publication_sequence_number"], msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
                         int(msg.revision), msg.provenance_json])
        return on_parameters

    def _on_diagnostics(self, msg) -> None:
        recv = time.time_ns()          # the clock of DDS's source/received timestamps
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if "blocks_accepted" in values:
                self.diagnostics.setdefault(st.name, []).append([recv, int(values["blocks_accepted"])])

    def dump(self) -> dict:
        return {"namespace": self.ns, "reliable": self.reliable, "probe_node": self.node.get_name(),
                "topics": self.topics, "diagnostics": self.diagnostics,
                "subscribers": {t: sorted(s) for t, s in self.subscribers.items()},
                "publishers": {t: sorted(s) for t, s in self.publishers.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--namespace", default="")
    ap.add_argument("--reliable", action="store_true")
    ap.add_argument("--max-s", type=float, default=3600.0)
    ap.add_argument("--topic", action="append", default=[], metavar="TYPE:NAME",
                    help="subscribe this topic from the start (the replay's inputs: no first block missed); "
                         "a std_msgs/String one is taken as latched")
    ap.add_argument("--ready-file", help="touched once the probe spins (the caller starts the graph then)")
    a = ap.parse_args(argv)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = {"now": False}

    def on_signal(signum, frame):
        stop["now"] = True
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    from rclpy.executors import SingleThreadedExecutor
    node = rclpy.create_node("keepup_probe", namespace=a.namespace or None)
    probe = Probe(node, a.namespace, a.reliable)
    for spec in a.topic:
        msgtype, name = spec.split(":", 1)
        if name not in probe.subs:
            probe.subscribe(name, msgtype, latched=msgtype == STRING)
    # the graph's outputs from the start too: found by the 0.5 s discovery instead, a node's first
    # outputs could be published before the probe subscribed and matched (then counted as lost)
    for name, msgtype in KNOWN_TOPICS.items():
        full = f"{a.namespace.rstrip('/')}{name}"
        if name.startswith("/maglev/") and full not in probe.subs:
            probe.subscribe(full, msgtype, latched=name in LATCHED_TOPICS)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    if a.ready_file:
        Path(a.ready_file).touch()
    end = time.monotonic() + a.max_s
    while not stop["now"] and time.monotonic() < end:
        ex.spin_once(timeout_sec=0.1)
    probe.discover()                 # the subscriber lists as they are at the end
    out = probe.dump()
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    tmp = Path(a.out).with_suffix(".tmp")
    tmp.write_text(json.dumps(out))
    tmp.replace(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
