"""The irregularity node over a real ROS graph: a pass recording with a known profile is
replayed; the profile the node publishes matches the band-passed truth."""

import numpy as np
import pytest

from irregularity_data import bandpass_truth, make_recording
from rosgraph import replay_through_node, ros_env
from test_irregularity_command import _write_bag

pytestmark = pytest.mark.ros


def test_node_publishes_growing_profile_matching_truth(tmp_path):
    rec = make_recording(40, 7, "constant", length_m=350.0, fs_hz=500.0, bias_mps2=[0.02, 0.0, 0.0])
    bag = tmp_path / "pass"
    _write_bag(rec, bag)
    got = replay_through_node(ros_env(60), "maglev_ros.nodes.irregularity", ["-p", "publish_period_s:=0.5"],
                              bag, ["maglev_msgs/msg/IrregularityProfile:/maglev/irregularity"],
                              tmp_path / "got.json", rate=5)
    msgs = got["/maglev/irregularity"]
    assert len(msgs) >= 2
    sizes = [len(m["irregularity_m"]) for m in msgs]
    assert sizes == sorted(sizes) and sizes[-1] > sizes[0]          # the profile grows
    last = msgs[-1]
    x = last["start_position_m"] + last["spacing_m"] * np.arange(len(last["irregularity_m"]))
    r = np.array([np.nan if v is None else v for v in last["irregularity_m"]])
    ok = np.isfinite(r)
    assert ok.sum() * last["spacing_m"] > 150.0                     # most of the 350 m pass
    truth = bandpass_truth(x, rec.truth_at(x),
                           last["min_wavelength_m"], last["max_wavelength_m"])
    corr = np.corrcoef(r[ok], truth[ok])[0, 1]
    err = np.sqrt(np.mean((r[ok] - truth[ok]) ** 2)) / np.sqrt(np.mean(truth[ok] ** 2))
    assert corr >= 0.95 and err <= 0.15, (corr, err)
    assert last["kind"] == "loaded" and last["sources"]


def test_node_defaults_follow_a_short_recorded_pass(tmp_path):
    """The bundled 12.7 s pass: with no parameters the node chooses its corner from the stream
    (as the offline verb does) and publishes a profile that matches the recorded truth."""
    from pathlib import Path
    bags = Path(__file__).resolve().parents[1] / "bags"
    got = replay_through_node(ros_env(60), "maglev_ros.nodes.irregularity", [], bags / "paper_pass",
                              ["maglev_msgs/msg/IrregularityProfile:/maglev/irregularity"],
                              tmp_path / "got.json", rate=5)
    msgs = got["/maglev/irregularity"]
    assert msgs, "no profile published with the node's defaults"
    last = msgs[-1]
    x = last["start_position_m"] + last["spacing_m"] * np.arange(len(last["irregularity_m"]))
    r = np.array([np.nan if v is None else v for v in last["irregularity_m"]])
    ok = np.isfinite(r)
    assert ok.sum() * last["spacing_m"] > 30.0
    truth_xr = np.loadtxt(bags / "paper_pass.irregularity.csv", delimiter=",", skiprows=1)
    dense = np.interp(x, truth_xr[:, 0], truth_xr[:, 1])
    truth = bandpass_truth(x, dense, last["min_wavelength_m"], last["max_wavelength_m"])
    corr = np.corrcoef(r[ok], truth[ok])[0, 1]
    assert corr >= 0.9, corr
