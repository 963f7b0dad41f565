"""Node ``replay``: publishes a contract bag's topics with their recorded timing.

Parameters (``--ros-args -p name:=value`` or ``--params-file``; each with its description and
range in its ParameterDescriptor, ``PARAMS`` below; rate, fast, loop, clock_period_s, progress and
linger_s also live, a change of the others is refused with the reason):
  bag (str)                      path of the rosbag2 bag (MCAP or sqlite3) or ROS 1 bag
  bags (string[])                several recordings, replayed one after the other (instead of bag)
  rate (float, 1.0)              bag seconds per wall second, 0.1-100
  fast (bool, false)             as fast as possible (ignores rate)
  start_offset_s (float, 0)      skip this much from the start of each bag
  duration_s (float, 0)          replay only this long of each bag (0: to the end)
  loop (bool, false)             start the recordings again at the end (each time as new recordings)
  topics (string[], all)         topics to publish (the metadata is always published)
  clock (bool, true)             publish rosgraph_msgs/Clock on /clock for use_sim_time nodes
  clock_period_s (float, 0.01)   bag-time period of /clock while waiting between messages
  paused (bool, false)           start paused
  progress (bool, true)          progress line on stderr
  wait_subscribers (int, 0)      before starting, wait until every data topic has this many
  wait_nodes (string[], none)    before starting, wait until these nodes are in the graph (a
                                 launcher lists the graph's other nodes, so none misses the start),
                                 then until those taking part in the run protocol are ready; after
                                 each recording, until they have published its results
  discover_timeout_s (float, 30) ... nodes of wait_nodes to appear in the graph, at most this long
                                 (discovery takes seconds on a loaded machine; a running node is
                                 not judged absent on the readiness budget)
  wait_timeout_s (float, 10)     ... subscribers / ready, at most this long
  results_timeout_s (float, 900) ... results of a recording, at most this long
  linger_s (float, 0.5)          keep the node alive this long after the last recording
  stall_timeout_s (float, 300)   give up (exit 1, naming the topic) when a reliable subscriber
                                 takes nothing for this long (stuck, or killed and still matched)

Timing follows the messages' header stamps (the contract's time truth; a block goes out at
the stamp of its first sample, in the bag's receive order, and /clock carries the same times);
the messages themselves are published as the recorded CDR bytes, never deserialised. The metadata
topic is latched (transient local). Topics are published under the node's namespace (relative
names; ``/clock`` is remapped by the launcher).

Services, named and typed like rosbag2's player (``maglev_msgs/srv``, rosbag2_interfaces' fields):
``~/pause``, ``~/resume``, ``~/toggle_paused``, ``~/is_paused``, ``~/set_rate`` (0.1-100; sets the
``rate`` parameter and leaves ``fast``), ``~/get_rate``, ``~/seek`` (bag time inside the replayed
window, forward or backward: the next messages are those stamped from there on, and /clock jumps
there). Also ``~/set_paused`` (std_srvs/SetBool) and ``~/toggle_pause`` (std_srvs/Trigger), and
the space bar when run in a terminal (q quits).

Data topics are reliable keep-all: a subscriber that cannot keep up fills its writer's history,
a publish then waits for room and, after DDS's blocking time, fails without queuing; the replay
offers the same message again until it is taken (``replay_timing.Backpressure``), so it runs at
the pace of its slowest reliable subscriber (best-effort ones hold nothing) and loses nothing. At
the end it waits until every reliable subscriber has acknowledged every message, since a writer
that goes away takes the messages it still holds with it.

Several recordings and the graph's results (``maglev_ros.nodes._lifecycle``, the run protocol):
each recording is announced on ``maglev/replay/events`` (``recording_start``), its metadata and
data go out, and once every reliable subscriber has taken its last message ``recording_end``
carries the messages published per topic; the replay then waits until every node of
``wait_nodes`` that takes part in the protocol (it publishes ``maglev/status``) says ``done`` for
that recording, so the next recording (or the end) never cuts a node's results short. A node of
``wait_nodes`` without a status is not waited for (said once); one that stays warming or busy
past the timeout is named in a warning and the replay goes on. ``finished`` ends the run.
"""
from __future__ import annotations

