"""The twin node adopts new parameters at a point a replay decides, not when they happen to arrive:
during a replay's recording a revision waits for the next recording's twin (its arrival time depends
on the wall clock, so adopting it at once would change the predictions at another block on every run);
on a live stream (no replay event) it is adopted at once."""
import json
from pathlib import Path

import pytest

SAMPLE = Path(__file__).resolve().parent.parent / "bags" / "paper_pass"

pytestmark = pytest.mark.ros


@pytest.fixture()
def node():
    import rclpy
    rclpy.init()
    from maglev_ros.nodes.twin import TwinNode
    n = TwinNode()
    yield n
    n.destroy_node()
    rclpy.shutdown()


def _metadata(seed: int):
    """The sample pass's metadata (a new recording: another run id)."""
    from std_msgs.msg import String

    from maglev_ros.bag_reader import BagReader
    with BagReader(SAMPLE) as r:
        md = dict(r.metadata.raw)
    md["run"] = {**md.get("run", {}), "id": f"run-{seed}"}
    return String(data=json.dumps(md))


def _params(rev: int, kp: float):
    from maglev_msgs.msg import TwinParameters
    m = TwinParameters()
    m.revision, m.names, m.values = rev, ["levitation.kp_a_per_m"], [kp]
    return m


def test_a_revision_within_a_replayed_recording_waits_for_the_next_one(node):
    node.lifecycle.events_seen.append("recording_start")          # a replay is running
    node._on_metadata(_metadata(0))
    first = node.core
    node._on_params(_params(3, 7200.0))
    assert first.frame_id != "twin rev 3" and "levitation.kp_a_per_m" not in first.parameters
    node.on_recording_end(0)
    node._on_metadata(_metadata(1))                               # the next recording's twin
    assert node.core is not first
    assert node.core.frame_id == "twin rev 3" and node.core.parameters["levitation.kp_a_per_m"] == 7200.0


def test_a_revision_on_a_live_stream_is_adopted_at_once(node):
    node._on_metadata(_metadata(0))
    node._on_params(_params(4, 7300.0))
    assert node.core.frame_id == "twin rev 4" and node.core.parameters["levitation.kp_a_per_m"] == 7300.0
