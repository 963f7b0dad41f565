"""Online updater: core decisions without ROS (material change, acceptance, durable history,
restore) against the known truth of the span, and the ``updater`` node over a real ROS graph
(publishes TwinParameters, stores the history, republishes after a restart)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from updating_data import ambient_metadata, true_modes
from maglev_ros.updating.online import OnlineUpdater
from rosgraph import domain_id, stop_processes

HERE = Path(__file__).resolve().parent
DESIGN = {"guideway": {"youngs_modulus_pa": 3.9e10, "density_kg_m3": 2500.0, "area_m2": 1.48,
                       "second_moment_m4": 0.457, "bearing_stiffness_n_per_m": 3.0e10, "damping_ratio": 0.02}}
F1 = {"youngs_modulus_pa": 1.08, "density_kg_m3": 0.95, "bearing_stiffness_n_per_m": 1.10}
F2 = {"youngs_modulus_pa": 0.93, "density_kg_m3": 1.04, "bearing_stiffness_n_per_m": 0.92}


def _model_freqs(md, values):
    from maglev_ros.twin.design import line_spans, twin_config_from_metadata, with_guideway
    from maglev_ros.twin.guideway import Guideway
    cfg = with_guideway(twin_config_from_metadata(md), **values)
    return Guideway(line_spans(md["line"], cfg)).frequencies_hz(0, 3)


def test_core_updates_on_material_change_only_and_restores(tmp_path):
    md = ambient_metadata(DESIGN)
    hist = tmp_path / "h.jsonl"
    up = OnlineUpdater(hist)
    assert up.on_modes(true_modes(md, F1)) is None          # no metadata yet: ignored
    up.set_metadata(md)
    pub = up.on_modes(true_modes(md, F1, seed=1))
    assert pub is not None and pub.revision == 1
    vals = dict(zip(pub.names, pub.values))
    assert "guideway.youngs_modulus_pa" in vals
    f_true = _model_freqs(md, {k: DESIGN["guideway"][k] * v for k, v in F1.items()})
    f_up = _model_freqs(md, {k.split(".")[1]: v for k, v in vals.items()})
    assert np.max(np.abs(f_up / f_true - 1)) < 0.005
    e_rho = vals["guideway.youngs_modulus_pa"] / vals["guideway.density_kg_m3"]
    assert abs(e_rho / (3.9e10 * 1.08 / (2500 * 0.95)) - 1) < 0.02
    # same structure, new noise: not a material change
    assert up.on_modes(true_modes(md, F1, seed=2)) is None
    # a lost mode is ignored, the others are unchanged: still no update
    lost = true_modes(md, F1, seed=3) + [dict(true_modes(md, F2)[0], status="lost", id="X")]
    assert up.on_modes(lost) is None
    # a changed structure: accepted as revision 2
    pub2 = up.on_modes(true_modes(md, F2, seed=4))
    assert pub2 is not None and pub2.revision == 2
    recs = [json.loads(l) for l in hist.read_text().splitlines()]
    assert [r["revision"] for r in recs] == [1, 2]
    assert recs[1]["data_used"]["kind"] == "modes" and recs[1]["fit"]["max_freq_error_after"] < 0.005
    # restart: the last accepted parameters of this line are restored and republished unchanged
    again = OnlineUpdater(hist)
    again.set_metadata(md)
    restored = again.restore()
    last = restored.publication
    assert last.revision == 2 and last.values == pub2.values and last.names == pub2.names
    assert "continuing from revision 2" in restored.message and str(hist) in restored.message
    assert again.on_modes(true_modes(md, F2, seed=5)) is None


def test_history_of_another_line_is_never_loaded(tmp_path):
    md = ambient_metadata(DESIGN)
    hist = tmp_path / "h.jsonl"
    up = OnlineUpdater(hist)
    up.set_metadata(md)
    assert up.restore().publication is None
    assert up.on_modes(true_modes(md, F1, seed=1)).revision == 1
    # the same file, a recording of another line (other spans): nothing loaded, and it says so
    other = json.loads(json.dumps(md))
    other["line"]["spans"][0]["length_m"] = 24.0
    up2 = OnlineUpdater(hist)
    up2.set_metadata(other)
    restored = up2.restore()
    assert restored.publication is None and up2.current == {} and up2.revision == 0
    assert "1 record(s) of other lines" in restored.message
    # the first line's record is still there for a recording of the first line
    up3 = OnlineUpdater(hist)
    up3.set_metadata(md)
    assert up3.restore().publication.revision == 1


def test_history_without_a_path_stays_in_memory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    md = ambient_metadata(DESIGN)
    up = OnlineUpdater(None)
    up.set_metadata(md)
    assert "memory only" in up.restore().message
    assert up.on_modes(true_modes(md, F1, seed=1)).revision == 1
    assert list(tmp_path.iterdir()) == []


def _env():
    return dict(os.environ, ROS_DOMAIN_ID=str(domain_id(100)), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONPATH=str(HERE.parent) + os.pathsep + str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", ""))


@pytest.mark.ros
def test_updater_node_publishes_stores_and_republishes_after_restart(tmp_path):
    md = ambient_metadata(DESIGN)
    (tmp_path / "md.json").write_text(json.dumps(md))
    (tmp_path / "modes.json").write_text(json.dumps(true_modes(md, F1, seed=1)))
    hist = tmp_path / "hist.jsonl"
    env = _env()
    node_cmd = [sys.executable, "-m", "maglev_ros.nodes.updater", "--ros-args", "-p", f"history_path:={hist}",
                "-p", "magnet_layer:=false"]
    node = subprocess.Popen(node_cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out1 = tmp_path / "got1.json"
    coll = subprocess.Popen([sys.executable, str(HERE / "ros_collect.py"), str(out1), "90", "3",
                             "maglev_msgs/msg/TwinParameters:/maglev/twin/parameters"], env=env)
    pub = subprocess.Popen([sys.executable, str(HERE / "updating_data.py"), str(tmp_path / "md.json"),
                            str(tmp_path / "modes.json"), "60"], env=env)
    try:
        coll.wait(timeout=120)
    finally:
        stop_processes(pub, coll, node)
    got = json.loads(out1.read_text())["/maglev/twin/parameters"]
    assert got, node.stdout.read() if node.stdout else ""
    m = got[-1]
    assert m["revision"] == 1 and "guideway.youngs_modulus_pa" in m["names"]
    vals = dict(zip(m["names"], m["values"]))
    e_rho = vals["guideway.youngs_modulus_pa"] / vals["guideway.density_kg_m3"]
    assert abs(e_rho / (3.9e10 * 1.08 / (2500 * 0.95)) - 1) < 0.02
    assert json.loads(m["provenance_json"])["data_used"]["kind"] == "modes"
    recs = [json.loads(l) for l in hist.read_text().splitlines()]
    assert len(recs) == 1 and recs[0]["revision"] == 1
    # restart: when the line's metadata arrives, republished from the history (the same modes
    # again are no new evidence: no new revision)
    node2 = subprocess.Popen(node_cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out2 = tmp_path / "got2.json"
    coll2 = subprocess.Popen([sys.executable, str(HERE / "ros_collect.py"), str(out2), "40", "2",
                              "maglev_msgs/msg/TwinParameters:/maglev/twin/parameters"], env=env)
    pub2 = subprocess.Popen([sys.executable, str(HERE / "updating_data.py"), str(tmp_path / "md.json"),
                             str(tmp_path / "modes.json"), "30"], env=env)
    try:
        coll2.wait(timeout=60)
    finally:
        stop_processes(pub2, coll2, node2)
    got2 = json.loads(out2.read_text())["/maglev/twin/parameters"]
    assert got2 and got2[-1]["revision"] == 1 and got2[-1]["values"] == m["values"]


SHUTDOWN_SCRIPT = r'''
import sys, threading, time
import numpy as np
from rclpy.node import Node
from maglev_ros.nodes._common import run_node
from maglev_ros.nodes.updater import UpdaterNode

class Busy(Node):
    """A node whose worker thread is still in native code (matrix products) when the node ends."""
    SHUTDOWN_WAIT_S = 0.5
    unfinished_work = UpdaterNode.unfinished_work

    def __init__(self):
        super().__init__("busy_updater")
        a = np.random.default_rng(0).standard_normal((400, 400))
        def work():
            while True:
                a @ a
        self.worker = threading.Thread(target=work, daemon=True)
        self.worker.start()
        self.exit_code = 7
        self.t0 = time.monotonic()
        self.create_timer(0.2, self._tick)
        self.finished = False

    def _tick(self):
        self.finished = time.monotonic() - self.t0 > 1.0

sys.exit(run_node(Busy, []))
'''


def test_a_node_ending_while_its_worker_runs_exits_promptly_with_its_code(tmp_path):
    """The updater's shutdown path: a worker still running after the wait is abandoned with a warning,
    and the process ends with the node's exit code (no interpreter teardown under the worker)."""
    script = tmp_path / "busy.py"
    script.write_text(SHUTDOWN_SCRIPT)
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, str(script)], env=_env(), capture_output=True, text=True, timeout=60)
    assert p.returncode == 7, p.stdout + p.stderr
    assert "its result is discarded" in p.stdout + p.stderr
    assert "Fatal Python error" not in p.stdout + p.stderr
    assert time.monotonic() - t0 < 30
