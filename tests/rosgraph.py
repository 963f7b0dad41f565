"""Running a node under test over a real ROS 2 graph: start it, replay a bag into it, collect
what it publishes (tests/ros_collect.py), stop everything; or talk to it from the test process
(``ros_context``, ``spin_until``, ``call``)."""
import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def domain_id(base: int) -> int:
    """A ROS domain for one test's graph, never the one a test running at the same time in another
    pytest-xdist worker uses: worker w of n takes the domains = w (mod n), all within Fast DDS's 0-232."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0)
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    return worker + workers * ((base + os.getpid()) % (230 // workers))


def ros_env(domain_base: int) -> dict:
    """Environment for one test's graph: its own domain id, DDS on loopback, the repo on path."""
    return dict(os.environ, ROS_DOMAIN_ID=str(domain_id(domain_base)),
                ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def replay_through_node(env: dict, node_module: str, node_params: list[str], bag, collect: list[str],
                        out: Path, rate: float, wait_subscribers: int = 1, idle_s: float = 4.0) -> dict:
    """Start ``node_module`` (``-p`` params), collect ``collect`` ("pkg/msg/Type:/topic"), replay
    ``bag`` at ``rate`` and return the collected messages per topic."""
    node = subprocess.Popen([sys.executable, "-m", node_module, "--ros-args", *node_params], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    coll = subprocess.Popen([sys.executable, str(HERE / "ros_collect.py"), str(out), "120",
                             str(idle_s), *collect], env=env)
    try:
        time.sleep(1.0)
        rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(bag),
                              "--rate", str(rate), "--quiet", "--wait-subscribers", str(wait_subscribers)],
                             env=env, capture_output=True, text=True, timeout=120)
        assert rep.returncode == 0, rep.stderr
        coll.wait(timeout=150)
    finally:
        stop_processes(node, coll)
    return json.loads(out.read_text())


def stop_processes(*procs) -> None:
    """SIGINT to each still running, then kill what has not ended within 10 s."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(2)
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


@contextlib.contextmanager
def ros_context(env: dict):
    """An rclpy context in the test process on ``env``'s ROS domain (DDS on loopback), shut down
    on exit: for a test that talks to node processes itself (services, parameters, graph queries)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions
    keys = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: env[k] for k in keys})      # read by rcl when the context starts
    ctx = Context()
    try:
        rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def spin_until(executor, cond, what: str, timeout_s: float = 60.0) -> None:
    """Spin ``executor`` until ``cond()``; AssertionError naming ``what`` after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, f"timed out after {timeout_s:g} s waiting for {what}"
        executor.spin_once(timeout_sec=0.05)


def call(executor, client, request, timeout_s: float = 30.0):
    """A service call from the test process: wait for the service, call, return the response."""
    spin_until(executor, client.service_is_ready, f"service {client.srv_name}", timeout_s)
    future = client.call_async(request)
    spin_until(executor, future.done, f"the response of {client.srv_name}", timeout_s)
    return future.result()
