"""Node ``daq_adapter``: DAQ drivers' per-sample messages -> the contract's SensorBlocks, live.

Takes what drivers publish (``sensor_msgs/Imu``, ``sensor_msgs/Range``, ``nav_msgs/Odometry``,
``std_msgs/Float64``, ``std_msgs/Float64MultiArray``), as the mapping file says
(:mod:`maglev_ros.daq_stream.mapping`), and publishes contract SensorBlocks on
``/testline/<...>`` (SI units, blocks of ``block_s``, aligned per topic on a stamp grid:
:mod:`maglev_ros.daq_stream.batcher`) and the recording's metadata, read from a YAML or JSON file,
latched on ``/testline/metadata``: the suite's nodes run on it as on a replay.

Driver subscriptions are reliable by default and follow the reliability their publishers offer
(``_qos.SensorSubscription``: a driver with ``qos_profile_sensor_data`` is taken best effort);
driver topic names are relative like the graph's (a namespace moves them too).

Health: ``/diagnostics`` (WARN on samples missing, late, duplicated or off the stamp grid, a
stamp rate other than the stated one, malformed messages) and ``maglev/status`` (state ready,
``detail`` the counts as JSON, updated every second).

Parameters: ``mapping`` (mapping YAML, required), ``metadata`` (metadata YAML/JSON, required),
``max_wait_s`` (0.5: a block waits at most this long, of stream time and of wall time, for a lagging
channel, then goes out with NaN there), ``idle_flush_s`` (1.0: no driver message for this long of wall time hands
out the open blocks), ``frame_id`` ("daq"), ``wait_subscribers`` (0: before subscribing to the
drivers, wait until every contract topic it publishes has this many subscribers, at most
``wait_timeout_s``; tests and demos lose nothing at the start).
"""
from __future__ import annotations

import json
import sys
import time

from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Imu, Range
from std_msgs.msg import Float64, Float64MultiArray, String

from maglev_msgs.msg import SensorBlock
from maglev_ros.contract import TOPIC_METADATA
from maglev_ros.nodes._common import QOS_STREAM, msg_from_block, run_node
from maglev_ros.nodes._diagnostics import ERROR, OK, WARN, Check, NodeDiagnostics
from maglev_ros.nodes._lifecycle import NodeLifecycle
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import SensorSubscription, publisher

# the mapping's types (daq_stream.mapping.DRIVER_TYPES) -> rclpy classes
DRIVER_CLASSES = {"sensor_msgs/msg/Imu": Imu, "sensor_msgs/msg/Range": Range, "nav_msgs/msg/Odometry": Odometry,
                  "std_msgs/msg/Float64": Float64, "std_msgs/msg/Float64MultiArray": Float64MultiArray}

PARAMS = (
    Param("mapping", "", "mapping YAML: driver topic and field -> contract channel (docs/daq_stream.md)"),
    Param("metadata", "", "the recording's metadata, YAML or JSON (the contract's document)"),
    Param("max_wait_s", 0.5, "a block waits at most this long (stream and wall time) for a lagging channel [s]",
          range=(0.0, 3600.0)),
    Param("idle_flush_s", 1.0, "no driver message for this long hands out the open blocks [s] (0: never)",
          range=(0.0, 1e6), apply=lambda node, v: setattr(node, "idle_flush_s", v)),
    Param("frame_id", "daq", "frame_id of the SensorBlocks published"),
    Param("wait_subscribers", 0, "subscribe to the drivers only once every contract topic published has "
                                 "this many subscribers", range=(0, 1000)),
    Param("wait_timeout_s", 120.0, "wait at most this long for them [s]", range=(0.0, 1e6)),
)


