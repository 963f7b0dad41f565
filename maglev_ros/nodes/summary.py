"""Node ``summary``: counts and fingerprints what flows through the graph, and says so at the end.

Used by ``maglev-ros demo`` to show that the recordings went through the node graph and what the
graph made of them: per topic the messages, SensorBlock samples, stamp span, out-of-order or
repeated stamps, and a content digest (:func:`message_digest`) so that runs can be compared;
per replayed recording the messages the replay published (its ``recording_end`` event) and the
recording's messages received here (those before its end: the replay announces the end once every
reliable subscriber took the last one, and starts the next recording only once this node said
``done``). Topics: the contract's and the suite's known outputs, subscribed
from the start (none misses a first message), plus any other ``testline/*`` or ``maglev/*`` topic
found in the graph; names are matched under the node's namespace and reported without it.

It ends when the replay says ``finished`` (``maglev/replay/events``) and every node taking part in
the run protocol said ``done`` for the last recording (``maglev/status``; after ``give_up_s`` it
ends without those the replay gave up on too), once nothing arrived for ``settle_s``. Without a
replay (a live stream) it ends ``idle_s`` after the last message. ``max_s`` is a hard stop.

Parameters: ``idle_s`` (3), ``settle_s`` (1), ``give_up_s`` (10), ``max_s`` (3600), ``json_out``
(the summary as JSON, kept current while the graph runs), ``reliable`` (false: best effort, never
slows the graph down; true: reliable keep-all, the replay waits for it and every message counts -
the demo's choice; a topic whose publishers are all best effort is then read best effort).
"""
from __future__ import annotations

import array
import hashlib
import json
import struct
import sys
import time

import numpy as np

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from maglev_ros.nodes._common import message_class, rel, run_node
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._lifecycle import (FINISHED, QOS_STATUS_READER, RECORDING_END, TOPIC_REPLAY_EVENTS,
                                         TOPIC_STATUS, NodeLifecycle, NodeStatus)

SENSOR_BLOCK = "maglev_msgs/msg/SensorBlock"
# subscribed at start: the replay's writers and the nodes' outputs (topic -> type)
KNOWN_TOPICS = {
    "/testline/metadata": "std_msgs/msg/String",
    **{t: SENSOR_BLOCK for t in ("/testline/guideway/accel", "/testline/guideway/displacement",
                                 "/testline/vehicle/accel", "/testline/vehicle/gap",
                                 "/testline/vehicle/position", "/testline/vehicle/body_accel")},
    **{f"/maglev/twin/{kind}/{g}": SENSOR_BLOCK for kind in ("predicted", "residual")
       for g in ("guideway_accel", "guideway_displacement", "vehicle_accel", "vehicle_gap", "body_accel")},
    "/maglev/modes": "maglev_msgs/msg/ModalEstimate",
    "/maglev/irregularity": "maglev_msgs/msg/IrregularityProfile",
    "/maglev/twin/parameters": "maglev_msgs/msg/TwinParameters",
    "/maglev/mismatch": "maglev_msgs/msg/MismatchReport",
    "/maglev/diagnosis": "std_msgs/msg/String",
}
PROTOCOL_TOPICS = ("/" + TOPIC_STATUS, "/" + TOPIC_REPLAY_EVENTS)

# What the digests leave out, because it depends on the wall clock and not on the recordings:
# the header stamp of the messages a node stamps with its clock when it publishes (parameters,
# the diagnosis' mismatch reports), and the wall-time keys of the JSON documents they carry.
STAMPED_AT_PUBLICATION = ("maglev_msgs/msg/TwinParameters", "maglev_msgs/msg/MismatchReport")
JSON_FIELDS = {"maglev_msgs/msg/TwinParameters": "provenance_json",
               "maglev_msgs/msg/MismatchReport": "detail_json"}
