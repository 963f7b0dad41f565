"""``maglev-ros launch monitor --adapter MAPPING --metadata META``: the DAQ adapter is the graph's
source instead of a replay, the same from the launch file; option mistakes are one line before any
node starts (no ROS graph is started here)."""
from pathlib import Path

import pytest
import yaml

from maglev_ros.cli import build_parser
from maglev_ros.commands.launch import launch_kwargs
from maglev_ros.daq_stream.sim import source_from_bag, write_config
from maglev_ros.errors import UserError
from test_launch_file import _from_launch_file, _from_launcher

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "bags" / "paper_pass"


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    return write_config(source_from_bag(BAG, 0.0, 0.05), tmp_path_factory.mktemp("daqcfg"))


def test_adapter_replaces_the_replay_in_both_launchers(monkeypatch, config):
    meta, mapping = config
    cli = _from_launcher(["--adapter", str(mapping), "--metadata", str(meta)])
    assert _from_launch_file(monkeypatch, {"adapter": str(mapping), "metadata": str(meta)}) == cli
    assert "replay" not in cli and set(cli) == {"daq_adapter", "irregularity", "modal_id", "updater",
                                                "discrepancy", "twin"}
    params = cli["daq_adapter"][3]
    assert params["mapping"] == str(mapping.resolve()) and params["metadata"] == str(meta.resolve())
    assert params["wait_subscribers"] == "1"


def _kwargs(argv):
    return launch_kwargs(build_parser().parse_args(["launch", "monitor", *argv]))


def test_option_mistakes_are_one_line(config, tmp_path):
    meta, mapping = config
    cases = [(["--adapter", str(mapping)], r"^--adapter and --metadata: give both"),
             (["--adapter", str(mapping), "--metadata", str(meta), "--bag", str(BAG)], r"two sources"),
             (["--daq-sim", str(BAG), "--bag", str(BAG)], r"^--daq-sim and --bag are two sources"),
             (["--adapter", str(tmp_path / "none.yaml"), "--metadata", str(meta)], r"^--adapter .*: no such file")]
    bad = tmp_path / "bad.yaml"
    doc = yaml.safe_load(mapping.read_text())
    doc["channels"]["M1G"]["unit"] = "g"
    bad.write_text(yaml.safe_dump(doc))
    cases.append((["--adapter", str(bad), "--metadata", str(meta)], rf"^{bad}: mapping key channels.M1G.unit: "))
    for argv, pattern in cases:
        with pytest.raises(UserError, match=pattern) as err:
            _kwargs(argv)
        assert "\n" not in str(err.value)
