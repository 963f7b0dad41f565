"""``maglev-ros demo``: the main job on the bundled sample bag (or any bag).

Checks the recording against the contract, replays it through the monitor node graph with a
summary node counting what flows, and prints the summary. Later stages (modes, irregularity,
twin, updating, diagnosis) extend it as they land.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from maglev_ros.errors import UserError

NAME = "demo"
HELP = "run the main job on the bundled sample bag: check, replay through the graph, summarise"
ORDER = 1
SAMPLE_BAG = Path(__file__).resolve().parents[2] / "bags" / "paper_pass"


def add_arguments(p) -> None:
    p.add_argument("--bag", default=str(SAMPLE_BAG), help="recording (default: bags/paper_pass)")
    p.add_argument("--rate", type=float, default=2.0, help="replay rate through the graph")
    p.add_argument("--out", default="out/demo", help="directory for the demo's outputs")


def _check(bag: str) -> dict:
    from maglev_ros.bag_reader import BagReader
    with BagReader(bag) as r:
        issues = r.check()
        topics = {t: i.to_dict() for t, i in r.topics.items()}
        summary = {"bag": bag, "duration_s": r.duration_s, "run_kind": r.metadata.run_kind,
                   "description": r.metadata.raw.get("description", ""), "topics": topics,
                   "issues": [i.to_dict() for i in issues]}
    print(f"recording {bag}: {summary['run_kind']}, {summary['duration_s']:.1f} s"
          + (f" - {summary['description']}" if summary["description"] else ""))
    for t, i in sorted(topics.items()):
        chans = ", ".join(i.get("channels", [])[:6]) + (" ..." if len(i.get("channels", [])) > 6 else "")
        rate = f" @ {i['sample_rate_hz']:g} Hz" if i.get("sample_rate_hz") else ""
        print(f"  {t:36s} {i['count']:6d} msgs{rate}  {chans}")
    errors = [i for i in summary["issues"] if i["severity"] == "error"]
    print(f"  contract: {len(errors)} errors, {len(summary['issues']) - len(errors)} warnings")
    if errors:
        raise UserError(f"{bag}: {errors[0]['message']}")
    return summary


def run(args) -> int:
    from maglev_ros.launch_graph import NodeSpec
    from maglev_ros.launcher import launch
    from maglev_ros.replay_timing import check_rate

    if not os.path.exists(args.bag):
        raise UserError(f"{args.bag}: no such bag")
    check_rate(args.rate)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("== 1. recording and contract")
    recording = _check(args.bag)

    print(f"== 2. replay through the node graph at {args.rate:g}x")
    graph_json = out / "graph_summary.json"
    graph_json.unlink(missing_ok=True)
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    summary = NodeSpec("summary", "maglev_ros.nodes.summary",
                       params={"idle_s": 3.0, "json_out": str(graph_json.resolve())})
    code = launch("monitor", bag=args.bag, extra=[summary], env=env, linger_s=5.0,
                  overrides={"replay": {"rate": float(args.rate), "progress": False,
                                        "wait_subscribers": 1},
                             "updater": {"history_path": str((out / "twin_parameters.jsonl").resolve())}})
    if code != 0:
        raise UserError(f"replay ended with code {code}")
    if not graph_json.exists():
        raise UserError("the summary node saw no messages (is DDS on loopback blocked?)")
    flow = json.loads(graph_json.read_text())
    expected = {t: i["count"] for t, i in recording["topics"].items()}
    lost = {t: (expected[t], flow.get(t, {}).get("messages", 0)) for t in expected
            if flow.get(t, {}).get("messages", 0) != expected[t]}
    print("  every recorded message went through the graph" if not lost
          else f"  messages missing on: {lost}")
    report = {"recording": recording, "graph": flow}
    (out / "demo.json").write_text(json.dumps(report, indent=1))
    print(f"== done: {out / 'demo.json'}")
    return 0 if not lost else 1
