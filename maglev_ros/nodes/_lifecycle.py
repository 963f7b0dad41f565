"""The graph's run protocol: when nodes are ready, where recordings end, when results are out.

A replay cannot know from DDS alone when a node has compiled its kernels or has published its
results for the recording just replayed; fixed waits made the outcome depend on the machine's
load. So the nodes and the replay say it on two topics (relative names: a namespace moves them):

``maglev/status`` (std_msgs/String JSON, transient-local, the last one per node)
    ``{"node": "twin", "state": "warming" | "ready" | "busy", "done": k, "detail": "..."}``:
    ``ready`` once the node is warm (kernels compiled, models built), ``busy`` while it works on a
    recording that has ended, ``done`` the index of the last recording whose results it has
    published (-1 before the first).
``maglev/replay/events`` (std_msgs/String JSON, reliable, transient-local, keep the last 64)
    ``{"event": "recording_start" | "recording_end" | "finished", "index": k, "bag": path,
    "messages": {topic: count}}``: a replay waits for every node it serves to be ready before its
    first message, publishes ``recording_end`` after every subscriber acknowledged the
    recording's last message (so a node has taken that recording's data before it hears of its
    end: the event arrives after the data in the node's queue), and waits for every node's
    ``done`` >= k before the next recording or before it ends.

A node takes part through :class:`NodeLifecycle`; it may define ``on_recording_start(index)``,
``on_recording_end(index)`` (finish that recording's results, possibly on a worker thread) and
``busy()`` (work still running); ``done`` is said once ``on_recording_end`` returned and
``busy()`` is false. A live sensor stream has no replay: nodes then keep their own idle rules.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from maglev_ros.nodes._common import QOS_LATCHED

TOPIC_STATUS = "maglev/status"
TOPIC_REPLAY_EVENTS = "maglev/replay/events"

WARMING, READY, BUSY = "warming", "ready", "busy"
RECORDING_START, RECORDING_END, FINISHED = "recording_start", "recording_end", "finished"

QOS_STATUS = QOS_LATCHED
# a node that joins while a multi-recording replay runs still gets the ends it missed
QOS_EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=64,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
# a reader of every node's status: KEEP_LAST is per topic, not per writer, so a depth-1 reader
# keeps only one of the statuses the nodes' writers hand a late joiner at once
QOS_STATUS_READER = QOS_EVENTS
POLL_S = 0.2


@dataclass
class NodeStatus:
    node: str
    state: str = WARMING
    done: int = -1
    detail: str = ""

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> "NodeStatus | None":
        """None for a message that is not a status (another tool on the topic)."""
        try:
            d = json.loads(text)
            return cls(str(d["node"]), str(d.get("state", WARMING)), int(d.get("done", -1)),
                       str(d.get("detail", "")))
        except (ValueError, KeyError, TypeError):
            return None


@dataclass
class ReplayEvent:
    event: str
    index: int = 0
    bag: str = ""
    messages: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> "ReplayEvent | None":
        try:
            d = json.loads(text)
            return cls(str(d["event"]), int(d.get("index", 0)), str(d.get("bag", "")),
                       dict(d.get("messages", {})))
        except (ValueError, KeyError, TypeError):
            return None


class NodeLifecycle:
    """A node's side of the protocol. ``ready=False``: the node calls :meth:`set_ready` once warm."""

    def __init__(self, node, ready: bool = True, diagnostics=None) -> None:
        self.node = node
        self.status = NodeStatus(node.get_name(), READY if ready else WARMING)
        self.pending: int | None = None          # a recording that ended, results not yet out
        self.events_seen: list[ReplayEvent] = []
        self._pub = node.create_publisher(String, TOPIC_STATUS, QOS_STATUS)
        node.create_subscription(String, TOPIC_REPLAY_EVENTS, self._on_event, QOS_EVENTS)
        node.create_timer(POLL_S, self._poll)
        if diagnostics is not None:
            diagnostics.add_check(self.check)
        self._say()

    def event(self, kind: str, index: int | None = None) -> "ReplayEvent | None":
        """The last replay event of ``kind`` (for recording ``index``) this node has seen."""
        return next((e for e in reversed(self.events_seen)
                     if e.event == kind and (index is None or e.index == index)), None)

    def set_ready(self, detail: str = "") -> None:
        if self.status.state == WARMING:
            self.status.state, self.status.detail = READY, detail
            self._say()

    def set_detail(self, detail: str) -> None:
        """Say a new ``detail`` (a source node's counts); nothing is published when it is unchanged."""
        if detail != self.status.detail:
            self.status.detail = detail
            self._say()

    def _say(self) -> None:
        msg = String()
        msg.data = self.status.to_json()
        self._pub.publish(msg)

    def _busy(self) -> bool:
        busy = getattr(self.node, "busy", None)
        return bool(busy()) if busy is not None else False

    def _on_event(self, msg) -> None:
        ev = ReplayEvent.from_json(msg.data)
        if ev is None:
            return
        self.events_seen.append(ev)
        if ev.event == RECORDING_START:
            hook = getattr(self.node, "on_recording_start", None)
            if hook is not None:
                hook(ev.index)
        elif ev.event == RECORDING_END and ev.index > self.status.done:
            hook = getattr(self.node, "on_recording_end", None)
            if hook is not None:
                hook(ev.index)
            self.pending = ev.index
            if self.status.state == READY:
                self.status.state = BUSY
            self._poll()

    def _poll(self) -> None:
        if self.pending is None or self._busy():
            return
        self.status.done, self.pending = self.pending, None
        if self.status.state == BUSY:
            self.status.state = READY
        self._say()

    def check(self):
        from maglev_ros.nodes._diagnostics import OK, WARN, Check
        values = {"state": self.status.state, "recordings_done": self.status.done + 1}
        if self.status.state == WARMING:
            return Check(WARN, "warming up", values)
        return Check(OK, "", values)


class GraphWaiter:
    """The replay's side: announces recording starts and ends, waits for nodes' states."""

    def __init__(self, node) -> None:
        self.node = node
        self.statuses: dict[str, NodeStatus] = {}
        self._pub = node.create_publisher(String, TOPIC_REPLAY_EVENTS, QOS_EVENTS)
        node.create_subscription(String, TOPIC_STATUS, self._on_status, QOS_STATUS_READER)

    def _on_status(self, msg) -> None:
        st = NodeStatus.from_json(msg.data)
        if st is not None:
            self.statuses[st.node] = st

    def announce(self, event: ReplayEvent) -> None:
        msg = String()
        msg.data = event.to_json()
        self._pub.publish(msg)

    def not_ready(self, names) -> list[str]:
        return [n for n in names if self.statuses.get(n) is None or self.statuses[n].state == WARMING]

    def not_done(self, names, index: int) -> list[str]:
        return [n for n in names if self.statuses.get(n) is None or self.statuses[n].done < index]

    def wait(self, executor, pending, timeout_s: float, should_quit=lambda: False) -> list[str]:
        """Spin until ``pending()`` is empty or ``timeout_s`` passed; returns what is still pending."""
        deadline = time.monotonic() + timeout_s
        left = pending()
        while left and time.monotonic() < deadline and not should_quit():
            executor.spin_once(timeout_sec=0.05)
            left = pending()
        return left