import os
import select
import signal
import sys
import termios
import threading
import time
import tty

import rclpy
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from std_srvs.srv import SetBool, Trigger

from maglev_msgs.srv import GetRate, IsPaused, Pause, Resume, Seek, SetRate, TogglePaused

from maglev_ros.contract import TOPIC_METADATA
from maglev_ros.errors import UserError
from maglev_ros.nodes._common import QOS_CLOCK, message_class, rel
from maglev_ros.nodes._lifecycle import (FINISHED, RECORDING_END, RECORDING_START, TOPIC_STATUS,
                                         GraphWaiter, ReplayEvent)
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher
from maglev_ros.replay_timing import RATE_MAX, RATE_MIN, Backpressure, ReplayClock, Stalled

# what rclpy raises when the writer cannot queue a message (rmw: "cannot publish data")
RCLError = _rclpy.RCLError
# while messages are due at once, the services and parameters are still served this often [s]
SERVE_PERIOD_S = 0.05


def _invalid_topic_name(topic: str) -> str:
    """Why ``topic`` cannot be a ROS 2 topic ('' if it can): a bag written by other tools may hold any name."""
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name
    try:
        validate_full_topic_name(topic)
    except InvalidTopicNameException as exc:
        return str(exc).splitlines()[0].removeprefix("Invalid topic name: ")
    return ""


def _set(attr):
    return lambda node, value: setattr(node, attr, value)


PARAMS = (
    Param("bag", "", "path of the rosbag2 bag (MCAP or sqlite3) or ROS 1 bag to replay"),
    Param("bags", [""], "several recordings, replayed one after the other (instead of bag)"),
    Param("rate", 1.0, "bag seconds per wall second", range=(RATE_MIN, RATE_MAX),
          apply=lambda node, v: node.set_rate(v)),
    Param("fast", False, "as fast as the subscribers take it (ignores rate)",
          apply=lambda node, v: node.set_fast(v)),
    Param("start_offset_s", 0.0, "skip this much from the start of the bag [s]", range=(0.0, 1e7)),
    Param("duration_s", 0.0, "replay only this long [s] (0: to the end)", range=(0.0, 1e7)),
    Param("loop", False, "start again at the end (bag time jumps back, as rosbag2 does)", apply=_set("loop")),
    Param("topics", [""], "topics to publish (empty: all; the metadata is always published)"),
    Param("clock", True, "publish rosgraph_msgs/Clock on /clock for use_sim_time nodes"),
    Param("clock_period_s", 0.01, "bag-time period of /clock while waiting between messages [s]",
          range=(1e-4, 1.0), apply=_set("clock_period_s")),
    Param("paused", False, "start paused (then: the pause/resume services or the space bar)"),
    Param("progress", True, "progress line on stderr", apply=_set("progress_on")),
    Param("wait_subscribers", 0, "before starting, wait until every data topic has this many subscribers",
          range=(0, 1000)),
    Param("wait_nodes", [""], "before starting, wait until these nodes (names in the replay's namespace, "
                              "or fully qualified) are in the graph, then ready; after each recording, "
                              "until they have published its results"),
    Param("discover_timeout_s", 30.0, "wait for the nodes of wait_nodes to appear in the graph at most this "
                                      "long [s]", range=(0.0, 1e9)),
    Param("wait_timeout_s", 10.0, "wait for subscribers / the nodes' being ready at most this long [s]",
          range=(0.0, 1e9)),
    Param("results_timeout_s", 900.0, "after each recording, wait for the nodes' results at most this long [s]",
          range=(0.0, 1e9)),
    Param("linger_s", 0.5, "keep the node alive this long after the last message [s]", range=(0.0, 1e9),
          apply=_set("linger_s")),
    Param("stall_timeout_s", 300.0, "give up (exit 1, naming the topic) when a reliable subscriber takes "
                                    "nothing for this long [s]", range=(0.1, 1e9)),
)


