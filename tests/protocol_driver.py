"""The replay's side of the graph run protocol for node tests (nodes/_lifecycle.py GraphWaiter):

    python tests/protocol_driver.py OUT.json TIMEOUT_S NODE[,NODE...] SUBSCRIBERS BAG [BAG ...]

waits until every named node is ready, then per bag announces ``recording_start``, replays it with
``maglev-ros replay --fast --wait-subscribers N`` (it ends once every reliable subscriber
acknowledged every message). SUBSCRIBERS ``auto``: N is the most subscribers any data topic has in
the graph, and the driver adds best-effort subscriptions (never waited for) to the topics with
fewer, so that the replay starts only once it sees every node's subscription on every topic (with
N = the fewest, a third node on the vehicle topics missed the first blocks under load); a
number: that N, no padding,
announces ``recording_end`` with the bag's message counts and waits until every node said done for
it; then ``finished``. It also publishes each recording's metadata (latched) before its replay, as
a replay that lives across recordings does. OUT.json gets the nodes' last statuses, the seconds each stage took and
"ok" (false with "error" on a timeout or a failed replay). Exit code 0 when ok.
"""
import json
import os
import subprocess
import sys
import time

import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

from std_msgs.msg import String

from maglev_ros.bag_reader import BagReader
from maglev_ros.nodes._common import QOS_CLOCK, QOS_LATCHED, message_class
from maglev_ros.nodes._lifecycle import FINISHED, RECORDING_END, RECORDING_START, GraphWaiter, ReplayEvent


def pad_subscribers(node, ex, bag) -> int:
    """Best-effort subscriptions of this node that bring every data topic of ``bag`` to as many
    subscribers as the busiest has (after the graph view settled); returns that number."""
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
    with BagReader(bag) as r:
        topics = {t: i.msgtype for t, i in r.topics.items() if i.is_sensor_block}
    have = {t: node.count_subscribers(t) for t in topics}
    n = max(have.values())
    for t, k in have.items():
        for _ in range(n - k):
            node.create_subscription(message_class(topics[t]), t, lambda _m: None, QOS_CLOCK)
    return n


def main() -> int:
    out, timeout_s, names, subs, bags = (sys.argv[1], float(sys.argv[2]), sys.argv[3].split(","), sys.argv[4],
                                         sys.argv[5:])
    rclpy.init()
    node = Node("protocol_driver")
    waiter = GraphWaiter(node)
    # each recording's metadata stays latched here while its nodes work: the replay process's own
    # latched copy goes with it, and a node whose metadata subscription matched late missed it
    metadata = node.create_publisher(String, "/testline/metadata", QOS_LATCHED)
    ex = EventsExecutor()
    ex.add_node(node)
    report = {"ok": False, "stages": []}
    t0 = time.monotonic()

    def stage(what, left):
        report["stages"].append([what, round(time.monotonic() - t0, 2)])
        if left:
            report["error"] = f"{what}: still pending {left}"
        return not left

    try:
        if not stage("ready", waiter.wait(ex, lambda: waiter.not_ready(names), timeout_s)):
            return 1
        for i, bag in enumerate(bags):
            with BagReader(bag) as r:
                counts = {t: int(info.count) for t, info in r.topics.items()}
                metadata.publish(String(data=r.read_metadata_json()))
            n = str(pad_subscribers(node, ex, bag)) if subs == "auto" else subs
            waiter.announce(ReplayEvent(RECORDING_START, i, str(bag)))
            rep = subprocess.Popen([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--fast", "--quiet",
                                    "--wait-subscribers", n], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   text=True, env=os.environ)
            while rep.poll() is None:       # keep taking the nodes' statuses meanwhile
                ex.spin_once(timeout_sec=0.05)
            log = rep.stdout.read()
            if rep.returncode != 0:
                report["error"] = f"replay of {bag} failed: {log[-2000:]}"
                return 1
            stage(f"replayed {i} ({n} subscribers per topic)", [])
            waiter.announce(ReplayEvent(RECORDING_END, i, str(bag), counts))
            if not stage(f"done {i}", waiter.wait(ex, lambda: waiter.not_done(names, i), timeout_s)):
                return 1
        waiter.announce(ReplayEvent(FINISHED, len(bags)))
        report["ok"] = True
        return 0
    finally:
        report["statuses"] = {n: json.loads(s.to_json()) for n, s in waiter.statuses.items()}
        with open(out, "w") as f:
            json.dump(report, f)
        end = time.monotonic() + 1.0        # let the last event reach the nodes before the writer goes
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
