"""Node ``replay``: publishes a contract bag's topics with their recorded timing.

Parameters (``--ros-args -p name:=value`` or ``--params-file``):
  bag (str, required)            path of the rosbag2 bag (MCAP or sqlite3) or ROS 1 bag
  rate (float, 1.0)              bag seconds per wall second, 0.1-100
  fast (bool, false)             as fast as possible (ignores rate)
  start_offset_s (float, 0)      skip this much from the start of the bag
  duration_s (float, 0)          replay only this long (0: to the end)
  loop (bool, false)             start again at the end (bag time jumps back, as rosbag2 does)
  topics (string[], all)         topics to publish (the metadata is always published)
  clock (bool, true)             publish rosgraph_msgs/Clock on /clock for use_sim_time nodes
  clock_period_s (float, 0.01)   bag-time period of /clock while waiting between messages
  paused (bool, false)           start paused
  progress (bool, true)          progress line on stderr
  wait_subscribers (int, 0)      before starting, wait until every data topic has this many
  wait_nodes (string[], none)    before starting, wait until these nodes are in the graph (a
                                 launcher lists the graph's other nodes, so none misses the start)
  wait_timeout_s (float, 10)     ... subscribers / nodes, at most this long
  linger_s (float, 0.5)          keep the node alive this long after the last message

Timing follows the messages' header stamps (the contract's time truth; a block goes out at
the stamp of its first sample, in the bag's receive order, and /clock carries the same times);
the messages themselves are published as the recorded CDR bytes, never deserialised. The metadata topic is latched
(transient local). Pause/resume: services ``~/set_paused`` (std_srvs/SetBool) and
``~/toggle_pause`` (std_srvs/Trigger), or the space bar when run in a terminal (q quits).
"""
from __future__ import annotations

import os
import select
import sys
import termios
import threading
import time
import tty

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_srvs.srv import SetBool, Trigger

from maglev_ros.contract import TOPIC_METADATA
from maglev_ros.errors import UserError
from maglev_ros.nodes._common import QOS_CLOCK, message_class, qos_for
from maglev_ros.replay_timing import ReplayClock, check_rate


class ReplayNode(Node):
    def __init__(self) -> None:
        super().__init__("replay")
        p = self.declare_parameter
        self.bag = p("bag", "").value
        self.rate = p("rate", 1.0).value
        self.fast = p("fast", False).value
        self.start_offset_s = p("start_offset_s", 0.0).value
        self.duration_s = p("duration_s", 0.0).value
        self.loop = p("loop", False).value
        self.topics = [t for t in p("topics", [""]).value if t]
        self.clock_on = p("clock", True).value
        self.clock_period_s = p("clock_period_s", 0.01).value
        start_paused = p("paused", False).value
        self.progress_on = p("progress", True).value
        self.wait_subscribers = p("wait_subscribers", 0).value
        self.wait_nodes = [n for n in p("wait_nodes", [""]).value if n]
        self.wait_timeout_s = p("wait_timeout_s", 10.0).value
        self.linger_s = p("linger_s", 0.5).value
        if not self.bag:
            raise UserError("parameter 'bag' is required (-p bag:=PATH)")
        self.clock = ReplayClock(rate=None if self.fast else check_rate(self.rate))
        if start_paused:
            self.clock.pause()
        self.quit = False
        self.published = 0
        self.exit_code = 0
        self.finished = False
        self._pubs: dict[str, object] = {}
        self._clock_pub = self.create_publisher(Clock, "/clock", QOS_CLOCK) if self.clock_on else None
        self.create_service(SetBool, "~/set_paused", self._on_set_paused)
        self.create_service(Trigger, "~/toggle_pause", self._on_toggle)

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

    # -- publishing ----------------------------------------------------------------------
    def publisher_for(self, topic: str, msgtype: str):
        pub = self._pubs.get(topic)
        if pub is None and topic not in self._pubs:
            cls = message_class(msgtype)
            if cls is None:
                self.get_logger().warning(f"{topic}: type {msgtype} is not available; not published")
            else:
                pub = self.create_publisher(cls, topic, qos_for(topic))
            self._pubs[topic] = pub
        return pub

    def publish_clock(self, bag_ns: int) -> None:
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


def _wait_until(node: ReplayNode, executor, ready, what) -> bool:
    deadline = time.monotonic() + node.wait_timeout_s
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
        if ready():
            return True
    node.get_logger().warning(f"waited {node.wait_timeout_s} s for {what()}; starting anyway")
    return False


def _wait_for_nodes(node: ReplayNode, executor) -> None:
    """Before anything is published (a node's idle timers must not start on the metadata)."""
    if not node.wait_nodes:
        return

    def absent() -> list[str]:
        names = {n.lstrip("/") for n in node.get_node_names()}
        return [n for n in node.wait_nodes if n.lstrip("/") not in names]

    if _wait_until(node, executor, lambda: not absent(), lambda: f"nodes {', '.join(absent())}"):
        # a node appears in the graph just before its constructor creates its subscriptions
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)