class ReplayNode(Node):
    def __init__(self) -> None:
        super().__init__("replay")
        v = declare(self, PARAMS)
        self.bag = v["bag"]
        self.bags = [b for b in v["bags"] if b] or ([self.bag] if self.bag else [])
        self.rate = v["rate"]
        self.fast = v["fast"]
        self.start_offset_s = v["start_offset_s"]
        self.duration_s = v["duration_s"]
        self.loop = v["loop"]
        self.topics = [t for t in v["topics"] if t]
        self.clock_on = v["clock"]
        self.clock_period_s = v["clock_period_s"]
        start_paused = v["paused"]
        self.progress_on = v["progress"]
        self.wait_subscribers = v["wait_subscribers"]
        self.wait_nodes = [n for n in v["wait_nodes"] if n]
        self.wait_timeout_s = v["wait_timeout_s"]
        self.discover_timeout_s = v["discover_timeout_s"]
        self.results_timeout_s = v["results_timeout_s"]
        self.linger_s = v["linger_s"]
        stall_timeout_s = self.stall_timeout_s = v["stall_timeout_s"]
        if not self.bags:
            raise UserError("parameter 'bag' (or 'bags') is required (-p bag:=PATH)")
        self.clock = ReplayClock(rate=None if self.fast else self.rate)
        self.backpressure = Backpressure(stall_timeout_s=stall_timeout_s,
                                         warn_after_s=min(5.0, stall_timeout_s / 2))
        if start_paused:
            self.clock.pause()
        self.quit = False
        self.published = 0
        self.exit_code = 0
        self.finished = False
        self.position_ns: int | None = None       # bag time of the last message or /clock published
        self.window_ns: tuple[int, int] | None = None   # what may be sought: [start, end] of the replay
        self.seek_ns: int | None = None           # a seek asked for, done by the replay loop
        self._pubs: dict[str, object] = {}
        self._clock_pub = self.create_publisher(Clock, "/clock", QOS_CLOCK) if self.clock_on else None
        self.waiter = GraphWaiter(self)      # before the wait for nodes: their statuses come meanwhile
        self.said_no_status: set[str] = set()
        srv = self.create_service
        srv(Pause, "~/pause", lambda req, res: (self.clock.pause(), res)[1])
        srv(Resume, "~/resume", lambda req, res: (self.clock.resume(), res)[1])
        srv(TogglePaused, "~/toggle_paused", lambda req, res: (self.toggle_pause(), res)[1])
        srv(IsPaused, "~/is_paused", self._on_is_paused)
        srv(SetRate, "~/set_rate", self._on_set_rate)
        srv(GetRate, "~/get_rate", self._on_get_rate)
        srv(Seek, "~/seek", self._on_seek)
        # the first names of the pause services (kept for existing callers)
        srv(SetBool, "~/set_paused", self._on_set_paused)
        srv(Trigger, "~/toggle_pause", self._on_toggle)

    # -- control -------------------------------------------------------------------------
    def _on_set_paused(self, request, response):
        (self.clock.pause if request.data else self.clock.resume)()
        response.success, response.message = True, "paused" if self.clock.paused else "playing"
        return response

    def _on_toggle(self, request, response):
        self.toggle_pause()
        response.success, response.message = True, "paused" if self.clock.paused else "playing"
        return response

    def toggle_pause(self) -> None:
        (self.clock.resume if self.clock.paused else self.clock.pause)()

    def _on_is_paused(self, request, response):
        response.paused = self.clock.paused
        return response

    def _on_get_rate(self, request, response):
        response.rate = float(self.rate)
        return response

    def _on_set_rate(self, request, response):
        """Through the parameters, so ``rate`` reads back what plays; a rate outside 0.1-100 fails."""
        result = self.set_parameters_atomically([Parameter("rate", value=float(request.rate)),
                                                 Parameter("fast", value=False)])
        response.success = bool(result.successful)
        if not result.successful:
            self.get_logger().warning(f"set_rate {request.rate}: refused ({result.reason})")
        return response

    def set_rate(self, rate: float) -> None:
        """The ``rate`` parameter's live change (the parameter services, ``~/set_rate``)."""
        self.rate = rate
        if not self.fast:
            self._pace(rate)

    def set_fast(self, fast: bool) -> None:
        """The ``fast`` parameter's live change."""
        self.fast = fast
        self._pace(None if fast else self.rate)

    def _pace(self, rate: float | None) -> None:
        # as fast as possible the clock does not follow bag time: go on from the last message's
        self.clock.set_rate(rate, bag_ns=self.position_ns if self.clock.rate is None else None)

    def _on_seek(self, request, response):
        t_ns = request.time.sec * 1_000_000_000 + request.time.nanosec
        ok = self.window_ns is not None and self.window_ns[0] <= t_ns <= self.window_ns[1]
        if ok:
            self.seek_ns = t_ns
        else:
            where = ("before the replay started" if self.window_ns is None else
                     f"outside the replayed window {self.window_ns[0] * 1e-9:.3f}-{self.window_ns[1] * 1e-9:.3f} s")
            self.get_logger().warning(f"seek to {t_ns * 1e-9:.3f} s refused: {where}")
        response.success = ok
        return response

    # -- publishing ----------------------------------------------------------------------
    def publisher_for(self, topic: str, msgtype: str):
        pub = self._pubs.get(topic)
        if pub is None and topic not in self._pubs:
            cls = message_class(msgtype)
            bad_name = _invalid_topic_name(topic)
            if bad_name:
                self.get_logger().warning(f"{topic!r}: not a valid ROS 2 topic name ({bad_name}); not published")
            elif cls is None:
                self.get_logger().warning(f"{topic}: type {msgtype} is not available; not published")
            else:
                pub = publisher(self, cls, topic)       # relative: under the node's namespace
            self._pubs[topic] = pub
        return pub

    def offer(self, executor, pub, topic: str, cdr: bytes) -> bool:
        """Publish ``cdr``; while the writer refuses it (a reliable subscriber is behind), serve the
        executor, wait and offer it again. False if the user quits meanwhile; Stalled past the bound."""
        bp = self.backpressure
        subscribers = None
        t0 = time.monotonic()
        while True:
            try:
                pub.publish(cdr)
            except RCLError:
                if not self.context.ok():     # shut down under us: not a subscriber's doing
                    self.quit = True
                    return False
                if subscribers is None:
                    subscribers = pub.get_subscription_count()
                wait_s = bp.refused(topic)
                if bp.warn_due():
                    self.get_logger().warning(
                        f"{topic}: a reliable subscriber has taken nothing for {bp.stalled_s():.0f} s; "
                        f"waiting for it (at most {bp.stall_timeout_s:.0f} s)")
                executor.spin_once(timeout_sec=0.0)
                if self.quit:
                    return False
                # returns early if everything is acknowledged (then the history has room again)
                pub.wait_for_all_acked(Duration(nanoseconds=int(wait_s * 1e9)))
                continue
            stalled_s = bp.stalled_s()
            bp.accepted(topic, time.monotonic() - t0)
            left = pub.get_subscription_count() if subscribers is not None else None
            if left is not None and left < subscribers:
                self.get_logger().warning(f"{topic}: a subscriber is gone ({subscribers} -> {left}); "
                                          f"publishing again after {stalled_s:.1f} s")
            elif stalled_s >= bp.warn_after_s:
                self.get_logger().info(f"{topic}: the subscribers take messages again after "
                                       f"{stalled_s:.1f} s")
            return True

    def drain(self, executor, last_clock_ns) -> None:
        """Wait until every reliable subscriber has acknowledged every message: a writer that goes
        away takes the messages it still holds with it."""
        bp = self.backpressure
        t0 = time.monotonic()
        for topic, pub in self._pubs.items():
            if pub is None or topic == TOPIC_METADATA:
                continue
            budget_s = bp.drain_budget_s(topic)
            start, warned = time.monotonic(), False
            while not self.quit and not pub.wait_for_all_acked(Duration(nanoseconds=100_000_000)):
                executor.spin_once(timeout_sec=0.0)
                if last_clock_ns is not None:
                    self.publish_clock(last_clock_ns)
                if self.quit:
                    return
                waited = time.monotonic() - start
                if waited > budget_s:
                    raise Stalled(topic, waited, "left the last messages unacknowledged")
                if not warned and waited >= bp.warn_after_s:
                    warned = True
                    self.get_logger().info(f"{topic}: waiting for the reliable subscribers to take "
                                           f"the last messages (at most {budget_s:.0f} s)")
        waited = time.monotonic() - t0
        if waited >= 0.5:
            self.get_logger().info(f"every reliable subscriber acknowledged every message "
                                   f"({waited:.1f} s after the last one was published)")

    def publish_clock(self, bag_ns: int) -> None:
        self.position_ns = int(bag_ns)
        if self._clock_pub is not None:
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
            self._clock_pub.publish(msg)


