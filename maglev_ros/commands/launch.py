"""``maglev-ros launch GRAPH``: start the suite's node graph (our own launcher; see launch/).

The options are the launch arguments of launch/monitor.launch.py (``launch_graph.LAUNCH_ARGUMENTS``)
and both compute what each node gets with ``launch_graph.node_launches``."""
from __future__ import annotations

import os
from pathlib import Path

from maglev_ros.errors import UserError

NAME = "launch"
HELP = "start a node graph (monitor) in separate processes, optionally driven by a bag replay"
ORDER = 40


def add_arguments(p) -> None:
    from maglev_ros.launch_graph import LAUNCH_ARGUMENTS
    default = {name: value for name, value, _ in LAUNCH_ARGUMENTS}    # the launch file's defaults
    p.add_argument("graph", help="graph name: monitor")
    p.add_argument("--bag", nargs="+", metavar="BAG",
                   help="replay this bag through the graph (several: one after the other, each with "
                        "its results before the next)")
    p.add_argument("--adapter", metavar="MAPPING.yaml",
                   help="live DAQ streams instead of a replay: the DAQ adapter with this mapping "
                        "(driver topic and field -> contract channel; docs/daq_stream.md); needs --metadata")
    p.add_argument("--metadata", metavar="META.yaml",
                   help="with --adapter: the recording's metadata (the contract's document, YAML or JSON)")
    p.add_argument("--daq-sim", metavar="BAG",
                   help="demo of live streams: the DAQ simulator publishes BAG's samples as driver messages "
                        "(at --rate) and the DAQ adapter feeds them to the graph; its mapping and metadata "
                        "are written to DIR/daq (--out)")
    p.add_argument("--rate", type=float, default=float(default["rate"]), help="replay rate (0.1-100)")
    p.add_argument("--fast", action="store_true", help="replay as fast as possible")
    p.add_argument("--params-file", help="ROS 2 parameters YAML passed to every node")
    p.add_argument("--namespace", default="", metavar="NS",
                   help="run the whole graph in this ROS namespace, /clock included (two lines side "
                        "by side: /line1, /line2)")
    p.add_argument("--use-sim-time", action="store_true",
                   help="the nodes run on the replay's /clock (the replay itself on wall time)")
    p.add_argument("--out", default=default["out"], metavar="DIR",
                   help="output directory of the launch (default out/monitor): the updater's "
                        "parameter history goes there")
    p.add_argument("--history", metavar="FILE",
                   help="the updater's parameter history (default DIR/twin_parameters.jsonl); only "
                        "records of the recording's own line are loaded from it")
    p.add_argument("--record", metavar="FILE.mcap",
                   help="record the graph's /maglev/* outputs, /testline/metadata and /diagnostics "
                        "to this MCAP file (Foxglove, rosbags; finished when the graph stops)")
    p.add_argument("--record-inputs", action="store_true",
                   help="with --record: also the /testline/* streams (the file is then a contract "
                        "bag that every verb reads)")
    p.add_argument("--record-reliable", action="store_true",
                   help="with --record: subscribe the streams reliably (nothing lost; the replay "
                        "then also waits for the recorder)")
    p.add_argument("--view", action="store_true",
                   help="also serve the live view to Foxglove (WebSocket; docs/live_view.md) and print its URL")
    p.add_argument("--view-port", type=int, default=8765, metavar="N",
                   help="port of the live view (default 8765)")
    p.add_argument("--view-host", default="127.0.0.1", metavar="HOST",
                   help="address the live view listens on (default 127.0.0.1; 0.0.0.0 serves other machines)")
    p.add_argument("--linger", type=float, default=float(default["linger_s"]), metavar="S",
                   help="extra time the graph keeps running after the replay's end, which comes once "
                        "every node has published the last recording's results (default 2 s)")
    p.add_argument("--results-timeout", type=float, default=float(default["results_timeout_s"]), metavar="S",
                   help="after each recording, wait at most this long for the nodes' results (the live "
                        "diagnosis of a pass takes minutes on a busy machine; default 900 s)")


