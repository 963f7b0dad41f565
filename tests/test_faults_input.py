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
    env = dict(os.environ, ROS_DOMAIN_ID=str(120 + os.getpid() % 40), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    r = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(nested_bag), "--fast", "--quiet"],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    _one_line(r.stderr, "metadata is nested too deeply")
