"""Node ``daq_sim``: a DAQ's drivers, simulated: a contract bag's samples published one message per
sample on driver topics (``/daq/guideway`` Float64MultiArray, ``/daq/imu_<id>`` Imu,
``/daq/gap_<id>`` Range, ``/daq/odom`` Odometry: :mod:`maglev_ros.daq_stream.sim`), paced at the
recording's time (``rate`` x real time; 0: as fast as the subscribers take them, reliable QoS).

With ``config_dir`` it first writes there the metadata (``daq_metadata.json``) and mapping
(``daq_mapping.yaml``) that bring its streams back to the contract through ``daq_adapter``.

Parameters: ``bag`` (required), ``start_s`` (0: from the bag's first sample), ``duration_s`` (0: to
the end), ``rate`` (1.0), ``reliable`` (false: sensor-data QoS, best effort keep-last 5, like a
driver; true: reliable keep-all, nothing lost), ``restamp`` (true: the first sample is stamped with
the node's start time; false: the bag's stamps), ``config_dir`` (""), ``block_s`` (0.1, the
mapping's), ``wait_subscribers`` (0: before publishing, wait until every driver topic has this many
subscribers, at most ``wait_timeout_s``). The node ends once everything is published (and, when
reliable, acknowledged).
"""
from __future__ import annotations

import struct
import sys
import time

from rclpy.duration import Duration
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

from maglev_ros.nodes._common import QOS_STREAM, rel, run_node
from maglev_ros.nodes.daq_adapter import DRIVER_CLASSES
from maglev_ros.nodes._params import Param, declare

PARAMS = (
    Param("bag", "", "contract bag whose samples are published"),
    Param("start_s", 0.0, "start this long after the bag's first sample [s]", range=(0.0, 1e9)),
    Param("duration_s", 0.0, "publish this long of the bag [s] (0: to its end)", range=(0.0, 1e9)),
    Param("rate", 1.0, "x real time (0: as fast as the subscribers take it)", range=(0.0, 1000.0)),
    Param("reliable", False, "reliable keep-all QoS (default: sensor-data QoS, best effort)"),
    Param("restamp", True, "stamp the first sample with the node's start time (false: the bag's stamps)"),
    Param("config_dir", "", "write daq_metadata.json and daq_mapping.yaml here first"),
    Param("block_s", 0.1, "block length of the mapping written [s]", range=(1e-3, 60.0)),
    Param("wait_subscribers", 0, "publish once every driver topic has this many subscribers", range=(0, 1000)),
    Param("wait_timeout_s", 120.0, "wait at most this long for them [s]", range=(0.0, 1e6)),
)
CHUNK = 2000        # messages per timer tick when unpaced
# what rclpy raises when the writer cannot queue a message (rmw: "cannot publish data")
RCLError = _rclpy.RCLError


_F64, _F32 = struct.Struct("<d"), struct.Struct("<f")
_STAMP = struct.Struct("<iI")


class _Serialised:
    """One stream's message as CDR bytes, the sample's stamp and values written in place (rclpy
    builds and serialises an Imu in tens of microseconds; at 18 k messages/s the simulator would be
    the bottleneck of what it measures). The offsets are found by serialising the message once with
    a sentinel in each field."""

    def __init__(self, msg, msg_type: str, n_values: int) -> None:
        from rclpy.serialization import serialize_message
        sentinels = [1.0e300 + 1.0e285 * i for i in range(n_values)]
        if msg_type == "std_msgs/msg/Float64MultiArray":
            msg.data = sentinels
            fmt = [_F64] * n_values
        elif msg_type == "sensor_msgs/msg/Imu":
            msg.linear_acceleration.z = sentinels[0]
            fmt = [_F64]
        elif msg_type == "sensor_msgs/msg/Range":
            sentinels = [3.0e33]
            msg.range = sentinels[0]
            fmt = [_F32]
        elif msg_type == "nav_msgs/msg/Odometry":
            msg.pose.pose.position.x, msg.twist.twist.linear.x = sentinels[0], sentinels[1]
            fmt = [_F64, _F64]
        self.buf = bytearray(serialize_message(msg))
        self.header = hasattr(msg, "header")
        self.fields = []
        for v, f in zip(sentinels, fmt):
            at = self.buf.find(f.pack(v))
            assert at > 0, msg_type
            self.fields.append((at, f))

    def message(self, stamp_ns: int, row) -> bytes:
        if self.header:
            _STAMP.pack_into(self.buf, 4, *divmod(int(stamp_ns), 1_000_000_000))
        for (at, f), v in zip(self.fields, row):
            f.pack_into(self.buf, at, float(v))
        return bytes(self.buf)


