"""A small process launcher for the node graph (``ros2 launch`` is not on PyPI; no rclpy here).

Starts each node of a graph as its own process, prefixes their output with the node name,
stops them all on Ctrl-C, and, when a finite replay ends, gives the others ``linger_s`` to
finish and then stops them too.

A replay in the graph publishes its latched metadata only when every other node of the graph is
up (``wait_nodes``: no node's idle timer starts early) and its data only when every data topic
has a subscriber (``wait_subscribers`` 1), each at most ``wait_timeout_s`` = 60 s (process
start-up and imports take seconds on a loaded machine), so no node misses the beginning; it stays alive during the
linger (``linger_s``), so its latched metadata stays available to late joiners.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from maglev_ros.launch_graph import NodeSpec, graph, ros_param_args


@dataclass
class Running:
    spec: NodeSpec
    proc: subprocess.Popen


def _pump(name: str, stream, out) -> None:
    for line in iter(stream.readline, ""):
        out.write(f"[{name}] {line}" if not line.startswith("\r") else line)
        out.flush()


def launch(graph_name: str, bag: str | None = None, overrides: dict | None = None,
           params_file: str | None = None, linger_s: float = 30.0, env: dict | None = None,
           out=sys.stderr, on_started=None, extra: list[NodeSpec] = ()) -> int:
    """Run a graph until its replay ends (or Ctrl-C). Returns the replay's exit code."""
    overrides = overrides or {}
    procs: list[Running] = []
    penv = dict(os.environ if env is None else env)
    specs = [s for s in list(graph(graph_name)) + list(extra) if bag or not s.needs_bag]
    others = [s.name for s in specs if not s.needs_bag]
    try:
        for spec in specs:
            params = dict(spec.params)
            if spec.needs_bag:
                params["bag"] = os.path.abspath(bag)
                params.update({"wait_nodes": others, "wait_subscribers": 1, "wait_timeout_s": 60.0,
                               "linger_s": float(linger_s)})
            params.update(overrides.get(spec.name, {}))
            cmd = [sys.executable, "-u", "-m", spec.module, "--ros-args", "-r", f"__node:={spec.name}"]
            if params_file:
                cmd += ["--params-file", params_file]
            cmd += ros_param_args(params)
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    text=True, env=penv, start_new_session=True)
            threading.Thread(target=_pump, args=(spec.name, proc.stdout, out), daemon=True).start()
            procs.append(Running(spec, proc))
        if on_started is not None:
            on_started()
        replay = next((r for r in procs if r.spec.needs_bag), None)
        while True:
            if replay is not None and replay.proc.poll() is not None:
                return replay.proc.returncode       # it lingered (linger_s) before exiting
            if replay is None and all(r.proc.poll() is not None for r in procs):
                return 0
            dead = [r for r in procs if r.proc.poll() not in (None, 0)]
            if replay is not None:
                dead = [r for r in dead if r is replay]
            if dead:
                out.write(f"[launch] {dead[0].spec.name} exited with code {dead[0].proc.returncode}\n")
                return dead[0].proc.returncode
            time.sleep(0.1)
    except KeyboardInterrupt:
        return 130
    finally:
        stop_all(procs)


def stop_all(procs: list[Running], timeout_s: float = 5.0) -> None:
    for r in procs:
        if r.proc.poll() is None:
            os.killpg(r.proc.pid, signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    for r in procs:
        try:
            r.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            os.killpg(r.proc.pid, signal.SIGKILL)
            r.proc.wait()
