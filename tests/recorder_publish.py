"""Publisher process for the recorder test: one message set of each /maglev type, and what was
published dumped as JSON (ros_collect.to_plain).

    python tests/recorder_publish.py OUT.json NAMESPACE TAG DIAG_SUBSCRIBERS

Publishes in NAMESPACE (relative names) with every field set from TAG (so two namespaces carry
different values). A latched message of each latched topic goes out before any subscriber is
there (a recorder must still get it); the rest once the topic has a subscriber. One
DiagnosticArray on /diagnostics once it has DIAG_SUBSCRIBERS subscribers (0: none). Ends when
every reliable subscriber has acknowledged every message.
"""
import json
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from maglev_msgs.msg import MismatchReport, ModalEstimate, SensorBlock, TwinParameters
from rclpy.node import Node
from std_msgs.msg import String

from maglev_ros.nodes._common import QOS_LATCHED, QOS_STREAM
from maglev_ros.nodes._diagnostics import QOS_DIAGNOSTICS
from ros_collect import to_plain as _to_plain

N_STREAM = 3          # messages per stream topic
STAMP_BASE_S = 1_700_000_000    # the test bag's first stamp: outputs in the recording's time


def to_plain(msg):
    """ros_collect's plain form, octets as ints (as rosbags decodes them)."""
    if isinstance(msg, bytes) and len(msg) == 1:
        return msg[0]
    if hasattr(msg, "get_fields_and_field_types"):
        return {f: to_plain(getattr(msg, f)) for f in msg.get_fields_and_field_types()}
    if isinstance(msg, list):
        return [to_plain(v) for v in msg]
    return _to_plain(msg)


def fill(msg, tag: int, k: int):
    """Every field of ``msg`` set from (tag, k): distinct per field, message and namespace."""
    base = 1000.0 * tag + 10.0 * k
    for i, (name, typ) in enumerate(msg.get_fields_and_field_types().items()):
        v = base + i + 0.25
        if name == "header":
            msg.header.stamp.sec, msg.header.stamp.nanosec = STAMP_BASE_S, 100_000_000 * k + tag
            msg.header.frame_id = f"frame-{tag}-{k}"
        elif typ == "string":
            setattr(msg, name, f"{name}-{tag}-{k}")
        elif typ in ("double", "float"):
            setattr(msg, name, v)
        elif typ in ("uint32", "int32"):
            setattr(msg, name, int(tag * 100 + k))
        elif typ == "octet":
            setattr(msg, name, bytes([k % 3]))
        elif typ == "sequence<string>":
            setattr(msg, name, [f"{name}{j}-{tag}" for j in range(3)])
        elif typ in ("sequence<double>", "sequence<float>"):
            setattr(msg, name, [v + 0.5 * j for j in range(6)])
        elif typ == "sequence<boolean>":
            setattr(msg, name, [bool((j + k) % 2) for j in range(3)])
        elif typ.startswith("sequence<"):
            setattr(msg, name, [fill(_nested[typ](), tag, k * 10 + j) for j in range(2)])
        else:
            raise TypeError(f"{type(msg).__name__}.{name}: no filler for {typ}")
    return msg


def _nested_types():
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
    from maglev_msgs.msg import ModalMode
    return {"sequence<maglev_msgs/ModalMode>": ModalMode,
            "sequence<diagnostic_msgs/DiagnosticStatus>": DiagnosticStatus,
            "sequence<diagnostic_msgs/KeyValue>": KeyValue}


_nested = _nested_types()


def main():
    out, namespace, tag, diag_subs = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    rclpy.init()
    node = Node("recorder_publish", namespace=namespace)
    sent: dict[str, list] = {}

    def pub(p, topic, msg):
        p.publish(msg)
        sent.setdefault(topic, []).append(to_plain(msg))

    latched = {"maglev/twin/parameters": node.create_publisher(TwinParameters, "maglev/twin/parameters", QOS_LATCHED),
               "maglev/diagnosis": node.create_publisher(String, "maglev/diagnosis", QOS_LATCHED)}
    streams = {"maglev/modes": node.create_publisher(ModalEstimate, "maglev/modes", QOS_STREAM),
               "maglev/mismatch": node.create_publisher(MismatchReport, "maglev/mismatch", QOS_STREAM),
               "maglev/twin/residual/vehicle_gap": node.create_publisher(SensorBlock, "maglev/twin/residual/vehicle_gap", QOS_STREAM)}
    # before any subscriber: only a transient-local subscription gets these
    pub(latched["maglev/twin/parameters"], "maglev/twin/parameters", fill(TwinParameters(), tag, 0))
    pub(latched["maglev/diagnosis"], "maglev/diagnosis", String(data=json.dumps({"schema": "test", "tag": tag})))
    diag = node.create_publisher(DiagnosticArray, "/diagnostics", QOS_DIAGNOSTICS) if diag_subs else None
    every = [*latched.values(), *streams.values()] + ([diag] if diag else [])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (
            all(p.get_subscription_count() >= 1 for p in every)
            and (diag is None or diag.get_subscription_count() >= diag_subs)):
        time.sleep(0.05)
    from rclpy.duration import Duration
    # the late joiner has the first latched message before a second one replaces it (depth 1)
    for p in latched.values():
        p.wait_for_all_acked(Duration(seconds=60))
    for k in range(N_STREAM):
        pub(streams["maglev/modes"], "maglev/modes", fill(ModalEstimate(), tag, k))
        pub(streams["maglev/mismatch"], "maglev/mismatch", fill(MismatchReport(), tag, k))
        blk = fill(SensorBlock(), tag, k)
        blk.channels, blk.units = ["M1G", "M2G", "M3G"], ["m", "m", "m"]
        blk.sample_rate_hz = 20.0               # 2 samples a block, a block every 0.1 s: no gaps
        blk.data = [float(tag + 0.125 * (k * 6 + j)) for j in range(6)]
        pub(streams["maglev/twin/residual/vehicle_gap"], "maglev/twin/residual/vehicle_gap", blk)
    pub(latched["maglev/twin/parameters"], "maglev/twin/parameters", fill(TwinParameters(), tag, 1))
    if diag is not None:
        pub(diag, "/diagnostics", fill(DiagnosticArray(), tag, 0))
    acked = all(p.wait_for_all_acked(Duration(seconds=60)) for p in every)
    with open(out, "w") as f:
        json.dump({"acked": acked, "sent": sent}, f)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