JSON_TOPICS = ("/maglev/diagnosis",)
WALL_CLOCK_KEYS = ("time_unix_s", "wall_time_s", "elapsed_s")
DIGEST_RULE = ("sha256 over the sorted sha256 of each message's fields (order-free: a node may interleave "
               "two sources on a topic; fields in definition order, arrays as their element bytes, numbers "
               "as float64/decimal, strings UTF-8, each with its length; not the CDR bytes, whose alignment "
               "padding a writer leaves uninitialised); not hashed, as wall-clock dependent: header.stamp of "
               + ", ".join(STAMPED_AT_PUBLICATION) + "; JSON keys " + ", ".join(WALL_CLOCK_KEYS)
               + " in " + ", ".join(f"{t.rsplit('/', 1)[1]}.{f}" for t, f in JSON_FIELDS.items())
               + " and " + ", ".join(JSON_TOPICS))


def _drop_wall_clock(doc):
    if isinstance(doc, dict):
        return {k: _drop_wall_clock(v) for k, v in doc.items() if k not in WALL_CLOCK_KEYS}
    if isinstance(doc, list):
        return [_drop_wall_clock(v) for v in doc]
    return doc


def _normal_json(text: str) -> str:
    try:
        return json.dumps(_drop_wall_clock(json.loads(text)), sort_keys=True)
    except ValueError:
        return text


def _hash_fields(h, value) -> None:
    """Feed ``value`` (a message, array, string, number) to ``h``, the same bytes for the same content."""
    if hasattr(value, "get_fields_and_field_types"):
        for name in value.get_fields_and_field_types():
            _hash_fields(h, getattr(value, name))
        return
    if isinstance(value, (array.array, np.ndarray, bytes, bytearray)):
        b = bytes(value) if isinstance(value, (bytes, bytearray)) else value.tobytes()
    elif isinstance(value, (list, tuple)):
        h.update(len(value).to_bytes(8, "little"))
        for v in value:
            _hash_fields(h, v)
        return
    elif isinstance(value, str):
        b = value.encode()
    elif isinstance(value, float):
        b = struct.pack("<d", value)
    else:                                   # bool, int
        b = str(int(value)).encode()
    h.update(len(b).to_bytes(8, "little"))
    h.update(b)


def message_digest(topic: str, msgtype: str, msg) -> str:
    """sha256 of a message's fields, after removing what the wall clock decides (``msg`` is changed)."""
    if msgtype in STAMPED_AT_PUBLICATION:
        msg.header.stamp.sec = msg.header.stamp.nanosec = 0
    field = JSON_FIELDS.get(msgtype, "data" if topic in JSON_TOPICS else None)
    if field is not None:
        setattr(msg, field, _normal_json(getattr(msg, field)))
    h = hashlib.sha256()
    _hash_fields(h, msg)
    return h.hexdigest()


def combined_digest(digests: list[str]) -> str:
    return hashlib.sha256("".join(sorted(digests)).encode()).hexdigest()


PARAMS = (
    Param("idle_s", 3.0, "without a replay: stop this long after the last message [s]", range=(0.0, 1e9),
          apply=lambda node, v: setattr(node, "idle_s", v)),
    Param("settle_s", 1.0, "after the replay's end and every node's results: stop once nothing arrived "
          "for this long [s]", range=(0.0, 1e9), apply=lambda node, v: setattr(node, "settle_s", v)),
    Param("give_up_s", 10.0, "after the replay's 'finished': stop without the results of nodes that did "
          "not say done within this long [s]", range=(0.0, 1e9), apply=lambda node, v: setattr(node, "give_up_s", v)),
    Param("max_s", 3600.0, "stop this long after the start at the latest [s]", range=(0.0, 1e9),
          apply=lambda node, v: setattr(node, "max_s", v)),
    Param("json_out", "", "also write the summary as JSON to this path (empty: none)"),
    Param("reliable", False, "subscribe reliable keep-all (the replay waits for this node; every message "
          "counts) instead of best effort"),
)