def _template(cls, msg_type: str, topic: str):
    msg = cls()
    if hasattr(msg, "header"):
        msg.header.frame_id = topic.rsplit("/", 1)[-1]
    if msg_type == "sensor_msgs/msg/Imu":
        msg.orientation_covariance[0] = -1.0           # REP 145: no orientation estimate
        msg.angular_velocity_covariance[0] = -1.0
    elif msg_type == "sensor_msgs/msg/Range":
        msg.radiation_type = msg.INFRARED              # a laser displacement sensor
        msg.field_of_view = 0.01
        msg.min_range, msg.max_range = 0.0, 0.05
    elif msg_type == "nav_msgs/msg/Odometry":
        msg.child_frame_id = "vehicle"
    return msg


class DaqSimNode(Node):
    def __init__(self) -> None:
        super().__init__("daq_sim")
        from maglev_ros.daq_stream.sim import source_from_bag, write_config
        from maglev_ros.errors import UserError
        v = declare(self, PARAMS)
        if not v["bag"]:
            raise UserError("parameter 'bag': expected a contract bag (-p bag:=PATH)")
        self.rate = v["rate"]
        offset = 0
        if v["restamp"]:
            from maglev_ros.bag_reader import BagReader
            with BagReader(v["bag"]) as r:
                first = min(b.stamp_ns for _, b in r.iter_blocks())
            offset = self.get_clock().now().nanoseconds - first - int(round(v["start_s"] * 1e9))
        self.source = source_from_bag(v["bag"], start_s=v["start_s"], duration_s=v["duration_s"] or None,
                                      offset_ns=offset, block_s=v["block_s"])
        if v["config_dir"]:
            meta, mapping = write_config(self.source, v["config_dir"])
            self.get_logger().info(f"wrote {meta} and {mapping}")
        qos = QOS_STREAM if v["reliable"] else qos_profile_sensor_data
        self.reliable = v["reliable"]
        self.pubs, self.msgs = [], []
        for s in self.source.streams:
            cls = DRIVER_CLASSES[s.msg_type]
            self.pubs.append(self.create_publisher(cls, rel(s.topic), qos))
            self.msgs.append(_Serialised(_template(cls, s.msg_type, s.topic), s.msg_type, s.values.shape[1]))
        self.stream_idx, self.rows = self.source.order()
        self.next = 0
        self.sent = 0
        self.wait_subscribers = v["wait_subscribers"]
        self.wait_deadline = time.monotonic() + v["wait_timeout_s"]
        self.t_wall0 = None
        self.t_stream0 = min(int(s.stamps_ns[0]) for s in self.source.streams)
        self.finished = False
        self.get_logger().info(f"{len(self.stream_idx)} messages on {len(self.pubs)} driver topics "
                               f"({self.source.samples} samples) at {'full speed' if not self.rate else f'{self.rate:g} x real time'}, "
                               f"{'reliable' if self.reliable else 'best effort'}")
        self.create_timer(0.001, self._tick)

    def _tick(self) -> None:
        if self.finished:
            return
        if self.t_wall0 is None:
            if self.wait_subscribers and time.monotonic() < self.wait_deadline:
                if any(p.get_subscription_count() < self.wait_subscribers for p in self.pubs):
                    return
            self.t_wall0 = time.monotonic()
        n = len(self.stream_idx)
        if self.rate > 0:
            now_stream = self.t_stream0 + (time.monotonic() - self.t_wall0) * self.rate * 1e9
        end = min(n, self.next + CHUNK) if self.rate == 0 else n
        streams = self.source.streams
        i = self.next
        while i < end:
            k, r = self.stream_idx[i], self.rows[i]
            s = streams[k]
            st = int(s.stamps_ns[r])
            if self.rate > 0 and st > now_stream:
                break
            try:
                self.pubs[k].publish(self.msgs[k].message(st, s.values[r]))
            except RCLError:
                if not self.reliable:
                    raise
                # reliable keep-all: the writer's history is full until a subscriber acknowledges;
                # offered again on the next tick (the driver is paced by its slowest subscriber)
                self.pubs[k].wait_for_all_acked(Duration(seconds=0.05))
                break
            i += 1
        self.sent += i - self.next
        self.next = i
        if self.next >= n:
            if self.reliable:
                for p in self.pubs:
                    p.wait_for_all_acked(Duration(seconds=30))
            took = time.monotonic() - self.t_wall0
            self.get_logger().info(f"published {self.sent} messages ({self.source.samples} samples) in {took:.2f} s")
            self.finished = True


def main(args=None) -> int:
    return run_node(DaqSimNode, args)


if __name__ == "__main__":
    sys.exit(main())
