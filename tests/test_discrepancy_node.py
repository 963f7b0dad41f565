"""The discrepancy node over a real ROS 2 graph: residual stream in, MismatchReport out."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rosgraph import domain_id

pytestmark = pytest.mark.ros
HERE = Path(__file__).resolve().parent


def test_node_publishes_a_mismatch_report_for_a_residual_burst(tmp_path):
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id(150))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONPATH"] = str(HERE.parent) + os.pathsep + env.get("PYTHONPATH", "")
    node = subprocess.Popen([sys.executable, "-m", "maglev_ros.nodes.discrepancy"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out = tmp_path / "got.json"
        subprocess.run([sys.executable, str(HERE / "discrepancy_ros_probe.py"), str(out)], env=env,
                       timeout=120, check=True)
        got = json.loads(out.read_text())
    finally:
        node.terminate()
        node.wait(timeout=20)
    assert len(got) == 1
    m = got[0]
    assert m["channels"] == ["G1A"] and m["f0_hz"] <= 40.0 <= m["f1_hz"]
    assert 19.0 <= m["t0_s"] <= 20.5 and 22.5 <= m["t1_s"] <= 24.0
    assert 95 <= m["x0"] <= 103 and 112 <= m["x1"] <= 120
    assert m["severity"] > 10 and "diagnose" in m["explanation"]
