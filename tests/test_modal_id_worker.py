"""modal_id's worker: windows are identified in order off the executor; with skip_when_busy a window
still waiting when a newer one completes is left out and counted, without it every window is
identified. The node is built in a subprocess (its own rclpy context) with the SSI replaced by a
stand-in that blocks until released, so "busy" is a state the test sets, not a timing."""
import json
import subprocess
import sys
import textwrap

import pytest

from rosgraph import ros_env

pytestmark = pytest.mark.ros

SCRIPT = textwrap.dedent('''
    import json, sys, threading, time
    import rclpy
    from maglev_ros.nodes.modal_id import ModalIdNode
    skip = sys.argv[1] == "true"
    rclpy.init(args=["t", "--ros-args", "-p", f"skip_when_busy:={sys.argv[1]}", "-p", "recording_modes:=false"])
    node = ModalIdNode()
    release, started, done = threading.Event(), threading.Event(), []

    class Up:
        modes, events = (), ()

    def identify(job):
        started.set()
        release.wait(60)
        done.append(job["n"])
        return Up()
    node.core.identify = identify
    node._submit(("window", {"n": 0, "window_s": 1.0}, 0))
    assert started.wait(60)                      # the worker is on window 0 now
    for n in range(1, 5):                        # four more complete while it is busy
        node._submit(("window", {"n": n, "window_s": 1.0}, n))
    queued = node.n_jobs
    release.set()
    deadline = time.monotonic() + 60
    while node.busy() and time.monotonic() < deadline:
        time.sleep(0.01)
    print(json.dumps({"identified": done, "skipped": node.windows_skipped, "queued": queued,
                      "busy": node.busy()}))
    node.diagnostics.close()
    node.destroy_node()
    rclpy.try_shutdown()
''')


@pytest.mark.parametrize("skip, identified, skipped", [("true", [0, 4], 3), ("false", [0, 1, 2, 3, 4], 0)])
def test_windows_are_identified_in_order_and_skipped_only_when_asked(skip, identified, skipped):
    p = subprocess.run([sys.executable, "-c", SCRIPT, skip], env=ros_env(81), capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    assert got["identified"] == identified and got["skipped"] == skipped
    assert got["queued"] == 1 + (1 if skip == "true" else 4)       # the running one and those waiting
    assert got["busy"] is False
