"""A test node that takes part in the graph's run protocol (maglev_ros.nodes._lifecycle).

    python tests/protocol_probe.py --ros-args -p log:=LOG.jsonl [-p delay_s:=1.5] [-p stuck:=true]
                                              [-p protocol:=false]

Counts the /testline/vehicle/accel blocks of each recording; when a recording ends it works for
``delay_s`` on a worker thread, then publishes ``{"index": k, "blocks": n}`` on maglev/probe.
``stuck``: never ready, never done; ``protocol`` false: no part in the protocol at all. Its start
(once subscribed), every replay event it hears and every result it publishes are appended to
``log`` as one JSON line each, in the order they happened.
"""
import json
import sys
import threading
import time

from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import SensorBlock
from maglev_ros.nodes._common import QOS_STREAM, run_node
from maglev_ros.nodes._lifecycle import (FINISHED, QOS_EVENTS, RECORDING_END, RECORDING_START, TOPIC_REPLAY_EVENTS,
                                         NodeLifecycle, ReplayEvent)


class Probe(Node):
    def __init__(self) -> None:
        super().__init__("probe")
        self.delay_s = float(self.declare_parameter("delay_s", 1.5).value)
        self.stuck = bool(self.declare_parameter("stuck", False).value)
        protocol = bool(self.declare_parameter("protocol", True).value)
        self.log_path = self.declare_parameter("log", "").value
        self.lock = threading.Lock()
        self.blocks = 0
        self.worker: threading.Thread | None = None
        self.pub = self.create_publisher(String, "maglev/probe", QOS_STREAM)
        self.create_subscription(SensorBlock, "testline/vehicle/accel", self._on_block, QOS_STREAM)
        self.create_subscription(String, TOPIC_REPLAY_EVENTS, self._on_event, QOS_EVENTS)
        if protocol:
            self.lifecycle = NodeLifecycle(self, ready=not self.stuck)
        self._log(what="up")

    def _log(self, **entry) -> None:
        with self.lock, open(self.log_path, "a") as f:
            f.write(json.dumps(entry) + "\n")

    def _on_block(self, msg) -> None:
        self.blocks += 1

    def _on_event(self, msg) -> None:
        ev = ReplayEvent.from_json(msg.data)
        if not hasattr(self, "lifecycle") or ev.event == FINISHED:   # else logged by the hooks, in order
            self._log(what="event", event=ev.event, index=ev.index, messages=ev.messages)

    def on_recording_start(self, index: int) -> None:
        self._log(what="event", event=RECORDING_START, index=index, messages={})

    def on_recording_end(self, index: int) -> None:
        ev = next(e for e in self.lifecycle.events_seen if e.event == RECORDING_END and e.index == index)
        self._log(what="event", event=RECORDING_END, index=index, messages=ev.messages)
        # the recording's blocks all came before its end (the replay announces it once they are taken)
        blocks, self.blocks = self.blocks, 0

        def work() -> None:
            time.sleep(self.delay_s)       # a node's results take a while
            self.pub.publish(String(data=json.dumps({"index": index, "blocks": blocks})))
            self._log(what="result", index=index, blocks=blocks)
        self.worker = threading.Thread(target=work, daemon=True)
        self.worker.start()

    def busy(self) -> bool:
        return self.stuck or (self.worker is not None and self.worker.is_alive())


if __name__ == "__main__":
    sys.exit(run_node(Probe))
