"""The suite's node graphs as data (no rclpy): used by ``maglev-ros launch`` and launch/*.launch.py.

Each later capability adds its node here once; both launchers pick it up. What each node of a
launch gets (parameters, namespace, remappings, params file) is computed once, by
:func:`node_launches`: ``maglev_ros.launcher`` turns it into command lines, the ROS 2 launch file
into ``launch_ros`` Node actions, so the two cannot drift. The monitor graph's launch arguments
(:data:`LAUNCH_ARGUMENTS`) are the options of ``maglev-ros launch`` and of monitor.launch.py.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field


@dataclass(frozen=True)
class NodeSpec:
    name: str                       # node name and console script
    module: str                     # python module with main()
    params: dict = field(default_factory=dict)
    needs_bag: bool = False         # only started when a bag is given
    # a processing node ends only when stopped: its end while the graph runs (even with exit
    # code 0, e.g. an outside SIGTERM) is a failure of the graph
    runs_until_stopped: bool = False
    # watches the graph (the live view): the replay does not wait for it, nor for its results
    observer: bool = False
    # ends by itself once the replay has finished (the demo's summary): the launcher waits for it
    # before stopping the others
    finishes: bool = False
    # declares ``stream_rate``: the launcher passes the replay's rate (output periods meant in wall time)
    takes_stream_rate: bool = False


GRAPHS: dict[str, list[NodeSpec]] = {
    "monitor": [
        NodeSpec("replay", "maglev_ros.nodes.replay", needs_bag=True),
        NodeSpec("irregularity", "maglev_ros.nodes.irregularity", runs_until_stopped=True, takes_stream_rate=True),
        NodeSpec("modal_id", "maglev_ros.nodes.modal_id", runs_until_stopped=True),
        # history_path: set by the launcher in its output directory (unset: memory only)
        NodeSpec("updater", "maglev_ros.nodes.updater", runs_until_stopped=True),
        NodeSpec("discrepancy", "maglev_ros.nodes.discrepancy", runs_until_stopped=True),
        # the twin measures the irregularity under the vehicle itself (irregularity_source
        # "vehicle"; see maglev_ros.twin.online) and judges vehicle channels only where it has
        NodeSpec("twin", "maglev_ros.nodes.twin", params={"irregularity_source": "vehicle", "dt_max_s": 5e-4},
                 runs_until_stopped=True),
    ],
}


def recorder_spec(path, include_inputs: bool = False, reliable: bool = False,
                  sim_time: bool = False) -> NodeSpec:
    """The MCAP recorder (maglev_ros.nodes.recorder) added to a graph: ``path`` absolute (the node
    runs elsewhere), log times on the replay's /clock when ``sim_time``."""
    import os
    return NodeSpec("recorder", "maglev_ros.nodes.recorder",
                    params={"path": os.path.abspath(path), "include_inputs": bool(include_inputs),
                            "reliable": bool(reliable), "use_sim_time": bool(sim_time)},
                    runs_until_stopped=True)


def adapter_spec(mapping, metadata) -> NodeSpec:
    """The DAQ adapter (maglev_ros.nodes.daq_adapter) as the graph's source instead of a replay: live
    driver streams -> contract SensorBlocks; it takes the drivers' data once every contract topic it
    publishes has a subscriber (the graph's nodes are up), at most WAIT_TIMEOUT_S."""
    import os
    return NodeSpec("daq_adapter", "maglev_ros.nodes.daq_adapter",
                    params={"mapping": os.path.abspath(mapping), "metadata": os.path.abspath(metadata),
                            "wait_subscribers": 1, "wait_timeout_s": WAIT_TIMEOUT_S},
                    runs_until_stopped=True)


def daq_sim_spec(bag, rate: float = 1.0, reliable: bool = False) -> NodeSpec:
    """The DAQ simulator (maglev_ros.nodes.daq_sim) publishing ``bag`` as driver streams; it starts
    once the adapter subscribes to every driver topic and ends when the bag is out."""
    import os
    return NodeSpec("daq_sim", "maglev_ros.nodes.daq_sim",
                    params={"bag": os.path.abspath(bag), "rate": float(rate), "reliable": bool(reliable),
                            "wait_subscribers": 1, "wait_timeout_s": WAIT_TIMEOUT_S})


VIEW_PORT = 8765          # Foxglove's usual WebSocket port


def view_node(host: str = "127.0.0.1", port: int = VIEW_PORT) -> NodeSpec:
    """The live view (Foxglove bridge) beside a graph: ``maglev-ros launch GRAPH --view``."""
    return NodeSpec("foxglove_bridge", "maglev_ros.nodes.foxglove_bridge", params={"host": host, "port": int(port)},
                    runs_until_stopped=True, observer=True)