def launch_kwargs(args) -> dict:
    """The keyword arguments of ``launcher.launch`` for these options (checked; no directory made)."""
    from maglev_ros.launch_graph import check_namespace, launch_overrides
    from maglev_ros.replay_timing import check_rate
    for bag in args.bag or []:
        if not os.path.exists(bag):
            raise UserError(f"{bag}: no such bag")
    if args.params_file and not os.path.exists(args.params_file):
        raise UserError(f"{args.params_file}: no such parameters file")
    if not args.fast:
        check_rate(args.rate)
    if args.linger < 0:
        raise UserError(f"--linger: expected seconds >= 0, got {args.linger}")
    if args.results_timeout < 0:
        raise UserError(f"--results-timeout: expected seconds >= 0, got {args.results_timeout}")
    adapter, metadata = getattr(args, "adapter", None), getattr(args, "metadata", None)
    sim = getattr(args, "daq_sim", None)
    if sim and (adapter or metadata):
        raise UserError("--daq-sim writes its own mapping and metadata: give it without --adapter / --metadata")
    if sim and args.bag:
        raise UserError("--daq-sim and --bag are two sources: give one")
    if sim and not os.path.exists(sim):
        raise UserError(f"--daq-sim {sim}: no such bag")
    if bool(adapter) != bool(metadata):
        raise UserError("--adapter and --metadata: give both (the mapping and the recording's metadata)")
    if adapter and args.bag:
        raise UserError("--adapter (live streams) and --bag (a replay) are two sources: give one")
    for opt, path in (("--adapter", adapter), ("--metadata", metadata)):
        if path and not os.path.isfile(path):
            raise UserError(f"{opt} {path}: no such file")
    if adapter:
        from maglev_ros.daq_stream.mapping import load_mapping, load_metadata_file
        load_mapping(adapter, load_metadata_file(metadata))      # its mistakes before any node starts
    return dict(adapter=adapter, metadata=metadata, bags=args.bag, params_file=args.params_file, linger_s=args.linger,
                results_timeout_s=args.results_timeout,
                namespace=check_namespace(args.namespace), use_sim_time=bool(args.use_sim_time),
                overrides=launch_overrides(rate=args.rate, fast=args.fast, out=args.out, history=args.history))


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.launcher import launch
    kwargs = launch_kwargs(args)
    from maglev_ros.launch_graph import extra_nodes, view_urls
    # the verb's own flags named first; extra_nodes checks the same for monitor.launch.py
    if args.record:
        from maglev_ros.outputs import check_file
        if not args.record.endswith(".mcap"):
            raise UserError(f"--record {args.record}: expected a file name ending in .mcap")
        check_file(args.record, "--record")
    elif args.record_inputs or args.record_reliable:
        raise UserError("--record-inputs / --record-reliable: given without --record FILE.mcap")
    if args.view:
        if not 1 <= args.view_port <= 65535:
            raise UserError(f"--view-port: expected a port 1-65535, got {args.view_port}")
        import importlib.util
        if importlib.util.find_spec("foxglove") is None:
            raise UserError("--view: the live view needs foxglove-sdk, which is not installed: "
                            "pip install foxglove-sdk==0.30.3 (scripts/install does)")
    # the same nodes as monitor.launch.py's record:=/view:= arguments
    extra = extra_nodes(args.record, args.record_inputs, args.record_reliable, sim_time=bool(args.bag),
                        view=args.view, view_host=args.view_host, view_port=args.view_port)
    history = Path(kwargs["overrides"]["updater"]["history_path"])
    try:
        history.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {history.parent}: cannot create directory ({exc.strerror})") from None
    if args.daq_sim:
        from maglev_ros.daq_stream.sim import source_from_bag, write_config
        from maglev_ros.launch_graph import daq_sim_spec
        meta, mapping = write_config(source_from_bag(args.daq_sim), Path(args.out) / "daq")
        print(f"daq_sim: {args.daq_sim} as driver streams; mapping {mapping.resolve()}, metadata {meta.resolve()}",
              flush=True)
        kwargs.update(adapter=str(mapping), metadata=str(meta))
        extra.append(daq_sim_spec(args.daq_sim, rate=0.0 if args.fast else args.rate, reliable=bool(args.fast)))
    print(f"launch {args.graph}: outputs in {history.parent.resolve()}; parameter history "
          f"{history.resolve()}" + (f"; namespace {kwargs['namespace']}" if kwargs["namespace"] else "")
          + (f"; recording to {Path(args.record).resolve()}" if args.record else ""), flush=True)
    if args.view:
        app, ws = view_urls(args.view_host, args.view_port)
        layout = Path(__file__).resolve().parents[1] / "config" / "foxglove_layout.json"
        print(f"live view: open {app}\n           or connect Foxglove to {ws}; layout: {layout}", flush=True)
    return launch(args.graph, extra=extra, **kwargs)