class _Keys:
    """Space toggles pause, q quits, when stdin is a terminal (restored on exit)."""

    def __init__(self, node: ReplayNode) -> None:
        self.node = node
        self.old = None
        if sys.stdin.isatty() and os.getpgrp() == os.tcgetpgrp(sys.stdin.fileno()):
            fd = sys.stdin.fileno()
            self.old = termios.tcgetattr(fd)
            tty.setcbreak(fd)
            threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        while not self.node.quit:
            if select.select([sys.stdin], [], [], 0.2)[0]:
                ch = sys.stdin.read(1)
                if ch == " ":
                    self.node.toggle_pause()
                elif ch in ("q", "Q"):
                    self.node.quit = True

    def restore(self) -> None:
        if self.old is not None:
            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, self.old)


class _Progress:
    def __init__(self, enabled: bool, total_s: float) -> None:
        self.enabled, self.total_s = enabled, total_s
        self.t_wall0 = time.monotonic()
        self.last = 0.0

    def show(self, node: ReplayNode, bag_s: float, force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (not force and now - self.last < 0.5):
            return
        self.last = now
        bag_s = max(bag_s, 0.0)
        frac = min(1.0, bag_s / self.total_s) if self.total_s > 0 else 1.0
        bar = "#" * int(frac * 24)
        speed = bag_s / max(now - self.t_wall0, 1e-9)
        state = "paused" if node.clock.paused else f"{speed:6.1f}x"
        sys.stderr.write(f"\r[replay] [{bar:<24}] {bag_s:8.2f}/{self.total_s:.2f} s {state} "
                         f"{node.published} msgs ")
        sys.stderr.flush()


def _wait_until(node: ReplayNode, executor, ready, what, timeout_s: float | None = None) -> bool:
    timeout_s = node.wait_timeout_s if timeout_s is None else timeout_s
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not node.quit:
        executor.spin_once(timeout_sec=0.05)
        if ready():
            return True
    if node.quit:
        return False
    node.get_logger().warning(f"waited {timeout_s:g} s for {what()}; starting anyway")
    return False


def _wait_for_nodes(node: ReplayNode, executor) -> None:
    """Before anything is published (a node's idle timers must not start on the metadata)."""
    if not node.wait_nodes:
        return
    ns = node.get_namespace().rstrip("/")
    # a plain name is a node of the replay's own namespace (another graph's twin is not ours)
    wanted = [n if n.count("/") > 1 else f"{ns}/{n.lstrip('/')}" for n in node.wait_nodes]

    def absent() -> list[str]:
        names = {f"{space.rstrip('/')}/{name}" for name, space in node.get_node_names_and_namespaces()}
        return [n for n in wanted if n not in names]

    if _wait_until(node, executor, lambda: not absent(), lambda: f"nodes {', '.join(absent())}",
                   node.discover_timeout_s):
        # a node appears in the graph just before its constructor creates its subscriptions
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)


