"""Node ``echo``: print the messages of a topic (ros2cli's ``ros2 topic echo`` is not on PyPI).

``maglev-ros echo TOPIC [--count N] [--timeout S] [--full]``. SensorBlocks are summarised per
channel (samples, rate, mean/min/max) unless ``--full``; other types print their fields.
The topic's type is discovered from the graph; the name is resolved as ROS does (a relative one
under the node's namespace) and the subscription takes the QoS its publishers offer (best effort,
latched).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node

from maglev_ros.errors import UserError
from maglev_ros.nodes._common import ALLOWED_TYPES, QOS_STREAM, message_class
from maglev_ros.nodes._qos import offered_qos
from maglev_ros.nodes._echo_options import add_arguments


def format_message(msg, full: bool = False) -> str:
    """One readable block of text for a message (SensorBlocks summarised per channel)."""
    name = type(msg).__name__
    if name == "SensorBlock":
        st = msg.header.stamp
        chans = list(msg.channels)
        data = np.asarray(msg.data, dtype=np.float64)
        n = data.size // max(len(chans), 1)
        lines = [f"SensorBlock {msg.header.frame_id or '-'} stamp={st.sec}.{st.nanosec:09d} "
                 f"rate={msg.sample_rate_hz:g} Hz samples={n}"]
        block = data[: n * len(chans)].reshape(n, len(chans)) if chans else data.reshape(0, 0)
        for j, ch in enumerate(chans):
            unit = msg.units[j] if j < len(msg.units) else "?"
            col = block[:, j]
            if full:
                lines.append(f"  {ch} [{unit}]: " + " ".join(f"{v:.6g}" for v in col))
            elif col.size:
                lines.append(f"  {ch:>10} [{unit}] mean={col.mean():+.5g} "
                             f"min={col.min():+.5g} max={col.max():+.5g}")
        return "\n".join(lines)
    if name == "String":
        return f"String: {msg.data}"
    return str(msg)


class EchoNode(Node):
    def __init__(self, topic: str, count: int, full: bool, type_timeout_s: float) -> None:
        super().__init__("echo")
        try:
            resolved = self.resolve_topic_name(topic)
        except Exception as exc:  # noqa: BLE001  (rclpy's invalid-name exceptions: one line for the user)
            raise UserError(f"{topic!r} is not a valid ROS 2 topic name ({str(exc).splitlines()[0]})") from None
        self.topic, self.count, self.full = resolved, count, full
        self.received = 0
        self.finished = False
        msgtype = self._discover_type(type_timeout_s)
        cls = message_class(msgtype)
        if cls is None and msgtype not in ALLOWED_TYPES:
            raise UserError(f"topic {topic} has type {msgtype}, which is not one of the message types echo "
                            f"reads ({', '.join(sorted(ALLOWED_TYPES))})")
        if cls is None:
            raise UserError(f"topic {topic} has type {msgtype}, which is not installed here")
        self.create_subscription(cls, self.topic, self._on_msg, offered_qos(self, self.topic, QOS_STREAM))

    def _discover_type(self, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for name, types in self.get_topic_names_and_types():
                if name == self.topic and types:
                    return types[0]
            time.sleep(0.05)
        raise UserError(f"no publisher of topic {self.topic} appeared within {timeout_s:g} s")

    def _on_msg(self, msg) -> None:
        self.received += 1
        print(format_message(msg, self.full), flush=True)
        print("---", flush=True)
        if self.count and self.received >= self.count:
            self.finished = True


def run(args: argparse.Namespace, ros_args: list[str] | None = None) -> int:
    rclpy.init(args=["echo"] + (ros_args or []))
    node = None
    from rclpy.experimental import EventsExecutor
    executor = EventsExecutor()
    try:
        node = EchoNode(args.topic, args.count, args.full, args.type_timeout)
        executor.add_node(node)
        end = time.monotonic() + args.timeout if args.timeout > 0 else float("inf")
        while rclpy.ok() and not node.finished and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    argv = argv[: len(argv) - len(ros_args)]
    parser = argparse.ArgumentParser(prog="echo", description=__doc__.splitlines()[0])
    add_arguments(parser)
    try:
        return run(parser.parse_args(argv), ros_args)
    except UserError as exc:
        print(f"echo: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
