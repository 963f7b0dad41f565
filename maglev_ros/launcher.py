"""A small process launcher for the node graph (``ros2 launch`` is not on PyPI; no rclpy here).

Starts each node of a graph as its own process, prefixes their output with the node name,
stops them all on Ctrl-C, and stops them too when a finite replay has ended.

What each node gets (parameters, namespace, remappings) is ``launch_graph.node_launches``, shared
with the ROS 2 launch file. With a ``namespace`` every node runs in it (``-r __ns:=NS``, ``/clock``
remapped to ``NS/clock``): two graphs run side by side on one ROS domain.

A replay in the graph (one or several recordings, ``bags``) publishes its latched metadata only
when every other node of the graph is up and, if it takes part in the run protocol
(``maglev_ros.nodes._lifecycle``), warm (``wait_nodes``), and its data only when every data topic
has a subscriber (``wait_subscribers`` 1), each at most ``wait_timeout_s`` (``WAIT_TIMEOUT_S``:
process start-up, imports and kernel compilation take a while on a loaded machine), so no node
misses the beginning. After each recording it waits until every node that takes part has
published that recording's results (at most ``results_timeout_s``), so when it exits the graph's
work is done: nodes that end by themselves (``NodeSpec.finishes``, the demo's summary) are given
``FINISH_TIMEOUT_S`` to end, then the rest is stopped. ``linger_s`` is extra time the replay stays
alive after its last recording (its latched metadata stays available to late joiners).

Every node process is watched. A node that ends with a non-zero code or by a signal (kill -9), or
a node that runs until stopped (``NodeSpec.runs_until_stopped``) ending at all, while the graph
runs stops the graph: the others get SIGINT (SIGKILL after ``STOP_TIMEOUT_S``) and
:class:`GraphFailure` names the node and how it ended. A node ending with code 0 by design (the
replay after its linger, the demo's summary) is no failure, nor is a clean exit when stopped.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from maglev_ros.errors import UserError
from maglev_ros.launch_graph import NodeSpec, node_launches, ros_args

STOP_TIMEOUT_S = 5.0
FINISH_TIMEOUT_S = 60.0
# exit codes of a node stopped by SIGINT: 0 from run_node; 130 / -SIGINT from Python when the
# signal came before the node installed its handler (still importing)
_STOPPED_CLEANLY = (0, 130, -signal.SIGINT)
# each node in a process group of its own (a terminal's Ctrl-C reaches the launcher only, which stops
# them in order), in the launcher's session: Linux's autogroup scheduling shares the cores per
# session, and the nodes' background threads (nodes._common.background_thread) only yield to the
# other nodes' stream work when they share one
_OWN_GROUP = {"process_group": 0} if sys.version_info >= (3, 11) else {"preexec_fn": os.setpgrp}


class GraphFailure(UserError):
    """A node of the graph ended while the graph ran, or crashed while it was being stopped."""


@dataclass
class Running:
    spec: NodeSpec
    proc: subprocess.Popen
    pump: threading.Thread | None = None
    killed: bool = False          # SIGKILLed by stop_all: it did not stop within its timeout


def how_it_ended(returncode: int) -> str:
    """'killed by SIGKILL' or 'exit code 1', from a Popen returncode."""
    if returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit code {returncode}"


def _ended_wrongly(r: Running) -> bool:
    rc = r.proc.poll()
    return rc is not None and (rc != 0 or r.spec.runs_until_stopped)


def _pump(name: str, stream, out) -> None:
    for line in iter(stream.readline, ""):
        out.write(f"[{name}] {line}" if not line.startswith("\r") else line)
        out.flush()


def command_lines(graph_name: str, bag: str | None = None, overrides: dict | None = None,
                  params_file: str | None = None, linger_s: float = 2.0, namespace: str = "",
                  use_sim_time: bool = False, extra: list[NodeSpec] = (), bags: list[str] | None = None,
                  results_timeout_s: float | None = None, adapter: str | None = None,
                  metadata: str | None = None) -> list[tuple[NodeSpec, list[str]]]:
    """(spec, command line) of every node :func:`launch` starts with these arguments."""
    return [(nl.spec, [sys.executable, "-u", "-m", nl.module, *ros_args(nl)])
            for nl in node_launches(graph_name, bag=bag, overrides=overrides, params_file=params_file,
                                    namespace=namespace, use_sim_time=use_sim_time, linger_s=linger_s,
                                    extra=extra, bags=bags, results_timeout_s=results_timeout_s,
                                    adapter=adapter, metadata=metadata)]


def launch(graph_name: str, bag: str | None = None, overrides: dict | None = None,
           params_file: str | None = None, linger_s: float = 2.0, env: dict | None = None,
           out=sys.stderr, on_started=None, extra: list[NodeSpec] = (), namespace: str = "",
           use_sim_time: bool = False, bags: list[str] | None = None,
           results_timeout_s: float | None = None, adapter: str | None = None,
           metadata: str | None = None) -> int:
    """Run a graph until its replay of ``bag`` (or ``bags``, in order) has ended and the graph's
    results are out. Returns 0 when every node ran and ended as it should, 130 on Ctrl-C; raises
    :class:`GraphFailure` (after stopping the graph) when a node failed."""
    procs: list[Running] = []
    failures: list[str] = []
    penv = dict(os.environ if env is None else env)
    cmds = command_lines(graph_name, bag=bag, overrides=overrides, params_file=params_file, linger_s=linger_s,
                         namespace=namespace, use_sim_time=use_sim_time, extra=extra, bags=bags,
                         results_timeout_s=results_timeout_s, adapter=adapter, metadata=metadata)
    try:
        for spec, cmd in cmds:
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    text=True, env=penv, **_OWN_GROUP)
            pump = threading.Thread(target=_pump, args=(spec.name, proc.stdout, out), daemon=True)
            pump.start()
            procs.append(Running(spec, proc, pump))
        if on_started is not None:
            on_started()
        replay = next((r for r in procs if r.spec.needs_bag), None)
        replay_ended = False
        while True:
            dead = [r for r in procs if _ended_wrongly(r)]
            if dead:
                for r in dead:
                    r.pump.join(2.0)                # its last words (a traceback) before our line
                    failures.append(f"node {r.spec.name} ended ({how_it_ended(r.proc.returncode)}) "
                                    f"while the graph was running")
                    out.write(f"[launch] {failures[-1]}: stopping the graph\n")
                break
            if replay_ended:
                break
            if replay is not None and replay.proc.poll() is not None:
                _await_finishers(procs, out)        # the replay ends once the results are out
                replay_ended = True
                continue                            # a node that failed meanwhile is still named
            if replay is None and all(r.proc.poll() is not None for r in procs):
                break
            time.sleep(0.1)
    except KeyboardInterrupt:
        stop_all(procs)
        return 130
    except BaseException:
        stop_all(procs)
        raise
    running = [r for r in procs if r.proc.poll() is None]
    stop_all(procs)
    for r in running:
        if r.pump is not None:
            r.pump.join(2.0)
        if r.killed:
            out.write(f"[launch] {r.spec.name} did not stop within {STOP_TIMEOUT_S:g} s of SIGINT: killed\n")
        elif r.proc.returncode not in _STOPPED_CLEANLY:
            failures.append(f"node {r.spec.name} ended ({how_it_ended(r.proc.returncode)}) while the "
                            f"graph was being stopped")
            out.write(f"[launch] {failures[-1]}\n")
    out.flush()
    if failures:
        more = f" (and {len(failures) - 1} more, see above)" if len(failures) > 1 else ""
        raise GraphFailure(failures[0] + more)
    return 0


def _await_finishers(procs: list[Running], out) -> None:
    """Give the nodes that end by themselves (the demo's summary) time to end, watching for failures."""
    deadline = time.monotonic() + FINISH_TIMEOUT_S
    waiting = [r for r in procs if r.spec.finishes]
    while any(r.proc.poll() is None for r in waiting):
        if time.monotonic() > deadline:
            names = ", ".join(r.spec.name for r in waiting if r.proc.poll() is None)
            out.write(f"[launch] {names} did not end within {FINISH_TIMEOUT_S:g} s of the replay's end: "
                      f"stopping the graph\n")
            return
        if any(_ended_wrongly(r) for r in procs):
            return                                  # the caller's next check names it
        time.sleep(0.1)


def stop_all(procs: list[Running], timeout_s: float = STOP_TIMEOUT_S) -> None:
    """SIGINT to every running node's process group; SIGKILL (``killed``) to those still running
    after ``timeout_s``."""
    for r in procs:
        if r.proc.poll() is None:
            _signal_group(r, signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    for r in procs:
        try:
            r.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            r.killed = True
            _signal_group(r, signal.SIGKILL)
            r.proc.wait()


def _signal_group(r: Running, sig: int) -> None:
    try:
        os.killpg(r.proc.pid, sig)
    except ProcessLookupError:      # the group is gone (the node ended meanwhile)
        pass