def _wait_for_subscribers(node: ReplayNode, executor, topics: list[str]) -> None:
    if node.wait_subscribers <= 0:
        return
    _wait_until(node, executor,
                lambda: all(node.count_subscribers(rel(t)) >= node.wait_subscribers for t in topics),
                lambda: f"{node.wait_subscribers} subscriber(s) on every data topic")


def _wait_for_matches(node: ReplayNode, executor, pubs: dict) -> None:
    """A writer created for a later recording (a topic the earlier ones lacked) has not matched the
    graph's subscribers yet: what it published now would reach none of them."""
    def unmatched() -> list[str]:
        return [t for t, pub in pubs.items()
                if pub.get_subscription_count() < node.count_subscribers(pub.topic_name)]
    if unmatched():
        _wait_until(node, executor, lambda: not unmatched(),
                    lambda: f"the subscribers of {', '.join(unmatched())} to match")


def _protocol_nodes(node: ReplayNode, say: bool = False) -> list[str]:
    """The nodes of ``wait_nodes`` that take part in the run protocol: a status came, or they have
    a status writer (its latched status is on its way). The others are not waited for (``say``:
    log them, once)."""
    writers = {i.node_name for i in node.get_publishers_info_by_topic(node.resolve_topic_name(TOPIC_STATUS))}
    names = [n.rsplit("/", 1)[-1] for n in node.wait_nodes]   # a status names its node without namespace
    taking_part = [n for n in names if n in node.waiter.statuses or n in writers]
    silent = [n for n in names if n not in taking_part and n not in node.said_no_status]
    if say and silent:
        node.said_no_status.update(silent)
        node.get_logger().info(f"{', '.join(silent)}: no run-protocol status ({TOPIC_STATUS}); "
                               f"not waited for (ready, results)")
    return taking_part