class DaqAdapterNode(Node):
    def __init__(self) -> None:
        super().__init__("daq_adapter")
        from maglev_ros.daq_stream.batcher import BlockBatcher
        from maglev_ros.daq_stream.mapping import load_mapping, load_metadata_file
        from maglev_ros.errors import UserError
        v = declare(self, PARAMS)
        for key in ("mapping", "metadata"):
            if not v[key]:
                raise UserError(f"parameter '{key}': expected a file path (-p {key}:=FILE)")
        self.metadata = load_metadata_file(v["metadata"])
        self.mapping = load_mapping(v["mapping"], self.metadata)
        self.batcher = BlockBatcher(self.mapping, frame_id=v["frame_id"], max_wait_s=v["max_wait_s"])
        self.idle_flush_s = v["idle_flush_s"]
        self.wait_subscribers = v["wait_subscribers"]
        self.wait_deadline = time.monotonic() + v["wait_timeout_s"]
        self.last_msg = None
        self.blocks_out = 0
        self.subs = []
        self.diagnostics = NodeDiagnostics(self)
        self.diagnostics.add_check(self.check)
        self.meta_pub = publisher(self, String, TOPIC_METADATA)
        self.pubs = {t: publisher(self, SensorBlock, t) for t in self.mapping.contract_topics}
        msg = String()
        msg.data = self.metadata.to_json()
        self.meta_pub.publish(msg)
        self.lifecycle = NodeLifecycle(self, ready=True, diagnostics=self.diagnostics)
        self._describe()
        self._subscribed = False
        self._gate = self.create_timer(0.05, self._subscribe_when_ready)
        self.create_timer(0.2, self._idle)
        self.create_timer(1.0, self._say_counts)

    def _describe(self) -> None:
        m = self.mapping
        for d in m.drivers.values():
            chans = ", ".join(f"{c.name}<-{c.field or f'data[{c.index}]'}"
                              + (f" [{c.unit}->{c.si_unit}]" if c.unit != c.si_unit else "")
                              + (" -g" if c.remove_gravity else "") + (" *-1" if c.sign < 0 else "")
                              for c in d.channels)
            self.get_logger().info(f"{d.topic} ({d.msg_type}, stamps: {d.stamp_source}): {chans}")
        for t in m.contract_topics:
            self.get_logger().info(f"{t}: {len(m.on_topic(t))} channel(s) at {m.rates_hz[t]:g} Hz, "
                                   f"blocks of {m.block_samples(t)}")
        unmapped = [sid for sid in self.metadata.sensors if sid not in {c.name for c in m.channels}]
        if unmapped:      # the nodes then see a recording without them, as a bag that lacks them
            self.get_logger().warning(f"{m.source}: the metadata's sensors {', '.join(unmapped)} have no channel "
                                      f"in the mapping; they are not published")

    # ------------------------------------------------------------------ start-up
    def _subscribe_when_ready(self) -> None:
        if self._subscribed:
            return
        if self.wait_subscribers > 0 and time.monotonic() < self.wait_deadline:
            if any(p.get_subscription_count() < self.wait_subscribers for p in self.pubs.values()):
                return
        elif self.wait_subscribers > 0:
            self.get_logger().warning(f"not every contract topic has {self.wait_subscribers} subscriber(s) "
                                      f"after the wait: taking the drivers' data now")
        self._subscribed = True
        self._gate.cancel()
        for d in self.mapping.drivers.values():
            cls = DRIVER_CLASSES[d.msg_type]
            # (SensorSubscription's one timer per node checks every sensor subscription's reliability)
            self.subs.append(SensorSubscription(self, cls, d.topic, self._cb(d.topic, cls, d.stamp_source == "receive"),
                                                qos=QOS_STREAM, raw=True))
        self.get_logger().info(f"taking {len(self.subs)} driver topic(s)")

    # ------------------------------------------------------------------ data
    def _cb(self, topic: str, cls, receive_stamp: bool):
        """The raw (serialised) message's mapped fields read at their CDR offsets (daq_stream.cdr: a
        fraction of rclpy's deserialisation); rclpy's deserialisation for what that reader does not take."""
        from rclpy.serialization import deserialize_message
        add_cdr, add = self.batcher.add_cdr, self.batcher.add_message
        clock = self.get_clock()

        def on_msg(buf) -> None:
            self.last_msg = time.monotonic()
            recv = clock.now().nanoseconds if receive_stamp else 0
            out = add_cdr(topic, buf, recv)
            if out is None:
                try:
                    out = add(topic, deserialize_message(buf, cls), recv)
                except Exception:  # noqa: BLE001  (bytes rclpy cannot read either: counted, never fatal)
                    self.batcher.malformed[topic] += 1
                    return
            for t, blk in out:
                self._publish(t, blk)
        return on_msg

    def _publish(self, topic: str, blk) -> None:
        self.pubs[topic].publish(msg_from_block(blk))
        self.blocks_out += 1

    def _idle(self) -> None:
        for t, blk in self.batcher.poll():          # blocks whose wait for a lagging channel is over
            self._publish(t, blk)
        if self.last_msg is None or not self.idle_flush_s:
            return
        if time.monotonic() - self.last_msg < self.idle_flush_s:
            return
        out = self.batcher.flush()
        if out:
            for t, blk in out:
                self._publish(t, blk)
            self.get_logger().info(f"no driver message for {self.idle_flush_s:g} s: handed out {len(out)} open "
                                   f"block(s)")
        self.last_msg = None

    # ------------------------------------------------------------------ health
    def counts(self) -> dict:
        st = self.batcher.stats()
        return {"blocks": self.blocks_out, "messages": sum(st.messages.values()),
                "malformed": sum(st.malformed.values()), **st.to_dict()["totals"],
                "rate_mismatch": [t.topic for t in st.topics if t.rate_mismatch]}

    def _say_counts(self) -> None:
        self.lifecycle.set_detail(json.dumps(self.counts()))

    def check(self) -> Check:
        st = self.batcher.stats()
        values = {"blocks_published": self.blocks_out}
        problems = []
        for t in st.topics:
            values[f"{t.topic} stamp_rate_hz"] = "" if t.stamp_rate_hz is None else f"{t.stamp_rate_hz:.6g}"
            values[f"{t.topic} rate_hz"] = f"{t.rate_hz:g}"
            if t.rate_mismatch:
                problems.append(f"{t.topic}: stamps advance at {t.stamp_rate_hz:.6g} Hz, stated {t.rate_hz:g} Hz")
            for c in t.channels:
                for key in ("samples", "missing", "late", "duplicate", "off_grid", "gaps", "gap_samples"):
                    values[f"{c.channel} {key}"] = getattr(c, key)
                bad = {k: getattr(c, k) for k in ("missing", "late", "duplicate", "off_grid") if getattr(c, k)}
                if bad:
                    problems.append(f"{c.channel} " + " ".join(f"{k} {n}" for k, n in bad.items()))
        for d, n in st.malformed.items():
            values[f"{d} malformed"] = n
            if n:
                problems.append(f"{d}: {n} message(s) without the mapped field")
        if not self._subscribed:
            return Check(WARN, f"waiting for {self.wait_subscribers} subscriber(s) per contract topic", values)
        if not problems:
            return Check(OK, "", values)
        level = ERROR if any(t.rate_mismatch for t in st.topics) else WARN
        return Check(level, "; ".join(problems[:8]) + (" ..." if len(problems) > 8 else ""), values)


def main(args=None) -> int:
    return run_node(DaqAdapterNode, args)


if __name__ == "__main__":
    sys.exit(main())
