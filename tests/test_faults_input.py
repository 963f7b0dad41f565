"""Hostile or broken user input gives one line, never a traceback: metadata nested 100 000 levels
deep, a topic name ROS does not accept."""
import json
import os
import subprocess
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))
from bagfactory import Faults, example_topics, make_metadata, write_foreign_bag  # noqa: E402

from maglev_ros.cli import main  # noqa: E402
from rosgraph import domain_id


def _one_line(err: str, *needles: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def nested_bag(tmp_path_factory):
    topics = example_topics()
    md = make_metadata(topics)
    deep = "[" * 100_000 + "]" * 100_000
    text = json.dumps(md)[:-1] + f', "deep": {deep}}}'
    return write_foreign_bag(tmp_path_factory.mktemp("nested") / "bag", md, topics,
                             faults=Faults(metadata_text=text))


@pytest.mark.parametrize("verb", ["info", "modes"])
def test_deeply_nested_metadata_is_one_line(nested_bag, verb, capsys):
    assert main([verb, str(nested_bag)]) == 1
    _one_line(capsys.readouterr().err, "metadata is nested too deeply", str(nested_bag))


def test_deeply_nested_metadata_stops_the_replay_in_one_line(nested_bag):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id(120)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    r = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(nested_bag), "--fast", "--quiet"],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    _one_line(r.stderr, "metadata is nested too deeply")


class _Log:
    def __init__(self):
        self.lines = []

    def warning(self, m):
        self.lines.append(m)


class _Node:
    def __init__(self):
        self.log = _Log()

    def get_logger(self):
        return self.log


class _Diag:
    def __init__(self):
        self.checks = []

    def add_check(self, f):
        self.checks.append(f)

    def check(self):                # the block gate's own check (dropped blocks)
        return self.checks[0]()


def _msg(channels, units, data, rate=100.0):
    from types import SimpleNamespace
    import numpy as np
    return SimpleNamespace(channels=list(channels), units=list(units), sample_rate_hz=rate,
                           data=np.asarray(data, np.float32).ravel().tobytes(),
                           header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=0), frame_id="x"))


def test_nodes_take_blocks_in_si_as_the_verbs_do():
    import numpy as np
    from maglev_ros.contract import unit_conversion
    from maglev_ros.nodes._common import BlockGate
    node, diag = _Node(), _Diag()
    gate = BlockGate(node, diag)
    x = np.array([[0.5, 1.0], [-0.25, 2.0]])
    b = gate.block(_msg(("M1A", "M2A"), ("g", "g"), x), "/testline/vehicle/accel")
    np.testing.assert_allclose(b.data, x * unit_conversion("g")[1], rtol=1e-6)
    assert b.units == ("m/s^2", "m/s^2")
    gate.block(_msg(("M1A", "M2A"), ("g", "g"), x), "/testline/vehicle/accel")
    assert len(node.log.lines) == 1 and "g -> m/s^2" in node.log.lines[0]      # said once per topic
    # a unit outside the table (a new stream: a changed layout is its own fault): dropped and counted
    gate.new_stream()
    assert gate.block(_msg(("M1A", "M2A"), ("furlong", "g"), x), "/testline/vehicle/accel") is None
    assert diag.check().values["dropped_unit"] == 1 and "furlong" in node.log.lines[-1]


def test_a_topic_name_ros_refuses_is_skipped_with_one_warning(tmp_path):
    topics = example_topics()
    md = make_metadata(topics)
    good = next(iter(topics))
    topics["/testline/extra/bad name"] = topics[good]
    bag = write_foreign_bag(tmp_path / "bag", md, topics)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id(125)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    r = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag), "--fast", "--quiet"],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "bad name" in ln]
    assert len(warn) == 1 and "not a valid ROS 2 topic name" in warn[0]


@pytest.mark.parametrize("verb", ["info", "modes", "irregularity", "diagnose"])
@pytest.mark.parametrize("damage", ["corrupt_yaml", "zero_byte_mcap"])
def test_a_damaged_bag_file_is_one_line_before_any_work(tmp_path, damage, verb, capsys):
    import shutil
    from pathlib import Path
    sample = Path(__file__).resolve().parents[1] / "bags" / "paper_ambient"
    if damage == "corrupt_yaml":
        bag = tmp_path / "bag"
        shutil.copytree(sample, bag)
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    else:
        bag = tmp_path / "empty.mcap"
        bag.write_bytes(b"")
    argv = {"info": ["info", str(bag)], "modes": ["modes", str(bag)],
            "irregularity": ["irregularity", str(bag), "--out", str(tmp_path / "r.csv")],
            "diagnose": ["diagnose", "--pass", str(bag), "--out", str(tmp_path / "d")]}[verb]
    assert main(argv) == 1
    _one_line(capsys.readouterr().err, str(bag), "cannot open bag")
    assert not (tmp_path / "r.csv").exists() and not (tmp_path / "d").exists()


def test_nodes_report_a_flat_lined_channel_on_diagnostics():
    import numpy as np
    from maglev_ros.nodes._common import BlockGate
    node, diag = _Node(), _Diag()
    gate = BlockGate(node, diag)
    checks = diag.checks
    rng = np.random.default_rng(1)
    for k in range(40):                         # 4 s at 1 kHz: G1 live, G2 flat-lined
        x = np.column_stack([rng.normal(0, 0.05, 100), np.full(100, 0.0)])
        assert gate.block(_msg(("G1LV", "G2LV"), ("m/s^2", "m/s^2"), x, rate=1000.0),
                          "/testline/guideway/accel") is not None
    health = checks[1]()
    assert health.level == 1 and "G2LV flat" in health.message and "G1LV" not in health.message
    assert any("[G2LV]" in ln and "flat-lined" in ln for ln in node.log.lines)
    assert checks[0]().level == 0               # no block was dropped: the data are still used
