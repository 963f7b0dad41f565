"""The irregularity node over a real ROS graph: a pass recording with a known profile is
replayed; the profile the node publishes matches the band-passed truth."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from irregularity_data import bandpass_truth, make_recording
from test_irregularity_command import _write_bag

pytestmark = pytest.mark.ros
HERE = Path(__file__).resolve().parent


def test_node_publishes_growing_profile_matching_truth(tmp_path):
    rec = make_recording(40, 7, "constant", length_m=350.0, fs_hz=500.0, bias_mps2=[0.02, 0.0, 0.0])
    bag = tmp_path / "pass"
    _write_bag(rec, bag)
    env = dict(os.environ, ROS_DOMAIN_ID=str(60 + os.getpid() % 40),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = tmp_path / "got.json"
    node = subprocess.Popen([sys.executable, "-m", "maglev_ros.nodes.irregularity", "--ros-args",
                             "-p", "publish_period_s:=0.5"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    coll = subprocess.Popen([sys.executable, str(HERE / "ros_collect.py"), str(out), "90", "4",
                             "maglev_msgs/msg/IrregularityProfile:/maglev/irregularity"], env=env)
    try:
        time.sleep(1.0)
        rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag),
                              "--rate", "5", "--quiet", "--wait-subscribers", "1"],
                             env=env, capture_output=True, text=True, timeout=120)
        assert rep.returncode == 0, rep.stderr
        coll.wait(timeout=120)
    finally:
        for p in (node, coll):
            if p.poll() is None:
                p.send_signal(2)
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
    msgs = json.loads(out.read_text())["/maglev/irregularity"]
    assert len(msgs) >= 2, node.stdout.read() if node.stdout else ""
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