def view_urls(host: str, port: int) -> tuple[str, str]:
    """(the Foxglove app's URL that opens the live view, the plain WebSocket URL)."""
    shown = "localhost" if host in ("127.0.0.1", "0.0.0.0", "") else host
    ws = f"ws://{shown}:{int(port)}"
    return f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url={ws}", ws


def extra_nodes(record: str | None = None, record_inputs: bool = False, record_reliable: bool = False,
                sim_time: bool = False, view: bool = False, view_host: str = "127.0.0.1",
                view_port: int = VIEW_PORT) -> list[NodeSpec]:
    """The nodes beside a graph that ``maglev-ros launch --record/--view`` and monitor.launch.py's
    ``record:=``/``view:=`` add: the MCAP recorder (log times on the replay's /clock when
    ``sim_time``, i.e. with a bag) and the Foxglove bridge. Raises UserError (one line) for a record
    file that is not .mcap, record options without a file, a port outside 1-65535."""
    from maglev_ros.errors import UserError
    out = []
    if record:
        if not str(record).endswith(".mcap"):
            raise UserError(f"record {record}: expected a file name ending in .mcap")
        out.append(recorder_spec(record, record_inputs, record_reliable, sim_time=sim_time))
    elif record_inputs or record_reliable:
        raise UserError("record_inputs / record_reliable: given without a record file (.mcap)")
    if view:
        if not 1 <= int(view_port) <= 65535:
            raise UserError(f"view_port: expected a port 1-65535, got {view_port}")
        out.append(view_node(view_host, int(view_port)))
    return out


def graph(name: str) -> list[NodeSpec]:
    from maglev_ros.errors import UserError
    if name not in GRAPHS:
        raise UserError(f"unknown graph '{name}' (known: {', '.join(sorted(GRAPHS))})")
    return GRAPHS[name]


def ros_param_args(params: dict) -> list[str]:
    """``-p name:=value`` arguments for a parameter dict (bools lower-case, lists in YAML)."""
    out: list[str] = []
    for k, v in params.items():
        if isinstance(v, bool):
            val = str(v).lower()
        elif isinstance(v, (list, tuple)):
            val = "[" + ",".join(repr(x) if isinstance(x, str) else str(x) for x in v) + "]"
        else:
            val = str(v)
        out += ["-p", f"{k}:={val}"]
    return out


# the monitor graph's launch arguments: (name, default as text, description); the CLI's options
# (`maglev-ros launch monitor --rate ...`) and monitor.launch.py's `name:=value` arguments
LAUNCH_ARGUMENTS = (
    ("bag", "", "replay this bag through the graph (empty: no replay, the graph waits for data)"),
    ("rate", "1.0", "replay rate, bag seconds per wall second (0.1-100)"),
    ("fast", "false", "replay as fast as the subscribers take it"),
    ("params_file", "", "ROS 2 parameters YAML passed to every node"),
    ("namespace", "", "namespace of the whole graph (two lines side by side: /line1, /line2)"),
    ("use_sim_time", "false", "nodes run on the replay's /clock (the replay itself on wall time)"),
    ("out", "out/monitor", "output directory: the updater's parameter history goes there"),
    ("history", "", "the updater's parameter history (default OUT/twin_parameters.jsonl)"),
    ("adapter", "", "the DAQ adapter's mapping YAML: live driver streams instead of a replay "
                    "(docs/daq_stream.md; needs metadata)"),
    ("metadata", "", "the recording's metadata (YAML or JSON) the DAQ adapter publishes"),
    ("linger_s", "2.0", "extra time the replay (and our launcher: the graph) stays after its end, "
                        "which comes once every node has published the last recording's results"),
    ("results_timeout_s", "900.0", "after each recording, wait at most this long for the nodes' results "
                                   "(the live diagnosis of a pass takes minutes on a busy machine)"),
    ("record", "", "record the graph's /maglev/* outputs, /testline/metadata and /diagnostics to this "
                   ".mcap file (empty: no recorder)"),
    ("record_inputs", "false", "with record: also the /testline/* streams (the file is then a contract "
                               "recording too)"),
    ("record_reliable", "false", "with record: subscribe the streams reliably (nothing lost; the replay "
                                 "then also waits for the recorder)"),
    ("view", "false", "also serve the live view to Foxglove (WebSocket; docs/live_view.md)"),
    ("view_host", "127.0.0.1", "address the live view listens on (0.0.0.0 serves other machines)"),
    ("view_port", str(VIEW_PORT), "port of the live view"),
)
# the replay's start-up gating in a launched graph: every other node up, a subscriber on every
# data topic, each at most this long (process start-up, imports and kernel compilation take a while
# on a loaded machine)
WAIT_TIMEOUT_S = 300.0
_NAMESPACE = re.compile(r"^(/[A-Za-z][A-Za-z0-9_]*)+$")


