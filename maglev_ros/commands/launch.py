"""``maglev-ros launch GRAPH``: start the suite's node graph (our own launcher; see launch/)."""
from __future__ import annotations

import os
from pathlib import Path

from maglev_ros.errors import UserError

NAME = "launch"
HELP = "start a node graph (monitor) in separate processes, optionally driven by a bag replay"
ORDER = 40


def add_arguments(p) -> None:
    p.add_argument("graph", help="graph name: monitor")
    p.add_argument("--bag", help="replay this bag through the graph")
    p.add_argument("--rate", type=float, default=1.0, help="replay rate (0.1-100)")
    p.add_argument("--fast", action="store_true", help="replay as fast as possible")
    p.add_argument("--params-file", help="ROS 2 parameters YAML passed to every node")
    p.add_argument("--out", default="out/monitor", metavar="DIR",
                   help="output directory of the launch (default out/monitor): the updater's "
                        "parameter history goes there")
    p.add_argument("--history", metavar="FILE",
                   help="the updater's parameter history (default DIR/twin_parameters.jsonl); only "
                        "records of the recording's own line are loaded from it")
    p.add_argument("--view", action="store_true",
                   help="also serve the live view to Foxglove (WebSocket; docs/live_view.md) and print its URL")
    p.add_argument("--view-port", type=int, default=8765, metavar="N",
                   help="port of the live view (default 8765)")
    p.add_argument("--view-host", default="127.0.0.1", metavar="HOST",
                   help="address the live view listens on (default 127.0.0.1; 0.0.0.0 serves other machines)")
    p.add_argument("--linger", type=float, default=30.0, metavar="S",
                   help="after a finite replay ends, keep the graph running this long so the twin, "
                        "updater and discrepancy nodes can finish (default 30 s; the updater's magnet "
                        "layer may take minutes on a busy machine)")


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.launcher import launch
    from maglev_ros.replay_timing import check_rate
    if args.bag and not os.path.exists(args.bag):
        raise UserError(f"{args.bag}: no such bag")
    if args.params_file and not os.path.exists(args.params_file):
        raise UserError(f"{args.params_file}: no such parameters file")
    if not args.fast:
        check_rate(args.rate)
    # one process's \r progress bar garbles the merged output: the replay logs its summary instead
    replay = {"rate": float(args.rate), "fast": bool(args.fast), "progress": False}
    if args.linger < 0:
        raise UserError(f"--linger: expected seconds >= 0, got {args.linger}")
    history = Path(args.history) if args.history else Path(args.out) / "twin_parameters.jsonl"
    try:
        history.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {history.parent}: cannot create directory ({exc.strerror})") from None
    print(f"launch {args.graph}: outputs in {history.parent.resolve()}; parameter history "
          f"{history.resolve()}", flush=True)
    extra = []
    if args.view:
        from maglev_ros.launch_graph import view_node, view_urls
        if not 1 <= args.view_port <= 65535:
            raise UserError(f"--view-port: expected a port 1-65535, got {args.view_port}")
        import importlib.util
        if importlib.util.find_spec("foxglove") is None:
            raise UserError("--view: the live view needs foxglove-sdk, which is not installed: "
                            "pip install foxglove-sdk==0.30.3 (scripts/install does)")
        extra.append(view_node(args.view_host, args.view_port))
        app, ws = view_urls(args.view_host, args.view_port)
        layout = Path(__file__).resolve().parents[1] / "config" / "foxglove_layout.json"
        print(f"live view: open {app}\n           or connect Foxglove to {ws}; layout: {layout}", flush=True)
    return launch(args.graph, bag=args.bag, params_file=args.params_file, linger_s=args.linger,
                  overrides={"replay": replay, "updater": {"history_path": str(history.resolve())}}, extra=extra)
