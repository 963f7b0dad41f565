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
    p.add_argument("--bag", nargs="+", metavar="BAG",
                   help="replay this bag through the graph (several: one after the other, each with "
                        "its results before the next)")
    p.add_argument("--rate", type=float, default=1.0, help="replay rate (0.1-100)")
    p.add_argument("--fast", action="store_true", help="replay as fast as possible")
    p.add_argument("--params-file", help="ROS 2 parameters YAML passed to every node")
    p.add_argument("--out", default="out/monitor", metavar="DIR",
                   help="output directory of the launch (default out/monitor): the updater's "
                        "parameter history goes there")
    p.add_argument("--history", metavar="FILE",
                   help="the updater's parameter history (default DIR/twin_parameters.jsonl); only "
                        "records of the recording's own line are loaded from it")
    p.add_argument("--linger", type=float, default=2.0, metavar="S",
                   help="extra time the graph keeps running after the replay's end, which comes once "
                        "every node has published the last recording's results (default 2 s)")
    p.add_argument("--results-timeout", type=float, default=900.0, metavar="S",
                   help="after each recording, wait at most this long for the nodes' results (the live "
                        "diagnosis of a pass takes minutes on a busy machine; default 900 s)")


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.launcher import launch
    from maglev_ros.replay_timing import check_rate
    for bag in args.bag or []:
        if not os.path.exists(bag):
            raise UserError(f"{bag}: no such bag")
    if args.params_file and not os.path.exists(args.params_file):
        raise UserError(f"{args.params_file}: no such parameters file")
    if not args.fast:
        check_rate(args.rate)
    # one process's \r progress bar garbles the merged output: the replay logs its summary instead
    replay = {"rate": float(args.rate), "fast": bool(args.fast), "progress": False}
    if args.linger < 0:
        raise UserError(f"--linger: expected seconds >= 0, got {args.linger}")
    if args.results_timeout < 0:
        raise UserError(f"--results-timeout: expected seconds >= 0, got {args.results_timeout}")
    history = Path(args.history) if args.history else Path(args.out) / "twin_parameters.jsonl"
    try:
        history.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {history.parent}: cannot create directory ({exc.strerror})") from None
    print(f"launch {args.graph}: outputs in {history.parent.resolve()}; parameter history "
          f"{history.resolve()}", flush=True)
    return launch(args.graph, bags=args.bag, params_file=args.params_file, linger_s=args.linger,
                  results_timeout_s=args.results_timeout,
                  overrides={"replay": replay, "updater": {"history_path": str(history.resolve())}})
