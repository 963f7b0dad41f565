"""maglev_ros.launcher over a real ROS 2 graph: the replay waits for every other node of the graph
(no node misses the start of a recording), keeps its latched metadata alive while the graph
lingers, and the graph stops when the linger is over."""
import io
import json
import time

import pytest

from maglev_ros import launch_graph
from maglev_ros.bag_reader import BagReader
from maglev_ros.launch_graph import NodeSpec
from maglev_ros.launcher import launch
from rosgraph import ros_env

pytestmark = pytest.mark.ros

BAG = launch_graph.__file__.rsplit("/maglev_ros/", 1)[0] + "/bags/paper_pass"


def test_replay_waits_for_the_graph_and_every_message_arrives(tmp_path, monkeypatch):
    env = ros_env(150)
    out = tmp_path / "flow.json"
    # the summary node is slow to start (imports); without waiting for it the replay at 20x would
    # be half over before it subscribes
    monkeypatch.setitem(launch_graph.GRAPHS, "_test", [
        NodeSpec("replay", "maglev_ros.nodes.replay", needs_bag=True),
        NodeSpec("summary", "maglev_ros.nodes.summary",
                 params={"idle_s": 1.0, "json_out": str(out), "reliable": True}),   # counts every message
    ])
    log = io.StringIO()
    t0 = time.monotonic()
    code = launch("_test", bag=BAG, env=env, linger_s=4.0, out=log,
                  overrides={"replay": {"rate": 20.0, "progress": False}})
    wall = time.monotonic() - t0
    assert code == 0, log.getvalue()
    with BagReader(BAG) as r:
        expected = {t: i.count for t, i in r.topics.items()}
    flow = json.loads(out.read_text())["topics"]
    got = {t: flow.get(t, {}).get("messages", 0) for t in expected}
    assert got == expected, log.getvalue()
    assert "starting anyway" not in log.getvalue()
    # the replay lingered (4 s) and then the graph stopped: bounded, not hanging
    assert 4.0 < wall < 90.0