class SummaryNode(Node):
    def __init__(self) -> None:
        super().__init__("summary")
        v = declare(self, PARAMS)
        self.idle_s, self.settle_s, self.give_up_s = v["idle_s"], v["settle_s"], v["give_up_s"]
        self.max_s, self.json_out, self.reliable = v["max_s"], v["json_out"], bool(v["reliable"])
        self.ns = self.get_namespace().rstrip("/")
        self.stats: dict[str, dict] = {}
        self._digests: dict[str, list[str]] = {}
        self._subs: dict[str, object] = {}
        self.recordings: list[dict] = []
        self._received: dict[str, int] = {}        # the current recording's messages so far
        self.statuses: dict[str, NodeStatus] = {}
        self.finished_event = None              # the replay's "finished" event
        self.t_finished = None
        self.t_start = time.monotonic()
        self.t_last = None
        self._t_written = -1.0
        self.ended_by = ""
        self.finished = False
        for topic, msgtype in KNOWN_TOPICS.items():
            self._subscribe(topic, msgtype, None)
        self.create_subscription(String, TOPIC_STATUS, self._on_status, QOS_STATUS_READER)
        self.lifecycle = NodeLifecycle(self)   # ready once subscribed: the replay waits for that
        self.create_timer(0.2, self._tick)

    # -- subscriptions ---------------------------------------------------------------------
    def _qos(self, topic: str, publishers) -> QoSProfile:
        """Reliable keep-all when asked and some publisher is reliable; the replay's metadata is
        read transient-local (its writer is created just before it publishes)."""
        reliable = self.reliable and (not publishers or any(
            i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in publishers))
        latched = reliable and (topic == "/testline/metadata" or bool(publishers) and all(
            i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in publishers))
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000,
                          reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

    def _subscribe(self, topic: str, msgtype: str, publishers) -> None:
        cls = message_class(msgtype)
        if cls is None:
            return
        if topic not in self.stats:
            self.stats[topic] = {"type": msgtype, "messages": 0, "samples": 0, "span_s": 0.0,
                                 "out_of_order": 0, "repeated": 0, "digest": None,
                                 "first_stamp_s": None, "last_stamp_s": None}
            self._digests[topic] = []
        else:
            self.destroy_subscription(self._subs.pop(topic))
        self._subs[topic] = self.create_subscription(cls, rel(topic), self._cb(topic, msgtype),
                                                     self._qos(topic, publishers))

    def _subscribe_new(self) -> None:
        for name, types in self.get_topic_names_and_types():
            if self.ns and not name.startswith(self.ns + "/"):
                continue
            topic = name[len(self.ns):]
            if topic in PROTOCOL_TOPICS or not topic.startswith(("/testline/", "/maglev/")):
                continue
            if topic not in self.stats:
                self._subscribe(topic, types[0], self.get_publishers_info_by_topic(name))
            elif self._subs[topic].qos_profile.reliability == ReliabilityPolicy.RELIABLE:
                # subscribed at start as reliable: a best-effort-only publisher (a DAQ driver) never matches
                pubs = self.get_publishers_info_by_topic(name)
                if pubs and all(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in pubs):
                    self._subscribe(topic, self.stats[topic]["type"], pubs)

    def _cb(self, topic: str, msgtype: str):
        st = self.stats[topic]
        seg = st.setdefault("_segment", {"first": None, "last": None})

        def on_msg(msg) -> None:
            self.t_last = time.monotonic()
            st["messages"] += 1
            if topic.startswith("/testline/"):
                self._received[topic] = self._received.get(topic, 0) + 1
            header = getattr(msg, "header", None)
            if header is not None:
                t = header.stamp.sec + header.stamp.nanosec * 1e-9
                if seg["last"] is not None:
                    if t < seg["last"]:
                        st["out_of_order"] += 1
                    elif t == seg["last"]:
                        st["repeated"] += 1
                if seg["first"] is None:
                    seg["first"] = t
                seg["last"] = t if seg["last"] is None else max(t, seg["last"])
                st["first_stamp_s"] = t if st.get("first_stamp_s") is None else min(t, st["first_stamp_s"])
                st["last_stamp_s"] = t if st.get("last_stamp_s") is None else max(t, st["last_stamp_s"])
            if hasattr(msg, "channels") and hasattr(msg, "data") and len(msg.channels):
                st["samples"] += len(msg.data) // len(msg.channels)
            self._digests[topic].append(message_digest(topic, msgtype, msg))   # last: it may blank the stamp
        return on_msg

    # -- the run protocol ------------------------------------------------------------------
    def on_recording_end(self, index: int) -> None:
        """NodeLifecycle's hook: called before this node says done, so before the next recording."""
        ev = self.lifecycle.event(RECORDING_END, index)
        self.recordings.append({"index": index, "bag": ev.bag if ev else "",
                                "published": dict(ev.messages) if ev else {}, "received": self._received})
        self._received = {}
        self._new_segments(inputs=True)

    def on_recording_start(self, index: int) -> None:
        """NodeLifecycle's hook: the nodes' results of the last recording came before (they said done)."""
        self._new_segments(inputs=False)

    def _new_segments(self, inputs: bool) -> None:
        """The next recording's time starts again: its stamps are checked for order among themselves.
        The recording's own messages end before its end event, the nodes' results before the next start."""
        for topic, st in self.stats.items():
            if topic.startswith("/testline/") != inputs:
                continue
            seg = st["_segment"]
            if seg["first"] is not None:
                st["span_s"] += seg["last"] - seg["first"]
            seg["first"] = seg["last"] = None

    def _check_finished(self) -> None:
        if self.finished_event is None:
            ev = self.lifecycle.event(FINISHED)
            if ev is not None:
                self.finished_event, self.t_finished = ev, time.monotonic()

    def _on_status(self, msg) -> None:
        st = NodeStatus.from_json(msg.data)
        if st is not None and st.node != self.get_name():
            self.statuses[st.node] = st

    def _results_out(self, now: float) -> bool:
        last = self.finished_event.index
        done = all(st.done >= last for st in self.statuses.values())
        return (done or now - self.t_finished > self.give_up_s) and now - self.t_finished >= self.settle_s

    # -- output ----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        topics = {}
        for topic, st in sorted(self.stats.items()):
            seg = st["_segment"]
            d = {k: v for k, v in st.items() if not k.startswith("_")}
            d["span_s"] = st["span_s"] + ((seg["last"] - seg["first"]) if seg["first"] is not None else 0.0)
            d["digest"] = combined_digest(self._digests[topic]) if self._digests[topic] else None
            topics[topic] = d
        return {"topics": topics, "recordings": self.recordings,
                "finished": self.finished_event is not None, "ended_by": self.ended_by,
                "nodes": {n: {"state": s.state, "done": s.done} for n, s in sorted(self.statuses.items())},
                "digest_rule": DIGEST_RULE}

    def _write_json(self) -> None:
        """Atomically (a reader never sees half a file; a stop mid-write loses nothing written)."""
        from maglev_ros import outputs
        outputs.write_json(self.json_out, self.to_dict(), indent=1)

    def _tick(self) -> None:
        self._subscribe_new()
        self._check_finished()
        now = time.monotonic()
        if self.json_out and self.t_last is not None and self.t_last > self._t_written:
            # kept current while the graph runs: the launcher may stop us before the end
            self._t_written = now
            self._write_json()
        quiet_s = now - self.t_last if self.t_last is not None else now - self.t_start
        if self.finished_event is not None:
            end = "finished" if quiet_s >= self.settle_s and self._results_out(now) else ""
        elif not self.lifecycle.events_seen:        # no replay: a live stream's pause ends it
            end = "idle" if self.t_last is not None and quiet_s > self.idle_s else ""
        else:
            end = ""
        if not end and now - self.t_start > self.max_s:
            end = "max_s"
        if end:
            self.ended_by, self.finished = end, True
            print(format_summary(self.to_dict()), flush=True)
            if self.json_out:
                self._write_json()


def format_summary(summary: dict) -> str:
    lines = [f"{'topic':40s} {'messages':>9s} {'samples':>10s} {'span s':>8s} {'order':>6s}  digest"]
    for topic, s in sorted(summary["topics"].items()):
        order = "ok" if not (s["out_of_order"] or s["repeated"]) else f"{s['out_of_order']}/{s['repeated']}!"
        digest = (s["digest"] or "-")[:12]
        lines.append(f"{topic:40s} {s['messages']:9d} {s['samples']:10d} {s['span_s']:8.2f} {order:>6s}  {digest}")
    return "\n".join(lines)


def main(args=None) -> int:
    return run_node(SummaryNode, args)


if __name__ == "__main__":
    sys.exit(main())
