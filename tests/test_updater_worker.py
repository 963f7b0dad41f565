"""The updater's guideway layer runs off the executor: the ``maglev/modes`` callback only hands the
estimate on; one fit at a time; an estimate arriving while a fit runs waits and a newer one
replaces it (counted); the callback returns while the fit is still running. The node is built in
a subprocess (its own rclpy context) with the fit replaced by a stand-in that blocks until
released, so "a fit is running" is a state the test sets, not a timing."""
import json
import subprocess
import sys
import textwrap

import pytest

from rosgraph import ros_env

pytestmark = pytest.mark.ros

SCRIPT = textwrap.dedent('''
    import json, threading, time
    import numpy as np
    import rclpy
    from maglev_msgs.msg import ModalEstimate, ModalMode
    from maglev_ros.nodes._common import stamp_to_msg
    from maglev_ros.nodes.updater import UpdaterNode
    rclpy.init(args=["t", "--ros-args", "-p", "magnet_layer:=false", "-p", "recording_update:=false"])
    node = UpdaterNode()
    release, started, fitted = threading.Event(), threading.Event(), []
    node.core.take_modes_job = lambda modes, stamp: {"stamp_s": stamp, "f": np.array([stamp]), "std": np.array([0.0])}
    node.core.changed = lambda f, std: True

    def compute(job):
        started.set()
        release.wait(60)
        fitted.append(job["stamp_s"])
        return job
    node.core.compute_modes_update = compute
    node.core.accept_modes_update = lambda result: None

    def estimate(stamp_s):
        m = ModalEstimate()
        stamp_to_msg(int(round(stamp_s * 1e9)), m.header)
        m.method = "ssi-cov online"
        mm = ModalMode()
        mm.id, mm.status, mm.frequency_hz = "M1", "tracked", 23.5
        m.modes.append(mm)
        node._on_modes(m)
    estimate(1.0)
    assert started.wait(60)                   # the first fit runs on the worker; the callback returned
    for s in (2.0, 3.0, 4.0):
        estimate(s)
    running = node.modes_running
    release.set()
    deadline = time.monotonic() + 60
    while node.modes_running and time.monotonic() < deadline:
        time.sleep(0.01)
    print(json.dumps({"fitted": fitted, "superseded": node.modes_superseded, "running_meanwhile": running,
                      "running_after": node.modes_running}))
    node.diagnostics.close()
    node.destroy_node()
    rclpy.try_shutdown()
''')


def test_the_guideway_layer_fits_the_newest_estimate_off_the_executor():
    p = subprocess.run([sys.executable, "-c", SCRIPT], env=ros_env(82), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    # 2.0 waited, 3.0 replaced it, 4.0 replaced 3.0: two superseded, the newest fitted next
    assert got == {"fitted": [1.0, 4.0], "superseded": 2, "running_meanwhile": True, "running_after": False}
