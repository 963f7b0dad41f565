"""Node ``summary``: counts what flows through the graph and prints a table when it goes quiet.

Used by ``maglev-ros demo`` to show that a replay went through the node graph: per topic the
messages, SensorBlock samples, stamp range and any out-of-order or repeated stamps. Topics are
discovered from the graph (every /testline/* and /maglev/* topic of the node's namespace, named
without it). Parameters: ``idle_s`` (stop this long after the last message, default 3, live),
``max_s`` (hard stop, default 600, live), ``json_out`` (also write the summary as JSON to this path).
"""
from __future__ import annotations

import sys
import time

from rclpy.node import Node

from maglev_ros.nodes._common import message_class, run_node
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import local_topic, subscription

PARAMS = (
    Param("idle_s", 3.0, "stop this long after the last message [s]", range=(0.0, 1e9),
          apply=lambda node, v: setattr(node, "idle_s", v)),
    Param("max_s", 600.0, "stop this long after the start at the latest [s]", range=(0.0, 1e7),
          apply=lambda node, v: setattr(node, "max_s", v)),
    Param("json_out", "", "also write the summary as JSON to this path (empty: none)"),
)


class SummaryNode(Node):
    def __init__(self) -> None:
        super().__init__("summary")
        v = declare(self, PARAMS)
        self.idle_s, self.max_s, self.json_out = v["idle_s"], v["max_s"], v["json_out"]
        self.stats: dict[str, dict] = {}
        self.t_start = time.monotonic()
        self.t_last = None
        self._t_written = -1.0
        self.finished = False
        self.create_timer(0.2, self._tick)

    def _subscribe_new(self) -> None:
        for fq_name, types in self.get_topic_names_and_types():
            name = local_topic(self, fq_name)     # the graph's name within our namespace
            if name is None or name in self.stats or not name.startswith(("/testline/", "/maglev/")):
                continue
            cls = message_class(types[0])
            if cls is None:
                continue
            self.stats[name] = {"type": types[0], "messages": 0, "samples": 0, "first_stamp_s": None,
                                "last_stamp_s": None, "out_of_order": 0, "repeated": 0}
            subscription(self, cls, name, self._cb(name))

    def _cb(self, topic: str):
        st = self.stats[topic]

        def on_msg(msg) -> None:
            self.t_last = time.monotonic()
            st["messages"] += 1
            header = getattr(msg, "header", None)
            if header is not None:
                t = header.stamp.sec + header.stamp.nanosec * 1e-9
                if st["last_stamp_s"] is not None:
                    if t < st["last_stamp_s"]:
                        st["out_of_order"] += 1
                    elif t == st["last_stamp_s"]:
                        st["repeated"] += 1
                if st["first_stamp_s"] is None:
                    st["first_stamp_s"] = t
                st["last_stamp_s"] = t if st["last_stamp_s"] is None else max(t, st["last_stamp_s"])
            if hasattr(msg, "channels") and hasattr(msg, "data") and len(msg.channels):
                st["samples"] += len(msg.data) // len(msg.channels)
        return on_msg

    def _write_json(self) -> None:
        """Atomically (a reader never sees half a file; a stop mid-write loses nothing written)."""
        from maglev_ros import outputs
        outputs.write_json(self.json_out, self.stats, indent=1)

    def _tick(self) -> None:
        self._subscribe_new()
        now = time.monotonic()
        if self.json_out and self.t_last is not None and self.t_last > self._t_written:
            # kept current while the graph runs: the launcher may stop us before we are idle
            self._t_written = now
            self._write_json()
        quiet = self.t_last is not None and now - self.t_last > self.idle_s
        if quiet or now - self.t_start > self.max_s:
            self.finished = True
            print(format_summary(self.stats), flush=True)
            if self.json_out:
                self._write_json()


def format_summary(stats: dict) -> str:
    lines = [f"{'topic':40s} {'messages':>9s} {'samples':>10s} {'span s':>8s} {'order':>6s}"]
    for topic in sorted(stats):
        s = stats[topic]
        span = (s["last_stamp_s"] - s["first_stamp_s"]) if s["first_stamp_s"] is not None else 0.0
        order = "ok" if not (s["out_of_order"] or s["repeated"]) else f"{s['out_of_order']}/{s['repeated']}!"
        lines.append(f"{topic:40s} {s['messages']:9d} {s['samples']:10d} {span:8.2f} {order:>6s}")
    return "\n".join(lines)


def main(args=None) -> int:
    return run_node(SummaryNode, args)


if __name__ == "__main__":
    sys.exit(main())