def _wait_ready(node: ReplayNode, executor) -> None:
    """Before the first message: every node that takes part says it is warm (kernels compiled)."""
    if not node.wait_nodes:
        return
    t0 = time.monotonic()
    left = node.waiter.wait(executor, lambda: node.waiter.not_ready(_protocol_nodes(node)),
                            node.wait_timeout_s, lambda: node.quit)
    _protocol_nodes(node, say=True)
    if left and not node.quit:
        node.get_logger().warning(f"waited {node.wait_timeout_s:g} s for {', '.join(left)} to be "
                                  f"ready (warm); starting anyway")
    elif time.monotonic() - t0 >= 1.0:
        node.get_logger().info(f"the graph is ready after {time.monotonic() - t0:.1f} s")


def _wait_results(node: ReplayNode, executor, index: int, last_clock_ns) -> None:
    """After a recording's end: every node that takes part has published its results for it."""
    if not node.wait_nodes:
        return
    t0 = time.monotonic()
    tick = {"t": t0}

    def pending() -> list[str]:
        # /clock repeats the last time meanwhile (best effort: a sim-time node may have lost a tick)
        if last_clock_ns is not None and time.monotonic() - tick["t"] >= 0.5:
            tick["t"] = time.monotonic()
            node.publish_clock(last_clock_ns)
        return node.waiter.not_done(_protocol_nodes(node), index)
    _protocol_nodes(node, say=True)
    left = node.waiter.wait(executor, pending, node.results_timeout_s, lambda: node.quit)
    waited = time.monotonic() - t0
    if left and not node.quit:
        node.get_logger().warning(
            f"recording {index}: {', '.join(left)} did not say done within {node.results_timeout_s:g} s "
            f"(results_timeout_s); going on without their results")
    elif waited >= 1.0:
        node.get_logger().info(f"recording {index}: every node published its results "
                               f"{waited:.1f} s after the recording ended")


def _check_bags(node: ReplayNode) -> None:
    """Every recording is readable and holds the topics asked for, before anything is published."""
    from maglev_ros.bag_reader import BagReader
    for bag in node.bags:
        with BagReader(bag) as reader:
            available = set(reader.topics)
        missing = [t for t in node.topics if t not in available]
        if missing:
            raise UserError(f"{bag}: no topic {missing[0]} in the bag "
                            f"(topics: {', '.join(sorted(available))})")