def _wait_for_subscribers(node: ReplayNode, executor, topics: list[str]) -> None:
    if node.wait_subscribers <= 0:
        return
    _wait_until(node, executor,
                lambda: all(node.count_subscribers(t) >= node.wait_subscribers for t in topics),
                lambda: f"{node.wait_subscribers} subscriber(s) on every data topic")


def replay(node: ReplayNode, executor) -> None:
    """The replay loop: open the bag, publish metadata latched, then every message on time."""
    from maglev_ros.bag_reader import BagReader

    last_clock_ns = None
    with BagReader(node.bag) as reader:
        available = set(reader.topics)
        missing = [t for t in node.topics if t not in available]
        if missing:
            raise UserError(f"{node.bag}: no topic {missing[0]} in the bag "
                            f"(topics: {', '.join(sorted(available))})")
        data_topics = [t for t in (node.topics or sorted(available)) if t != TOPIC_METADATA]
        t0_ns = int(round(reader.start_time_s * 1e9))
        window_start = t0_ns + int(node.start_offset_s * 1e9)
        total_s = max(0.0, reader.duration_s - node.start_offset_s)
        if node.duration_s > 0:
            total_s = min(total_s, node.duration_s)
        window = dict(start_s=node.start_offset_s or None,
                      duration_s=node.duration_s if node.duration_s > 0 else None)

        _wait_for_nodes(node, executor)
        if TOPIC_METADATA in available:
            for topic, msgtype, _, cdr in reader.iter_raw(topics=[TOPIC_METADATA]):
                node.publisher_for(topic, msgtype).publish(cdr)
                break
        for t in data_topics:
            node.publisher_for(t, reader.topics[t].msgtype)
        # a topic skipped (type not on the allow-list) never gets a subscriber: not waited for
        _wait_for_subscribers(node, executor, [t for t in data_topics if node._pubs.get(t) is not None])

        keys = _Keys(node)
        progress = _Progress(node.progress_on, total_s)
        clock_period_ns = int(max(node.clock_period_s, 1e-4) * 1e9)
        try:
            while True:
                node.clock.start(window_start)
                node.publish_clock(window_start)  # sim time is valid before the first block
                last_clock_ns = window_start
                for topic, msgtype, stamp_ns, cdr in reader.iter_raw(topics=data_topics, **window):
                    # Wait until due: sleep in slices, keep /clock ticking, serve services.
                    while not node.quit:
                        remaining = node.clock.wall_due(stamp_ns) - time.monotonic()
                        if remaining <= 0 and not node.clock.paused:
                            break
                        executor.spin_once(timeout_sec=0.0)
                        bag_now = node.clock.bag_now_ns()
                        if node._clock_pub is not None and bag_now - last_clock_ns >= clock_period_ns:
                            node.publish_clock(min(bag_now, stamp_ns))
                            last_clock_ns = bag_now
                        progress.show(node, (bag_now - window_start) * 1e-9)
                        time.sleep(min(max(remaining, 0.0) if not node.clock.paused else 0.05,
                                       node.clock_period_s / max(node.clock.rate or 1.0, 1.0)))
                    if node.quit:
                        return
                    if stamp_ns > last_clock_ns:
                        node.publish_clock(stamp_ns)
                        last_clock_ns = stamp_ns
                    pub = node.publisher_for(topic, msgtype)
                    if pub is not None:
                        pub.publish(cdr)
                        node.published += 1
                    progress.show(node, (stamp_ns - window_start) * 1e-9)
                if not node.loop:
                    break
            progress.show(node, total_s, force=True)
            if node.progress_on:
                sys.stderr.write("\n")
            wall = time.monotonic() - progress.t_wall0
            node.get_logger().info(
                f"published {node.published} messages, {total_s:.2f} s of recording in "
                f"{wall:.2f} s wall ({total_s / max(wall, 1e-9):.1f}x real time)")
        finally:
            keys.restore()
    # Let reliable writers hand out what they hold before the node goes away; /clock (best effort,
    # like every ROS /clock) repeats the last time meanwhile, so a sim-time node that lost the final
    # tick under load still ends at the recording's end (an end-to-end run saw 29.92 s of 30.02 s)
    end = time.monotonic() + node.linger_s
    while time.monotonic() < end:
        if last_clock_ns is not None:
            node.publish_clock(last_clock_ns)
        executor.spin_once(timeout_sec=0.05)


def main(args=None) -> int:
    rclpy.init(args=args if args is not None else sys.argv)
    node = None
    executor = SingleThreadedExecutor()
    code = 0
    try:
        node = ReplayNode()
        executor.add_node(node)
        replay(node, executor)
    except UserError as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        code = 130
    finally:
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