@dataclass(frozen=True)
class NodeLaunch:
    """One node of a launch: what both launchers give it."""
    name: str
    module: str                     # python -m MODULE (our launcher); the executable is ``name``
    params: dict
    namespace: str = ""             # "" or "/a/b"
    remaps: tuple = ()              # ((from, to), ...)
    params_file: str | None = None
    spec: NodeSpec | None = None


def check_namespace(namespace: str) -> str:
    """``namespace`` as a fully qualified ROS namespace ('' for none; 'line1' -> '/line1')."""
    from maglev_ros.errors import UserError
    ns = (namespace or "").strip()
    if ns in ("", "/"):
        return ""
    ns = "/" + ns.strip("/")
    if not _NAMESPACE.match(ns):
        raise UserError(f"namespace {namespace!r}: expected names of letters, digits and '_' "
                        f"(each starting with a letter) joined by '/', e.g. /line1")
    return ns


def launch_overrides(rate: float = 1.0, fast: bool = False, out: str = "out/monitor",
                     history: str | None = None) -> dict:
    """Per-node parameters of ``maglev-ros launch monitor`` / monitor.launch.py from their options."""
    hist = history or os.path.join(out, "twin_parameters.jsonl")
    # one process's \r progress bar garbles the merged output: the replay logs its summary instead
    return {"replay": {"rate": float(rate), "fast": bool(fast), "progress": False},
            "updater": {"history_path": os.path.abspath(hist)}}


def node_launches(graph_name: str, bag: str | None = None, overrides: dict | None = None,
                  params_file: str | None = None, namespace: str = "", use_sim_time: bool = False,
                  linger_s: float = 2.0, extra=(), bags: list[str] | None = None,
                  results_timeout_s: float | None = None, adapter: str | None = None,
                  metadata: str | None = None) -> list[NodeLaunch]:
    """What every node of ``graph_name`` (plus ``extra`` NodeSpecs) gets in a launch.

    The replay (only with a bag) starts when every other node of the graph is up and every data
    topic has a subscriber (at most WAIT_TIMEOUT_S each) and lingers ``linger_s`` after its end; in a
    ``namespace`` every node runs there and /clock is remapped into it; ``use_sim_time`` puts every
    node but the replay on /clock; ``overrides`` ({node: {param: value}}) come last. ``adapter`` (a
    mapping file, with ``metadata``): the DAQ adapter is the graph's source (no bag then)."""
    from maglev_ros.errors import UserError
    overrides = overrides or {}
    ns = check_namespace(namespace)
    bags = list(bags or ([bag] if bag else []))
    if bool(adapter) != bool(metadata):
        raise UserError("the DAQ adapter needs both its mapping (adapter) and the recording's metadata "
                        f"(metadata); got only {'adapter' if adapter else 'metadata'}")
    if adapter and bags:
        raise UserError("the DAQ adapter (live streams) and a replayed bag are two sources: give one")
    sources = [adapter_spec(adapter, metadata)] if adapter else []
    specs = [s for s in list(graph(graph_name)) + sources + list(extra) if bags or not s.needs_bag]
    others = [s.name for s in specs if not s.needs_bag and not s.observer]
    remaps = (("/clock", f"{ns}/clock"),) if ns else ()
    out = []
    for spec in specs:
        params = dict(spec.params)
        if spec.needs_bag:
            params["bags"] = [os.path.abspath(b) for b in bags]
            # [""]: no node to wait for (observers only); an empty list has no ROS parameter type
            params.update({"wait_nodes": others or [""], "wait_subscribers": 1, "wait_timeout_s": WAIT_TIMEOUT_S,
                           "linger_s": float(linger_s)})
            if results_timeout_s is not None:
                params["results_timeout_s"] = float(results_timeout_s)
        elif use_sim_time:
            params["use_sim_time"] = True
        if spec.takes_stream_rate and bags:
            params["stream_rate"] = _replay_rate(overrides.get("replay", {}))
        params.update(overrides.get(spec.name, {}))
        out.append(NodeLaunch(spec.name, spec.module, params, ns, remaps, params_file or None, spec))
    return out


def _replay_rate(replay_params: dict) -> float:
    """The replay's pace in bag seconds per wall second (1 when unpaced: its pace is unknown)."""
    if replay_params.get("fast"):
        return 1.0
    return float(replay_params.get("rate", 1.0))


def ros_args(nl: NodeLaunch) -> list[str]:
    """The ``--ros-args`` part of our launcher's command line for ``nl``."""
    cmd = ["--ros-args", "-r", f"__node:={nl.name}"]
    if nl.namespace:
        cmd += ["-r", f"__ns:={nl.namespace}"]
    for src, dst in nl.remaps:
        cmd += ["-r", f"{src}:={dst}"]
    if nl.params_file:
        cmd += ["--params-file", nl.params_file]
    return cmd + ros_param_args(nl.params)