def replay(node: ReplayNode, executor) -> None:
    """The run: wait for the graph, replay each recording with its results, say finished."""
    _check_bags(node)
    _wait_for_nodes(node, executor)
    _wait_ready(node, executor)
    keys = _Keys(node)
    last_clock_ns = None
    totals: dict[str, int] = {}
    index = 0
    try:
        while True:
            for bag in node.bags:
                node.waiter.announce(ReplayEvent(RECORDING_START, index, bag))
                counts, last_clock_ns = play_recording(node, executor, bag, index)
                if node.quit:
                    return
                node.waiter.announce(ReplayEvent(RECORDING_END, index, bag, counts))
                for t, n in counts.items():
                    totals[t] = totals.get(t, 0) + n
                _wait_results(node, executor, index, last_clock_ns)
                if node.quit:
                    return
                index += 1
            if not node.loop:
                break
    finally:
        keys.restore()
    node.waiter.announce(ReplayEvent(FINISHED, index - 1, messages=totals))
    node.finished = True
    # Let reliable writers hand out what they hold before the node goes away; /clock (best effort,
    # like every ROS /clock) repeats the last time meanwhile, so a sim-time node that lost the final
    # tick under load still ends at the recording's end (an end-to-end run saw 29.92 s of 30.02 s)
    end = time.monotonic() + node.linger_s
    while time.monotonic() < end and not node.quit:
        if last_clock_ns is not None:
            node.publish_clock(last_clock_ns)
        executor.spin_once(timeout_sec=0.05)


def play_recording(node: ReplayNode, executor, bag: str, index: int):
    """One recording: metadata latched, then every message on time, then drained (every reliable
    subscriber took every message). Returns (messages published per topic, last /clock time)."""
    from maglev_ros.bag_reader import BagReader

    counts: dict[str, int] = {}
    last_clock_ns = None
    node.backpressure = Backpressure(stall_timeout_s=node.stall_timeout_s,
                                     warn_after_s=min(5.0, node.stall_timeout_s / 2))
    with BagReader(bag) as reader:
        available = set(reader.topics)
        data_topics = [t for t in (node.topics or sorted(available)) if t != TOPIC_METADATA]
        t0_ns = int(round(reader.start_time_s * 1e9))
        window_start = t0_ns + int(node.start_offset_s * 1e9)
        total_s = max(0.0, reader.duration_s - node.start_offset_s)
        if node.duration_s > 0:
            total_s = min(total_s, node.duration_s)
        window = dict(start_s=node.start_offset_s or None,
                      duration_s=node.duration_s if node.duration_s > 0 else None)

        meta_pub = None
        if TOPIC_METADATA in available:
            for topic, msgtype, _, cdr in reader.iter_raw(topics=[TOPIC_METADATA]):
                meta_pub = node.publisher_for(topic, msgtype)
                meta_pub.publish(cdr)
                counts[topic] = 1
                break
        new = {t: node.publisher_for(t, reader.topics[t].msgtype) for t in data_topics if t not in node._pubs}
        # a topic skipped (type not on the allow-list) never gets a subscriber: not waited for
        if index == 0:
            _wait_for_subscribers(node, executor, [t for t in data_topics if node._pubs.get(t) is not None])
        _wait_for_matches(node, executor, {t: p for t, p in new.items() if p is not None})
        if meta_pub is not None:
            # every node has the recording's metadata before its first block (DDS does not order topics)
            meta_pub.wait_for_all_acked(Duration(seconds=node.wait_timeout_s))

        progress = _Progress(node.progress_on, total_s)
        # what ~/seek may jump to: the replayed window of this recording
        node.window_ns = (window_start, window_start + int(round(total_s * 1e9)))
        published0 = node.published
        segment_start, segment = window_start, window
        last_serve = time.monotonic()
        while True:
            node.clock.start(segment_start)
            node.publish_clock(segment_start)  # sim time is valid before the first block
            last_clock_ns = segment_start
            for topic, msgtype, stamp_ns, cdr in reader.iter_raw(topics=data_topics, **segment):
                if time.monotonic() - last_serve >= SERVE_PERIOD_S:
                    # messages due at once (fast, or behind) still leave services served
                    executor.spin_once(timeout_sec=0.0)
                    last_serve = time.monotonic()
                # Wait until due: sleep in slices, keep /clock ticking, serve services.
                while not node.quit and node.seek_ns is None:
                    remaining = node.clock.wall_due(stamp_ns) - time.monotonic()
                    if remaining <= 0 and not node.clock.paused:
                        break
                    executor.spin_once(timeout_sec=0.0)
                    last_serve = time.monotonic()
                    bag_now = node.clock.bag_now_ns()
                    if (node._clock_pub is not None
                            and bag_now - last_clock_ns >= int(max(node.clock_period_s, 1e-4) * 1e9)):
                        node.publish_clock(min(bag_now, stamp_ns))
                        last_clock_ns = bag_now
                    progress.show(node, (bag_now - window_start) * 1e-9)
                    time.sleep(min(max(remaining, 0.0) if not node.clock.paused else 0.05,
                                   node.clock_period_s / max(node.clock.rate or 1.0, 1.0)))
                if node.quit:
                    return counts, last_clock_ns
                if node.seek_ns is not None:
                    break
                if stamp_ns > last_clock_ns:
                    node.publish_clock(stamp_ns)
                    last_clock_ns = stamp_ns
                pub = node.publisher_for(topic, msgtype)
                if pub is not None:
                    if not node.offer(executor, pub, topic, cdr):
                        return counts, last_clock_ns
                    node.published += 1
                    counts[topic] = counts.get(topic, 0) + 1
                progress.show(node, (stamp_ns - window_start) * 1e-9)
            if node.seek_ns is None:
                break
            # go on from the sought time to the window's end, /clock from there
            segment_start, node.seek_ns = node.seek_ns, None
            segment = dict(start_s=(segment_start - t0_ns) * 1e-9,
                           duration_s=(node.window_ns[1] - segment_start) * 1e-9 if node.duration_s > 0 else None)
            node.get_logger().info(f"seek: replaying from bag time {segment_start * 1e-9:.3f} s")
        progress.show(node, total_s, force=True)
        if node.progress_on:
            sys.stderr.write("\n")
        wall = time.monotonic() - progress.t_wall0
        bp = node.backpressure
        waits = "".join(f"; a reliable subscriber of {t} set the pace: {bp.held_n.get(t, 0)} "
                        f"message(s) waited {bp.held_s.get(t, 0.0):.1f} s for room in the "
                        f"writer's history, {bp.refused_n.get(t, 0)} refused and offered again"
                        for t in bp.paced(wall))
        which = f"recording {index} ({bag}): " if len(node.bags) > 1 or node.loop else ""
        node.get_logger().info(
            f"{which}published {node.published - published0} messages, {total_s:.2f} s of recording in "
            f"{wall:.2f} s wall ({total_s / max(wall, 1e-9):.1f}x real time){waits}")
        node.drain(executor, last_clock_ns)
    return counts, last_clock_ns


def main(args=None) -> int:
    # SIGINT/SIGTERM end the loops through ``quit`` instead of rclpy invalidating the context under
    # a publish that is waiting for a subscriber (a traceback, not an exit)
    rclpy.init(args=args if args is not None else sys.argv,
               signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = SingleThreadedExecutor()
    stop = {"signum": None}

    def on_signal(signum, frame):
        stop["signum"] = signum
        if node is not None:
            node.quit = True
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    code = 0
    try:
        node = ReplayNode()
        node.quit = stop["signum"] is not None
        executor.add_node(node)
        replay(node, executor)
    except (UserError, Stalled) as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        code = 130
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if stop["signum"] is not None and code == 0:
            code = 128 + stop["signum"]
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
